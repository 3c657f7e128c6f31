"""Build the FEM soft-object library: ``assets_usd/objects/soft/*.usda`` + deformable manifest entries.

24 objects: 4 material classes (sponge, bread, plush, rubber) x 3 size bins (small 3-6 cm,
medium 6-12 cm, large 12-20 cm by longest side) x 2 shapes. One object per class is held out
as ``test`` (1 of 6 = 17% of each family), spread over the bins. Every object is a star-shaped
procedural surface (a superellipsoid, a noisy ellipsoid or a union of two ellipsoids, sampled
on an icosphere, so it is watertight by construction), decimated and tetrahedralized by fTetWild
(pytetwild, MPL-2.0) to 200-500 tets (:data:`TARGET_TETS`), and written by
:func:`d3grasp.authoring.usd_soft.write_soft_usd`.

Reproducibility: the surfaces and materials are pure functions of :data:`SPECS`; fTetWild is not
deterministic, so the build **reuses the tets committed in the existing USD files** and only
re-meshes an object when its file is missing, when its shape parameters changed (a hash of
them is stored in the file), or with ``--regenerate-tets``. Rebuilding without
``--regenerate-tets`` rewrites byte-identical files.

Materials (orders of magnitude; each class's values are spread log-evenly over its range by
object index, so the library spans 5 kPa to 1 MPa, a 200x stiffness range):

* sponge (open-cell polyurethane foam): E 10-50 kPa, nu 0.15, rho 30-80 kg/m^3. Gibson & Ashby,
  *Cellular Solids* (2nd ed., 1997), ch. 5: flexible PU foams of relative density 0.02-0.05
  have E ~ 1e4-1e5 Pa and nu ~ 0.1-0.3.
* bread (crumb): E 15-80 kPa, nu 0.25, rho 200-300 kg/m^3. Liu & Scanlon, *J. Texture
  Studies* 34 (2003): white-bread crumb E ~ 10-100 kPa at densities ~ 0.2-0.3 g/cm^3.
* plush (fibre-filled toys): E 5-30 kPa, nu 0.3, rho 100-200 kg/m^3; polyester fibrefill
  batting is softer than PU foam at a few times its density (fill ~ 15-30 kg/m^3 plus fabric and
  compression in a stuffed toy); the effective modulus is an estimate of the first-contact
  stiffness of a stuffed toy, not a measured value.
* rubber (soft silicone / natural-rubber toys): E 0.1-1 MPa, nu 0.45, rho 1000-1100 kg/m^3.
  Platinum-cure silicones (Shore 00-30 to 20A) have E ~ 0.07-1 MPa and rho ~ 1.07 g/cm^3;
  nu is held at 0.45 (not 0.5): VBD's neo-Hookean volume term stiffens without bound as nu -> 0.5.

Like the rigid library, no object weighs more than :data:`MAX_MASS` (the hand cannot lift
more): a large rubber object would otherwise reach ~1 kg, so its density is lowered (a hollow or
foam-cored toy) and the manifest records both ``density`` (used) and ``nominal_density``.

Damping (``material["damping"]``, Pa s): Newton's VBD tet damping is a viscosity on the rate of
the Green strain, so it is set as ``E * tau`` with a class time constant ``tau`` (foams and
bread are lossy, rubber is not). Newton does not read it from USD; the environment writes it
into ``model.tet_materials[:, 2]`` after loading.

Run: ``python tools/build_soft_objects.py [--out assets_usd] [--regenerate-tets]``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from a checkout without installing
    sys.path.insert(0, str(REPO))

from d3grasp.authoring.manifest import SIZE_BINS, AssetEntry, install_built_assets, size_bin_of  # noqa: E402
from d3grasp.authoring.tetmesh import rest_volume_and_mass, surface_faces, tetrahedralize  # noqa: E402
from d3grasp.authoring.usd_soft import read_soft_usd, write_soft_usd  # noqa: E402

SOFT_DIR = "objects/soft"
MAX_MASS = 0.5  # kg, the same cap as the rigid library
# Tets per size bin, and the share of the generated surface's faces kept before meshing. 200 / 250 /
# 400 tets on surfaces decimated to an eighth (since 2026-12-04; before, 300 / 500 / 800 on the full
# surfaces): 54% of the tets, a soft evaluation in 0.71x the time, and under a plate's weight
# (tools/soft_plate_test.py) a compression within 10% of a 2.5x finer mesh for 19 of the 24 objects
# against 20 with the old budgets (docs/design.md, Where a soft step's time goes).
TARGET_TETS = {"small": 200, "medium": 250, "large": 400}
SURFACE_DECIMATION = (8, 6, 4, 2)  # keep 1/k of the faces, the first k that stays closed
# Recommended contact radius of the tet nodes (m): Newton takes none from USD and defaults to
# 0.1 m, which explodes a 5 cm object. A few millimetres keeps the visual gap to the ground
# small while staying below half the smallest edge of the coarsest surface.
PARTICLE_RADIUS = 0.003


@dataclass(frozen=True)
class MaterialClass:
    youngs_modulus: tuple[float, float]  # Pa, range spread over the class's objects
    poissons_ratio: float
    density: tuple[float, float]  # kg/m^3
    damping_tau: float  # s; damping = E * tau (Pa s)
    friction: float  # recorded only; Newton's soft contact friction is model.soft_contact_mu
    color: tuple[float, float, float]


CLASSES: dict[str, MaterialClass] = {
    "sponge": MaterialClass((1.0e4, 5.0e4), 0.15, (30.0, 80.0), 2e-3, 1.0, (0.95, 0.85, 0.3)),
    "bread": MaterialClass((1.5e4, 8.0e4), 0.25, (200.0, 300.0), 2e-3, 0.8, (0.85, 0.6, 0.3)),
    "plush": MaterialClass((5.0e3, 3.0e4), 0.3, (100.0, 200.0), 2e-3, 0.9, (0.7, 0.45, 0.8)),
    "rubber": MaterialClass((1.0e5, 1.0e6), 0.45, (1000.0, 1100.0), 2e-3, 1.0, (0.9, 0.2, 0.15)),
}


@dataclass(frozen=True)
class Spec:
    """One object: its shape recipe and where it sits in its class."""

    asset_id: str
    family: str  # material class
    shape: str  # key of SHAPES
    dims: tuple[float, float, float]  # bounding-box side lengths (m) before meshing
    params: dict[str, float] = field(default_factory=dict)
    split: str = "train"
    seed: int = 0

    def shape_hash(self) -> str:
        """Hash of everything that determines the surface; stored in the USD to detect stale tets."""
        doc = {"shape": self.shape, "dims": self.dims, "params": self.params, "seed": self.seed}
        blob = json.dumps(doc, sort_keys=True).encode() + str(TARGET_TETS).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


# --------------------------------------------------------------------------------------------
# Star-shaped surfaces: r(direction) on an icosphere, so every surface is closed and consistently
# wound by construction (the icosphere's topology, every vertex moved along its own ray).


def _radial_mesh(radius_of: Callable[[np.ndarray], np.ndarray], subdivisions: int = 4) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    d = sphere.vertices / np.linalg.norm(sphere.vertices, axis=1, keepdims=True)
    r = radius_of(d)
    if not np.all(np.isfinite(r)) or r.min() <= 0:
        raise RuntimeError("radial shape function must be finite and positive")
    return trimesh.Trimesh(d * r[:, None], sphere.faces.copy(), process=False)


def _superellipsoid_r(d: np.ndarray, abc: np.ndarray, e1: float, e2: float) -> np.ndarray:
    """Distance along unit rays ``d`` to the superellipsoid ``(|x/a|^(2/e2) + |y/b|^(2/e2))^(e2/e1)
    + |z/c|^(2/e1) = 1``; the inside-outside function is homogeneous of degree 2/e1 in the ray
    parameter, so the hit is at ``F(d)^(-e1/2)``."""
    q = np.abs(d) / abc
    f = (q[:, 0] ** (2 / e2) + q[:, 1] ** (2 / e2)) ** (e2 / e1) + q[:, 2] ** (2 / e1)
    return f ** (-e1 / 2)


def _ellipsoid_exit(d: np.ndarray, center: np.ndarray, abc: np.ndarray) -> np.ndarray:
    """Far intersection distance of rays from the origin with an ellipsoid (0 where missed)."""
    u = d / abc
    c = -center / abc
    a = np.sum(u * u, axis=1)
    b = -2.0 * (u @ c)
    cc = float(c @ c) - 1.0
    disc = b * b - 4 * a * cc
    t = (-b + np.sqrt(np.maximum(disc, 0.0))) / (2 * a)
    return np.where(disc > 0, np.maximum(t, 0.0), 0.0)


def shape_superellipsoid(spec: Spec, rng: np.random.Generator) -> trimesh.Trimesh:
    """Rounded boxes (sponges), loaves and pillows (small e1, e2: boxy; 1: ellipsoidal)."""
    e1, e2 = spec.params["e1"], spec.params["e2"]
    return _radial_mesh(lambda d: _superellipsoid_r(d, np.ones(3), e1, e2))


def shape_blob(spec: Spec, rng: np.random.Generator) -> trimesh.Trimesh:
    """A sphere with a few seeded low-frequency bumps (plush toys, dough-like lumps)."""
    amp = spec.params.get("amp", 0.12)
    k = int(spec.params.get("lobes", 4))
    axes = rng.normal(size=(k, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    weights = rng.uniform(0.5, 1.0, size=k) * amp / k * 2.0
    widths = rng.uniform(2.0, 4.0, size=k)

    def r(d: np.ndarray) -> np.ndarray:
        bumps = sum(w * np.exp(widths[i] * (d @ axes[i] - 1.0)) for i, w in enumerate(weights))
        return 1.0 + bumps

    return _radial_mesh(r)


def shape_two_ellipsoids(spec: Spec, rng: np.random.Generator) -> trimesh.Trimesh:
    """Body + head (rubber duck, plush teddy): the union of two ellipsoids, star-shaped about the
    body centre as long as the head overlaps the body (the rays' far exits are taken)."""
    p = spec.params
    body = np.array([1.0, p.get("body_y", 0.7), p.get("body_z", 0.6)])
    head_c = np.array([p.get("head_x", 0.55), 0.0, p.get("head_z", 0.55)])
    head = np.full(3, p.get("head_r", 0.42))

    def r(d: np.ndarray) -> np.ndarray:
        return np.maximum(_ellipsoid_exit(d, np.zeros(3), body), _ellipsoid_exit(d, head_c, head))

    return _radial_mesh(r)


SHAPES: dict[str, Callable[[Spec, np.random.Generator], trimesh.Trimesh]] = {
    "superellipsoid": shape_superellipsoid,
    "blob": shape_blob,
    "two_ellipsoids": shape_two_ellipsoids,
}


def _s(
    asset_id: str,
    family: str,
    shape: str,
    dims_cm: tuple[float, float, float],
    split: str = "train",
    **params: float,
) -> Spec:
    seed = int(hashlib.sha256(asset_id.encode()).hexdigest()[:8], 16)
    return Spec(asset_id, family, shape, tuple(x / 100.0 for x in dims_cm), dict(params), split, seed)  # type: ignore[arg-type]


SB, BL, TE = "superellipsoid", "blob", "two_ellipsoids"
# Dimensions in cm (x, y, z). Longest sides sit inside their bins with >= 0.5 cm margin, since
# fTetWild's envelope moves the surface by up to ~1% of the diagonal.
SPECS: list[Spec] = [
    # sponges: rounded blocks
    _s("sponge_cube_s", "sponge", SB, (4.5, 4.0, 3.0), e1=0.2, e2=0.2),
    _s("sponge_bar_s", "sponge", SB, (5.5, 3.5, 2.5), e1=0.25, e2=0.2),
    _s("sponge_kitchen_m", "sponge", SB, (10.0, 7.0, 3.0), "test", e1=0.2, e2=0.2),
    _s("sponge_block_m", "sponge", SB, (8.0, 6.0, 4.5), e1=0.3, e2=0.3),
    _s("sponge_bath_l", "sponge", SB, (15.0, 10.0, 5.0), e1=0.35, e2=0.4),
    _s("sponge_slab_l", "sponge", SB, (13.0, 9.0, 6.0), e1=0.2, e2=0.25),
    # bread: rolls, buns, loaves
    _s("bread_roll_s", "bread", SB, (5.5, 4.0, 3.5), e1=0.8, e2=0.9),
    _s("bread_bun_s", "bread", SB, (5.0, 5.0, 3.0), e1=0.6, e2=1.0),
    _s("bread_roll_m", "bread", SB, (11.0, 6.0, 5.0), e1=0.7, e2=0.8),
    _s("bread_bun_m", "bread", SB, (9.0, 9.0, 5.5), e1=0.6, e2=1.0),
    _s("bread_loaf_l", "bread", SB, (18.0, 10.0, 9.0), "test", e1=0.4, e2=0.3),
    _s("bread_baguette_l", "bread", SB, (19.0, 6.5, 5.5), e1=0.8, e2=0.6),
    # plush: lumpy blobs, teddy-like body + head, pillows
    _s("plush_blob_s", "plush", BL, (5.0, 4.0, 4.0), "test", amp=0.15, lobes=4),
    _s("plush_teddy_s", "plush", TE, (5.5, 3.5, 4.0), head_x=0.6, head_z=0.45, head_r=0.45),
    _s("plush_teddy_m", "plush", TE, (10.0, 7.0, 8.0), head_x=0.6, head_z=0.5, head_r=0.45),
    _s("plush_blob_m", "plush", BL, (9.0, 8.0, 6.0), amp=0.2, lobes=5),
    _s("plush_pillow_l", "plush", SB, (18.0, 12.0, 6.0), e1=0.6, e2=0.5),
    _s("plush_blob_l", "plush", BL, (15.0, 12.0, 10.0), amp=0.2, lobes=6),
    # rubber: balls, pucks, ducks
    _s("rubber_ball_s", "rubber", SB, (4.5, 4.5, 4.5), e1=1.0, e2=1.0),
    _s("rubber_puck_s", "rubber", SB, (5.0, 5.0, 2.0), e1=0.3, e2=1.0),
    _s("rubber_ball_m", "rubber", SB, (7.0, 7.0, 7.0), "test", e1=1.0, e2=1.0),
    _s("rubber_duck_m", "rubber", TE, (9.0, 6.0, 7.5), head_x=0.6, head_z=0.6, head_r=0.45),
    _s("rubber_ball_l", "rubber", SB, (12.5, 12.5, 12.5), e1=1.0, e2=1.0),
    _s("rubber_duck_l", "rubber", TE, (14.0, 9.0, 11.0), head_x=0.6, head_z=0.6, head_r=0.45),
]


def make_surface(spec: Spec) -> trimesh.Trimesh:
    """The closed surface of ``spec``: generated in unit size, scaled to ``dims``, centred."""
    rng = np.random.default_rng(spec.seed)
    m = SHAPES[spec.shape](spec, rng)
    m.apply_translation(-0.5 * (m.bounds[0] + m.bounds[1]))
    m.apply_scale(np.asarray(spec.dims) / m.extents)
    m = trimesh.Trimesh(m.vertices, m.faces, process=True)
    if not m.is_watertight or not m.is_winding_consistent or m.volume <= 0:
        raise RuntimeError(f"{spec.asset_id}: generator made an open or inverted surface")
    return m


def meshing_surface(spec: Spec) -> trimesh.Trimesh:
    """The surface fTetWild meshes: :func:`make_surface` with 1/k of its faces (quadric decimation),
    the first k of :data:`SURFACE_DECIMATION` that leaves it closed and consistently wound; the full
    surface when none does."""
    full = make_surface(spec)
    for k in SURFACE_DECIMATION:
        m = full.simplify_quadric_decimation(face_count=len(full.faces) // k)
        if m.is_watertight and m.is_winding_consistent:
            return m
    return full


def material_for(spec: Spec, volume: float) -> dict[str, float | str]:
    """The spec's material: class values spread log-evenly over the class range by object index."""
    cls = CLASSES[spec.family]
    members = [s.asset_id for s in SPECS if s.family == spec.family]
    f = members.index(spec.asset_id) / max(len(members) - 1, 1)
    e = math.exp(math.log(cls.youngs_modulus[0]) * (1 - f) + math.log(cls.youngs_modulus[1]) * f)
    e = float(f"{e:.3g}")  # round so the manifest reads cleanly; still exact in float32
    nominal = round(cls.density[0] + f * (cls.density[1] - cls.density[0]), 1)
    density = min(nominal, math.floor(MAX_MASS / volume))
    return {
        "class": spec.family,
        "youngs_modulus": e,
        "poissons_ratio": cls.poissons_ratio,
        "density": float(density),
        "nominal_density": float(nominal),
        "damping": float(f"{e * cls.damping_tau:.3g}"),
        "friction": cls.friction,
    }


def _stored_hash(path: Path) -> str | None:
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    prim = stage.GetDefaultPrim() if stage else None
    if not prim:
        return None
    data = prim.GetCustomDataByKey("d3grasp:shape_hash")
    return str(data) if data is not None else None


def build_one(spec: Spec, tmp: Path, committed: Path, regenerate_tets: bool) -> AssetEntry:
    """Mesh (or reuse) one object, write it into ``tmp``, return its manifest entry."""
    rel = f"{SOFT_DIR}/{spec.asset_id}.usda"
    old = committed / rel
    h = spec.shape_hash()
    if old.exists() and not regenerate_tets and _stored_hash(old) == h:
        got = read_soft_usd(old)
        points, tets = got["points"], got["tets"]
        source_note = "tets reused"
    else:
        points, tets = tetrahedralize(meshing_surface(spec), TARGET_TETS[_bin_of_spec(spec)])
        source_note = "tets regenerated"
    volume = rest_volume_and_mass(points, tets, 1.0)[0]
    material = material_for(spec, volume)
    extents = [float(x) for x in points.max(axis=0) - points.min(axis=0)]
    size_bin = size_bin_of(max(extents))
    if size_bin != _bin_of_spec(spec):
        raise RuntimeError(f"{spec.asset_id}: meshed size {max(extents):.4f} m left bin {_bin_of_spec(spec)}")
    write_soft_usd(
        tmp / rel,
        points,
        tets,
        material,
        name=spec.asset_id,
        color=CLASSES[spec.family].color,
        doc=f"d3grasp soft object {spec.asset_id} ({spec.family}, {spec.shape}); "
        "built by tools/build_soft_objects.py, tets by fTetWild (pytetwild).",
        custom_data={"d3grasp:shape_hash": h},
    )
    _, mass = rest_volume_and_mass(points, tets, float(material["density"]))
    return AssetEntry(
        id=spec.asset_id,
        path=rel,
        kind="deformable",
        family=spec.family,
        size_bin=size_bin,
        extents=extents,
        mass=mass,
        volume=volume,
        material=material,
        split=spec.split,  # type: ignore[arg-type]
        stats={
            "num_tets": int(len(tets)),
            "num_nodes": int(len(points)),
            "num_surface_triangles": int(len(surface_faces(tets))),
            "particle_radius": PARTICLE_RADIUS,
        },
        source=f"procedural:{spec.shape} seed={spec.seed} params={json.dumps(spec.params, sort_keys=True)}; "
        f"fTetWild ({source_note})",
    )


def _bin_of_spec(spec: Spec) -> str:
    return size_bin_of(max(spec.dims))


def build(out_root: Path, regenerate_tets: bool = False, *, progress: bool = True) -> list[AssetEntry]:
    """Rebuild ``out_root/objects/soft/`` and the deformable entries of ``out_root/manifest.json``.

    Reuses the tets committed under ``out_root`` unless ``regenerate_tets`` (see the module
    docstring). Writes into a temporary directory and replaces the old files only when every
    object succeeded.
    """
    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".soft-build-", dir=out_root))
    try:
        entries = []
        for i, spec in enumerate(SPECS):
            t0 = time.perf_counter()
            entries.append(build_one(spec, tmp, out_root, regenerate_tets))
            if progress:
                e = entries[-1]
                print(
                    f"[{i + 1:2d}/{len(SPECS)}] {e.id:18s} {e.size_bin:6s} {e.stats['num_tets']:4d} tets "
                    f"{e.stats['num_nodes']:4d} nodes {e.mass * 1e3:6.1f} g "
                    f"E {e.material['youngs_modulus']:.3g} Pa ({time.perf_counter() - t0:.1f} s)",
                    flush=True,
                )
        install_built_assets(tmp, out_root, SOFT_DIR, entries, kind="deformable")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return entries


