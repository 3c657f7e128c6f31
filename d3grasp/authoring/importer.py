"""Turning meshes into library assets: the logic behind ``d3grasp-assets import``.

:func:`author_rigid` and :func:`author_soft` write one asset and return its manifest entry; the
procedural library builders in ``tools/`` use them too, so imported and shipped assets have the
same form. :func:`import_meshes` checks every input first, writes into a temporary directory and
moves the result into place only when every mesh succeeded, so a failure leaves no partial
output behind (or, asked to skip invalid meshes, writes the rest and lists what it refused).
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from d3grasp.authoring.convex import MAX_HULL_VERTICES, MAX_HULLS, convex_decompose
from d3grasp.authoring.manifest import AssetEntry, read_manifest, size_bin_of, write_manifest
from d3grasp.authoring.meshcheck import MeshError, load_and_check
from d3grasp.authoring.usd_rigid import mass_properties, write_rigid_usd
from d3grasp.parallel import run_units

# Defaults for imported meshes: a hard plastic for rigid objects, a foam for soft ones.
DEFAULT_RIGID_DENSITY = 1000.0  # kg/m^3
DEFAULT_RIGID_FRICTION = 0.8
DEFAULT_SOFT_DENSITY = 200.0  # kg/m^3, polyurethane foam class
DEFAULT_YOUNGS_MODULUS = 5.0e4  # Pa, soft sponge
DEFAULT_POISSONS_RATIO = 0.3
DEFAULT_SOFT_FRICTION = 1.0
DEFAULT_TARGET_TETS = 800
# Visual meshes above this many triangles are decimated (when fast-simplification is present)
# to keep asset files small; collision uses hulls and does not depend on it.
MAX_VISUAL_FACES = 4000

RIGID_DIR = "objects/rigid"
SOFT_DIR = "objects/soft"


def asset_id_from_name(name: str) -> str:
    """A valid USD prim name / manifest id from a file stem: ``"My mug (2)"`` -> ``"my_mug_2"``."""
    s = re.sub(r"[^0-9a-zA-Z_]+", "_", name).strip("_").lower()
    if not s:
        s = "asset"
    if s[0].isdigit():
        s = "m_" + s
    return s


def centered(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Copy of ``mesh`` translated so its bounding-box centre is the origin (the body origin)."""
    m = mesh.copy()
    m.apply_translation(-0.5 * (m.bounds[0] + m.bounds[1]))
    return m


def _visual_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    if len(mesh.faces) <= MAX_VISUAL_FACES:
        return mesh
    try:
        import fast_simplification
    except ImportError:
        return mesh
    v, f = fast_simplification.simplify(
        np.asarray(mesh.vertices, dtype=np.float32),
        np.asarray(mesh.faces, dtype=np.int32),
        target_reduction=1.0 - MAX_VISUAL_FACES / len(mesh.faces),
    )
    return trimesh.Trimesh(v, f, process=True)


def author_rigid(
    mesh: trimesh.Trimesh,
    root: str | Path,
    asset_id: str,
    *,
    family: str,
    density: float,
    friction: float,
    split: str = "train",
    source: str = "",
    coacd_threshold: float = 0.08,
    max_hulls: int = MAX_HULLS,
    max_hull_vertices: int = MAX_HULL_VERTICES,
    seed: int = 0,
    color: tuple[float, float, float] = (0.7, 0.6, 0.5),
    extra_material: dict[str, Any] | None = None,
) -> AssetEntry:
    """Write ``root/objects/rigid/<asset_id>.usda`` from a checked mesh; return its entry.

    Mass properties come from the closed surface at ``density``; an open surface (allowed for
    rigid imports) takes its volume from the collision hulls instead, which is what the
    simulator collides with.
    """
    root = Path(root)
    m = centered(mesh)
    hulls = convex_decompose(
        m, threshold=coacd_threshold, max_hulls=max_hulls, max_hull_vertices=max_hull_vertices, seed=seed
    )
    if m.is_watertight:
        props = mass_properties(m, density)
        volume_from = "surface"
    else:
        solid = trimesh.util.concatenate([trimesh.Trimesh(h.vertices, h.faces) for h in hulls])
        props = mass_properties(solid, density)
        volume_from = "hulls"
    extents = [float(e) for e in m.extents]
    size_bin = size_bin_of(max(extents))
    rel = f"{RIGID_DIR}/{asset_id}.usda"
    material = {"density": float(density), "friction": float(friction), **(extra_material or {})}
    write_rigid_usd(
        root / rel,
        asset_id,
        _visual_mesh(m),
        hulls,
        props,
        density=density,
        friction=friction,
        color=color,
        custom_data={"id": asset_id, "family": family, "size_bin": size_bin},
    )
    return AssetEntry(
        id=asset_id,
        path=rel,
        kind="rigid",
        family=family,
        size_bin=size_bin,
        extents=extents,
        mass=float(props.mass),
        volume=float(props.volume),
        material=material,
        split=split,  # type: ignore[arg-type]
        stats={
            "num_hulls": len(hulls),
            "num_hull_vertices": [len(h.vertices) for h in hulls],
            "volume_from": volume_from,
        },
        source=source,
    )


