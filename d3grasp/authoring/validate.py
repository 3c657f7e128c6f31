"""Load every asset of a library in Newton and check that it reads back as the manifest says.

This is the end-to-end check of the asset pipeline: the numbers compared here come from the
manifest (computed at authoring time with trimesh / NumPy), the values checked against them are
what Newton's USD importer produced. Rigid: one body, one collision shape per hull, the authored
mass, friction and a positive-definite inertia. Deformable: particle and tet counts, the Lamé
parameters k_mu = E/2(1+nu) and k_lambda = E nu/((1+nu)(1-2nu)) on every tet, and total particle
mass = density x volume. The hand (when present) must load with positive, finite masses.

Each asset loads into its own ``ModelBuilder`` (no ``finalize``): that reads exactly what the
importer produced without compiling simulation kernels, so a whole library checks in seconds.
"""

from __future__ import annotations

import io
import math
import re
from collections.abc import Callable, Iterable
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from d3grasp.authoring.manifest import SIZE_BINS, AssetEntry, read_manifest, resolve_asset_path, size_bin_of

MASS_RTOL = 1e-4  # float32 storage in USD and in Newton
MATERIAL_RTOL = 1e-4
SOFT_MASS_RTOL = 1e-3  # per-particle float32 sums


@dataclass
class AssetCheck:
    """The outcome of checking one asset: named checks (pass/fail) and what was read back."""

    id: str
    kind: str
    size_bin: str
    path: str
    checks: dict[str, bool] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)
    readback: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.errors and all(self.checks.values())

    def check(self, name: str, ok: bool, detail: str) -> None:
        self.checks[name] = bool(ok)
        if not ok:
            self.errors.append(f"{self.path}: {name}: {detail}")


@dataclass
class ValidationReport:
    manifest: Path
    assets: list[AssetCheck]
    hand: AssetCheck | None = None
    library_errors: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return (
            not self.library_errors and all(a.ok for a in self.assets) and (self.hand is None or self.hand.ok)
        )

    def failures(self) -> list[str]:
        out = list(self.library_errors)
        for a in [*self.assets, *([self.hand] if self.hand else [])]:
            out += a.errors
        return out

    def table(self) -> str:
        """Summary: counts by kind x size bin, statistics, and PASS/FAIL per check."""
        lines = [f"manifest: {self.manifest}"]
        bins = list(SIZE_BINS)
        kinds = sorted({a.kind for a in self.assets})
        head = f"{'kind':<12}" + "".join(f"{b:>8}" for b in bins) + f"{'total':>8}{'train':>7}{'test':>6}"
        lines += [head, "-" * len(head)]
        for k in kinds:
            ak = [a for a in self.assets if a.kind == k]
            counts = "".join(f"{sum(a.size_bin == b for a in ak):>8}" for b in bins)
            n_test = sum(a.readback.get("split") == "test" for a in ak)
            lines.append(f"{k:<12}{counts}{len(ak):>8}{len(ak) - n_test:>7}{n_test:>6}")
        lines.append("")
        rigid = [a for a in self.assets if a.kind == "rigid" and "mass" in a.readback]
        if rigid:
            hulls = [a.readback["num_hulls"] for a in rigid]
            masses = [a.readback["mass"] for a in rigid]
            fams = {a.readback.get("family") for a in rigid}
            lines.append(
                f"rigid: {len(rigid)} objects, {len(fams)} families, hulls/object {min(hulls)}-{max(hulls)} "
                f"(mean {np.mean(hulls):.1f}), mass {min(masses) * 1e3:.1f}-{max(masses) * 1e3:.1f} g"
            )
        soft = [a for a in self.assets if a.kind == "deformable" and "mass" in a.readback]
        if soft:
            tets = [a.readback["num_tets"] for a in soft]
            masses = [a.readback["mass"] for a in soft]
            lines.append(
                f"deformable: {len(soft)} objects, tets/object {min(tets)}-{max(tets)}, "
                f"mass {min(masses) * 1e3:.1f}-{max(masses) * 1e3:.1f} g"
            )
        if self.hand is not None:
            r = self.hand.readback
            lines.append(
                f"hand: {self.hand.path}: bodies {r.get('bodies', '?')}, joints {r.get('joints', '?')}, "
                f"shapes {r.get('shapes', '?')}, mass {r.get('mass', float('nan')):.3f} kg"
            )
        lines.append("")
        names: list[str] = []
        for a in [*self.assets, *([self.hand] if self.hand else [])]:
            for n in a.checks:
                if n not in names:
                    names.append(n)
        lines.append(f"{'check':<28}{'passed':>8}{'failed':>8}  result")
        everything = [*self.assets, *([self.hand] if self.hand else [])]
        for n in names:
            passed = sum(1 for a in everything if a.checks.get(n) is True)
            failed = sum(1 for a in everything if a.checks.get(n) is False)
            lines.append(f"{n:<28}{passed:>8}{failed:>8}  {'PASS' if failed == 0 else 'FAIL'}")
        for e in self.library_errors:
            lines.append(f"{'library':<28}{'':>8}{'':>8}  FAIL: {e}")
        lines.append("")
        lines.append("RESULT: " + ("PASS" if self.ok else f"FAIL ({len(self.failures())} problems)"))
        return "\n".join(lines)