def summary(entries: list[AssetEntry]) -> str:
    lines = []
    for fam in CLASSES:
        es = [e for e in entries if e.family == fam]
        bins = {b: sum(e.size_bin == b for e in es) for b in SIZE_BINS}
        young = [e.material["youngs_modulus"] for e in es]
        lines.append(
            f"{fam:7s} n={len(es)} bins={bins} test={sum(e.split == 'test' for e in es)} "
            f"E {min(young):.3g}-{max(young):.3g} Pa "
            f"mass {min(e.mass for e in es) * 1e3:.0f}-{max(e.mass for e in es) * 1e3:.0f} g"
        )
    tets = np.array([e.stats["num_tets"] for e in entries])
    nodes = np.array([e.stats["num_nodes"] for e in entries])
    es = [e.material["youngs_modulus"] for e in entries]
    lines.append(
        f"total {len(entries)}; tets min/median/max {tets.min()}/{int(np.median(tets))}/{tets.max()}; "
        f"nodes {nodes.min()}/{int(np.median(nodes))}/{nodes.max()}; stiffness span {max(es) / min(es):.0f}x"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=REPO / "assets_usd", help="library root (default: assets_usd/)"
    )
    ap.add_argument(
        "--regenerate-tets", action="store_true", help="re-mesh every object (fTetWild is not deterministic)"
    )
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    entries = build(args.out, regenerate_tets=args.regenerate_tets)
    print(summary(entries))
    size = sum(p.stat().st_size for p in (args.out / SOFT_DIR).glob("*.usda"))
    print(f"built in {time.perf_counter() - t0:.1f} s; {size / 1e6:.2f} MB on disk")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