def surface_triangle_count(tets: np.ndarray) -> int:
    """Number of boundary triangles of a tet mesh (faces used by exactly one tet)."""
    t = np.asarray(tets, dtype=np.int64)
    faces = np.concatenate([t[:, [0, 1, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 3]], t[:, [1, 2, 3]]])
    _, counts = np.unique(np.sort(faces, axis=1), axis=0, return_counts=True)
    return int(np.count_nonzero(counts == 1))


def author_soft(
    mesh: trimesh.Trimesh,
    root: str | Path,
    asset_id: str,
    *,
    family: str,
    youngs_modulus: float,
    poissons_ratio: float,
    density: float,
    friction: float = DEFAULT_SOFT_FRICTION,
    target_tets: int = DEFAULT_TARGET_TETS,
    split: str = "train",
    source: str = "",
    extra_material: dict[str, Any] | None = None,
    label: str | None = None,
) -> AssetEntry:
    """Tet-mesh a closed surface and write ``root/objects/soft/<asset_id>.usda``; return its entry.

    Uses the soft-body authoring functions (:mod:`d3grasp.authoring.tetmesh`,
    :mod:`d3grasp.authoring.usd_soft`). ``label`` names the input in errors (default: the id).
    """
    from d3grasp.authoring.tetmesh import tet_signed_volumes, tetrahedralize
    from d3grasp.authoring.usd_soft import write_soft_usd

    root = Path(root)
    m = centered(mesh)
    label = label or asset_id
    try:
        points, tets = tetrahedralize(m, target_tets)
    except ValueError as exc:
        raise MeshError(f"{label}: tet meshing failed ({exc})") from None
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    vols = tet_signed_volumes(points, tets)
    if len(tets) == 0 or np.any(vols <= 0):
        raise MeshError(f"{label}: tet meshing produced {len(tets)} tets, some inverted or empty")
    volume = float(vols.sum())
    material = {
        "density": float(density),
        "friction": float(friction),
        "youngs_modulus": float(youngs_modulus),
        "poissons_ratio": float(poissons_ratio),
        **(extra_material or {}),
    }
    extents = [float(e) for e in points.max(axis=0) - points.min(axis=0)]
    try:
        size_bin = size_bin_of(max(extents))
    except ValueError as exc:  # the mesher can shrink a body that sat on a bin's lower edge
        raise MeshError(f"{label}: after tet meshing, {exc}") from None
    rel = f"{SOFT_DIR}/{asset_id}.usda"
    write_soft_usd(
        root / rel,
        points,
        tets,
        material,
        name=asset_id,
        custom_data={"id": asset_id, "family": family, "size_bin": size_bin},
    )
    return AssetEntry(
        id=asset_id,
        path=rel,
        kind="deformable",
        family=family,
        size_bin=size_bin,
        extents=extents,
        mass=density * volume,
        volume=volume,
        material=material,
        split=split,  # type: ignore[arg-type]
        stats={
            "num_tets": len(tets),
            "num_nodes": len(points),
            "num_surface_triangles": surface_triangle_count(tets),
        },
        source=source,
    )