def _close(a: float, b: float, rtol: float) -> bool:
    return math.isfinite(a) and math.isfinite(b) and abs(a - b) <= rtol * max(abs(a), abs(b), 1e-12)


def _usd_error_reason(text: str) -> str:
    """The useful part of a USD parser error (its messages carry C++ template names)."""
    m = re.search(r":(\d+):(\d+): ([A-Za-z ]*error)", text)
    if m:
        return f"{m.group(3)} at line {m.group(1)}, column {m.group(2)}"
    quoted = re.findall(r": '([^'\n]*)'", text)
    return quoted[-1][:160] if quoted else "cannot be parsed"


def _open_stage_checked(path: Path) -> None:
    """Raise ``ValueError('<file>: ...')`` when ``path`` is not a readable USD stage."""
    from pxr import Tf, Usd

    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise ValueError(f"{path}: malformed USD ({_usd_error_reason(str(exc))})") from None
    if stage is None:
        raise ValueError(f"{path}: malformed USD (could not open stage)")
    if not stage.GetDefaultPrim():
        raise ValueError(f"{path}: malformed USD (no default prim)")


def _load(path: Path):
    """A ModelBuilder holding the single asset at ``path`` (importer chatter silenced)."""
    import newton

    _open_stage_checked(path)
    builder = newton.ModelBuilder()
    sink = io.StringIO()
    try:
        with redirect_stdout(sink), redirect_stderr(sink):
            builder.add_usd(str(path))
    except Exception as exc:
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ValueError(f"{path}: Newton failed to load it ({msg[:160]})") from None
    return builder


def _check_rigid(builder, entry: AssetEntry, res: AssetCheck) -> None:
    from newton import ShapeFlags

    res.check("rigid: body count = 1", builder.body_count == 1, f"{builder.body_count} bodies")
    colliders = [
        i for i in range(builder.shape_count) if builder.shape_flags[i] & int(ShapeFlags.COLLIDE_SHAPES)
    ]
    n_hulls = int(entry.stats.get("num_hulls", -1))
    res.check(
        "rigid: colliders = hulls",
        len(colliders) == n_hulls,
        f"{len(colliders)} colliders, manifest {n_hulls}",
    )
    mass = float(builder.body_mass[0]) if builder.body_count else float("nan")
    res.check(
        "rigid: mass read-back", _close(mass, entry.mass, MASS_RTOL), f"{mass} kg, manifest {entry.mass} kg"
    )
    rho = float(entry.material.get("density", float("nan")))
    res.check(
        "mass = density x volume",
        _close(entry.mass, rho * entry.volume, 1e-6),
        f"manifest mass {entry.mass} != {rho} x {entry.volume}",
    )
    if builder.body_count:
        inertia = np.array(builder.body_inertia[0], dtype=np.float64).reshape(3, 3)
        eig = (
            np.linalg.eigvalsh(0.5 * (inertia + inertia.T))
            if np.all(np.isfinite(inertia))
            else [float("nan")]
        )
        res.check("rigid: inertia pos. definite", bool(np.all(np.asarray(eig) > 0)), f"eigenvalues {eig}")
    mu = float(entry.material.get("friction", float("nan")))
    mus = [float(builder.shape_material_mu[i]) for i in colliders]
    res.check(
        "material: friction",
        bool(mus) and all(_close(m, mu, MATERIAL_RTOL) for m in mus),
        f"collider friction {sorted(set(round(m, 4) for m in mus))}, manifest {mu}",
    )
    res.readback.update(mass=mass, num_hulls=len(colliders))