def _author_one(
    path: Path, aid: str, mesh: trimesh.Trimesh, tmp: Path, opts: dict[str, Any]
) -> AssetEntry | str:
    """Author one checked mesh into ``tmp``: its entry, or the one-line reason it was refused (a
    string, so a refusal crosses a process boundary as plain data)."""
    scale = opts["scale"]
    src = f"import:{path.name}" + (f" scale={scale:g}" if scale != 1.0 else "")
    common = {
        "family": opts["family"],
        "density": opts["density"],
        "friction": opts["friction"],
        "source": src,
    }
    try:
        if opts["deformable"]:
            return author_soft(
                mesh,
                tmp,
                aid,
                youngs_modulus=opts["youngs_modulus"],
                poissons_ratio=opts["poissons_ratio"],
                target_tets=opts["target_tets"],
                label=str(path),
                **common,
            )
        return author_rigid(mesh, tmp, aid, **common)
    except MeshError as exc:
        return str(exc)


def _unique_ids(paths: list[Path], taken: set[str]) -> list[str]:
    ids = []
    used = set(taken)
    for p in paths:
        base = asset_id_from_name(p.stem)
        aid, k = base, 1
        while aid in used:
            aid = f"{base}_{k}"
            k += 1
        used.add(aid)
        ids.append(aid)
    return ids


@dataclass
class ImportResult:
    """What :func:`import_meshes` did: the assets written, the meshes refused, the assets replaced."""

    entries: list[AssetEntry]
    skipped: list[tuple[Path, str]] = field(default_factory=list)  # (mesh file, one-line reason)
    replaced: list[AssetEntry] = field(default_factory=list)  # the old entries the new ones replaced


def _check_soft_options(youngs_modulus: float, poissons_ratio: float, target_tets: int) -> None:
    """Refuse soft-body material and tet-count options out of range."""
    if not (youngs_modulus > 0 and np.isfinite(youngs_modulus)):
        raise ValueError(f"Young's modulus must be positive, got {youngs_modulus}")
    if not (-1.0 < poissons_ratio < 0.5):
        raise ValueError(f"Poisson's ratio must be in (-1, 0.5), got {poissons_ratio}")
    from d3grasp.authoring.tetmesh import MAX_TETS, MIN_TETS

    if not (MIN_TETS <= target_tets <= MAX_TETS):
        raise ValueError(f"--target-tets must be in [{MIN_TETS}, {MAX_TETS}], got {target_tets}")


def _material(deformable: bool, density: float | None, friction: float | None) -> tuple[float, float]:
    """The density and friction to author: the given ones, checked, or the kind's defaults."""
    rho = density if density is not None else (DEFAULT_SOFT_DENSITY if deformable else DEFAULT_RIGID_DENSITY)
    if not (np.isfinite(rho) and rho > 0):
        raise ValueError(f"density must be positive, got {rho}")
    mu = friction
    if mu is None:
        mu = DEFAULT_SOFT_FRICTION if deformable else DEFAULT_RIGID_FRICTION
    if not (np.isfinite(mu) and mu >= 0):
        raise ValueError(f"friction must be non-negative, got {mu}")
    return rho, mu


def _author_all(
    items: list[tuple[Path, str, trimesh.Trimesh]],
    tmp: Path,
    opts: dict[str, Any],
    workers: int,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None,
) -> dict[int, AssetEntry | str]:
    """Author every checked mesh into ``tmp``: per item index, its entry or why it was refused."""
    units = [(p, aid, mesh, tmp, opts) for p, aid, mesh in items]
    authored: dict[int, AssetEntry | str] = {}
    bar = iter(progress(items)) if progress else None
    if bar is not None:
        next(bar, None)  # show the bar at 0 before the first (slow) mesh

    def done(k: int, result: AssetEntry | str) -> None:
        authored[k] = result
        if bar is not None:
            next(bar, None)

    # coacd (minutes for a many-part shape) and tet meshing are per mesh and independent: one
    # process per core; each mesh's asset is the same whichever process authored it.
    run_units(_author_one, units, workers, done)
    return authored


def _move_into_place(
    tmp: Path, out_dir: Path, manifest_path: Path, existing: list[AssetEntry], entries: list[AssetEntry]
) -> list[AssetEntry]:
    """Move the authored files from ``tmp`` into ``out_dir``, then write the merged manifest
    (atomically); the existing entries the new ones replaced."""
    for e in entries:
        dst = out_dir / e.path
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp / e.path, dst)
    by_id = {e.id: e for e in entries}
    replaced = [old for old in existing if old.id in by_id]
    write_manifest(manifest_path, [e for e in existing if e.id not in by_id] + entries)
    for old in replaced:  # a kind change leaves the old file in the other kind's folder
        if old.path != by_id[old.id].path:
            (out_dir / old.path).unlink(missing_ok=True)
    return replaced


def import_meshes(
    paths: Iterable[str | Path],
    out_dir: str | Path,
    *,
    deformable: bool = False,
    scale: float = 1.0,
    density: float | None = None,
    friction: float | None = None,
    youngs_modulus: float = DEFAULT_YOUNGS_MODULUS,
    poissons_ratio: float = DEFAULT_POISSONS_RATIO,
    target_tets: int = DEFAULT_TARGET_TETS,
    family: str = "imported",
    skip_invalid: bool = False,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
    workers: int = 1,
) -> ImportResult:
    """Import user meshes into the library at ``out_dir`` (USD files + ``out_dir/manifest.json``).

    By default every mesh must succeed: any :class:`MeshError` (a bad file, a mesh out of the
    graspable size range, a failed tet meshing) aborts the whole import with ``out_dir``
    untouched. With ``skip_invalid`` the meshes that fail are left out and listed in
    ``ImportResult.skipped`` with their reasons, and the rest are written; a :class:`MeshError`
    is still raised when none succeeds. Entries whose ids already exist in ``out_dir``'s
    manifest (re-imports of the same file name) replace the old ones, the old file too when the
    kind changed (rigid and soft assets live in different folders); they are listed in
    ``ImportResult.replaced``. Other entries are kept. ``progress`` wraps the per-mesh loop
    (e.g. ``tqdm``). ``workers`` processes author the meshes (``d3grasp.parallel``); the assets
    do not depend on their number.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("no mesh files given")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"--scale must be a positive number, got {scale}")
    if deformable:
        _check_soft_options(youngs_modulus, poissons_ratio, target_tets)
    rho, mu = _material(deformable, density, friction)

    out_dir = Path(out_dir)
    manifest_path = out_dir / "manifest.json"
    existing = read_manifest(manifest_path) if manifest_path.exists() else []
    # Re-importing a file replaces its asset, so ids are made unique only among this batch.
    ids = _unique_ids(paths, set())
    skipped: list[tuple[Path, str]] = []

    def refuse(p: Path, exc: MeshError) -> None:
        if not skip_invalid:
            raise exc
        skipped.append((p, str(exc).removeprefix(f"{p}: ")))

    # 1) Check everything before writing anything.
    items: list[tuple[Path, str, trimesh.Trimesh]] = []
    for p, aid in zip(paths, ids, strict=True):
        try:
            items.append((p, aid, load_and_check(p, scale=scale, require_watertight=deformable)))
        except MeshError as exc:
            refuse(p, exc)

    # 2) Author into a temporary directory next to the output (same file system: atomic moves).
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".d3grasp-import-", dir=out_dir.parent))
    try:
        opts = {
            "deformable": deformable,
            "family": family,
            "density": rho,
            "friction": mu,
            "youngs_modulus": youngs_modulus,
            "poissons_ratio": poissons_ratio,
            "target_tets": target_tets,
            "scale": scale,
        }
        authored = _author_all(items, tmp, opts, workers, progress)
        entries: list[AssetEntry] = []
        for k, (p, _aid, _mesh) in enumerate(items):
            result = authored[k]
            if isinstance(result, str):
                refuse(p, MeshError(result))
                continue
            entries.append(result)
        if not entries:
            reasons = "; ".join(f"{p.name}: {why}" for p, why in skipped[:3])
            raise MeshError(f"{out_dir}: none of the {len(paths)} meshes could be imported ({reasons})")
        # 3) Move into place, then write the merged manifest (atomically).
        replaced = _move_into_place(tmp, out_dir, manifest_path, existing, entries)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return ImportResult(entries=entries, skipped=skipped, replaced=replaced)