def _check_soft(builder, entry: AssetEntry, res: AssetCheck) -> None:
    n_nodes, n_tets = int(entry.stats.get("num_nodes", -1)), int(entry.stats.get("num_tets", -1))
    res.check(
        "soft: particle count", builder.particle_count == n_nodes, f"{builder.particle_count} vs {n_nodes}"
    )
    res.check("soft: tet count", builder.tet_count == n_tets, f"{builder.tet_count} vs {n_tets}")
    E = float(entry.material.get("youngs_modulus", float("nan")))
    nu = float(entry.material.get("poissons_ratio", float("nan")))
    k_mu = E / (2.0 * (1.0 + nu))
    k_lambda = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    mats = np.asarray(builder.tet_materials, dtype=np.float64).reshape(-1, 3)
    ok_mu = mats.size > 0 and np.allclose(mats[:, 0], k_mu, rtol=MATERIAL_RTOL, atol=0)
    ok_la = mats.size > 0 and np.allclose(mats[:, 1], k_lambda, rtol=MATERIAL_RTOL, atol=0)
    res.check("material: k_mu", bool(ok_mu), f"k_mu {mats[:1, 0]} vs E/2(1+nu) = {k_mu}")
    res.check("material: k_lambda", bool(ok_la), f"k_lambda {mats[:1, 1]} vs {k_lambda}")
    mass = float(np.sum(builder.particle_mass))
    rho = float(entry.material.get("density", float("nan")))
    res.check(
        "soft: mass = density x vol",
        _close(mass, rho * entry.volume, SOFT_MASS_RTOL),
        f"particle mass {mass} kg vs {rho} x {entry.volume} m^3",
    )
    res.check(
        "soft: mass read-back", _close(mass, entry.mass, SOFT_MASS_RTOL), f"{mass} vs manifest {entry.mass}"
    )
    res.readback.update(mass=mass, num_tets=builder.tet_count, num_nodes=builder.particle_count)


def validate_entry(manifest_path: str | Path, entry: AssetEntry) -> AssetCheck:
    """Load one manifest entry in Newton and compare what it reads back with the manifest."""
    path = resolve_asset_path(manifest_path, entry)
    res = AssetCheck(entry.id, entry.kind, entry.size_bin, str(path))
    res.readback.update(split=entry.split, family=entry.family)
    try:
        expected_bin = size_bin_of(max(entry.extents))
    except ValueError as exc:
        expected_bin = f"none ({exc})"
    res.check(
        "size bin matches extents", expected_bin == entry.size_bin, f"{entry.size_bin} vs {expected_bin}"
    )
    try:
        builder = _load(path)
    except ValueError as exc:
        res.checks["loads in Newton"] = False
        res.errors.append(str(exc))
        return res
    res.checks["loads in Newton"] = True
    if entry.kind == "rigid":
        _check_rigid(builder, entry, res)
    elif entry.kind == "deformable":
        _check_soft(builder, entry, res)
    else:
        res.errors.append(f"{path}: unknown asset kind '{entry.kind}'")
    return res


def validate_hand(path: str | Path) -> AssetCheck:
    """Load the hand USD and check it is a multi-body articulation with sane masses."""
    path = Path(path)
    res = AssetCheck("hand", "hand", "-", str(path))
    try:
        b = _load(path)
    except ValueError as exc:
        res.checks["hand: loads in Newton"] = False
        res.errors.append(str(exc))
        return res
    res.checks["hand: loads in Newton"] = True
    masses = np.asarray(b.body_mass, dtype=np.float64)
    res.check("hand: loads as articulation", b.body_count > 1 and b.joint_count > 1, f"{b.body_count} bodies")
    res.check(
        "hand: masses positive",
        masses.size > 0 and bool(np.all((masses > 0) & np.isfinite(masses))),
        f"{masses}",
    )
    res.readback.update(
        bodies=b.body_count, joints=b.joint_count, shapes=b.shape_count, mass=float(masses.sum())
    )
    return res


def validate_library(
    manifest_path: str | Path | None = None,
    *,
    hand: str | Path | None | bool = True,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
) -> ValidationReport:
    """Validate every asset of a manifest (default: the shipped library).

    ``hand``: ``True`` checks ``hands/dexhand13.usda`` next to the manifest when it exists, a
    path checks that file, ``False``/``None`` skips the hand. A manifest that cannot be read
    raises ``ValueError``/``FileNotFoundError`` naming the file.
    """
    from d3grasp.paths import default_manifest

    mpath = Path(manifest_path) if manifest_path is not None else default_manifest()
    if mpath.is_dir():
        mpath = mpath / "manifest.json"
    entries = read_manifest(mpath)
    report = ValidationReport(mpath.resolve(), [])
    if not entries:
        report.library_errors.append(f"{mpath}: manifest lists no assets")
    ids = [e.id for e in entries]
    if len(set(ids)) != len(ids):
        report.library_errors.append(f"{mpath}: duplicate asset ids")
    items: Iterable[AssetEntry] = progress(entries) if progress else entries
    for e in items:
        report.assets.append(validate_entry(mpath, e))
    if hand is True:
        hp = mpath.parent / "hands" / "dexhand13.usda"
        if hp.exists():
            report.hand = validate_hand(hp)
    elif hand:
        report.hand = validate_hand(hand)
    return report
