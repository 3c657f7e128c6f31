"""Loading and checking user meshes before they become simulation assets.

Every check raises :class:`MeshError` with the message ``"<file>: <reason>"`` so the command line
can print it as one line. The checks guard against what breaks a simulation later in ways that
are hard to trace back to the input: non-finite coordinates, flat or empty geometry, inverted
winding (negative volume, hence negative mass), open surfaces (no defined volume) and sizes the
hand cannot hold (usually a unit mistake: millimetres read as metres).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

from d3grasp.authoring.manifest import SIZE_BINS

MESH_SUFFIXES = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")

# Graspable range of the longest side (metres), from the manifest's size bins.
MIN_LONGEST_SIDE = min(lo for lo, _ in SIZE_BINS.values())
MAX_LONGEST_SIDE = max(hi for _, hi in SIZE_BINS.values())
# Below this the thinnest side is a sheet, not a solid: contact and mass become meaningless.
MIN_THICKNESS = 1e-3


class MeshError(ValueError):
    """A mesh file cannot become an asset; the message is ``"<file>: <reason>"``."""


def _fail(name: str | Path, reason: str) -> MeshError:
    return MeshError(f"{name}: {reason}")


def load_mesh_file(path: str | Path) -> trimesh.Trimesh:
    """Read a mesh file into one triangle mesh (scenes, e.g. GLB, are concatenated).

    Only reads and checks that there is finite triangle data; geometry checks live in
    :func:`check_mesh`. Vertices are not merged yet so that NaN coordinates are still visible.
    """
    path = Path(path)
    if not path.exists():
        raise _fail(path, "file not found")
    if not path.is_file():
        raise _fail(path, "not a regular file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise _fail(
            path, f"unsupported file type '{path.suffix}' (expected one of {', '.join(MESH_SUFFIXES)})"
        )
    if path.stat().st_size == 0:
        raise _fail(path, "empty file")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except (ImportError, UnicodeDecodeError):
        # Text formats fall back to charset detection on undecodable bytes: binary garbage.
        fmt = path.suffix.lower().lstrip(".").upper()
        raise _fail(path, f"unreadable mesh: not valid {fmt} data (undecodable bytes)") from None
    except Exception as exc:  # trimesh raises many types on corrupt input; all mean "unreadable"
        msg = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise _fail(path, f"unreadable mesh ({msg[:120]})") from None
    if isinstance(loaded, trimesh.Scene):  # force="mesh" returns an empty Scene when nothing loads
        geoms = [g for g in loaded.geometry.values() if isinstance(g, trimesh.Trimesh)]
        if not geoms:
            raise _fail(path, "no triangle geometry in file")
        loaded = trimesh.util.concatenate(geoms)
    if not isinstance(loaded, trimesh.Trimesh):
        raise _fail(path, f"no triangle geometry in file (got {type(loaded).__name__})")
    if len(loaded.vertices) == 0 or len(loaded.faces) == 0:
        raise _fail(path, "no triangles in file (garbage or empty content?)")
    return loaded


def _suggest_scale(longest: float, scale: float) -> str:
    """A power-of-ten change of ``scale`` that brings ``longest`` into range, as a hint."""
    for exp in range(-4, 5):
        s = 10.0**exp
        if MIN_LONGEST_SIDE <= longest * s <= MAX_LONGEST_SIDE:
            return f"; try --scale {scale * s:g}"
    return "; rescale with --scale"


def check_mesh(
    mesh: trimesh.Trimesh,
    name: str | Path,
    *,
    scale: float = 1.0,
    require_watertight: bool = False,
    check_size: bool = True,
) -> trimesh.Trimesh:
    """Validate and clean a mesh; returns a new, scaled, processed mesh.

    - non-finite coordinates, fewer than 4 vertices, zero area or a flat/degenerate shape: error;
    - ``scale`` is applied first; the longest side must then be in the size bins' range;
    - winding is made consistent and outward (fixes inverted normals and negative volume);
    - open surfaces are repaired where that is sound (merging duplicate vertices, filling
      holes); with ``require_watertight`` (soft bodies, which need a volume to fill with tets) a
      surface that stays open is an error.
    """
    if not (math.isfinite(scale) and scale > 0):
        raise _fail(name, f"scale must be a positive finite number, got {scale}")
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if verts.size == 0 or faces.size == 0:
        raise _fail(name, "no triangles")
    if not np.all(np.isfinite(verts)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(verts), axis=1)))
        raise _fail(name, f"{bad} vertices have NaN or infinite coordinates")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise _fail(name, "face indices out of range")
    m = trimesh.Trimesh(verts * scale, faces, process=True, validate=True)
    if len(m.vertices) < 4 or len(m.faces) < 4:
        raise _fail(name, f"degenerate mesh ({len(m.vertices)} vertices, {len(m.faces)} faces after cleanup)")
    ext = m.extents
    longest = float(ext.max())
    if m.area <= 1e-12 or longest <= 0:
        raise _fail(name, "degenerate mesh (zero surface area)")
    if float(ext.min()) < MIN_THICKNESS:
        raise _fail(
            name,
            f"degenerate mesh: flat (thinnest side {ext.min() * 1000:.3g} mm < {MIN_THICKNESS * 1000:g} mm)",
        )
    if check_size and not (MIN_LONGEST_SIDE <= longest <= MAX_LONGEST_SIDE):
        raise _fail(
            name,
            f"longest side {longest * 100:.4g} cm (after scale {scale:g}) is outside the graspable range "
            f"{MIN_LONGEST_SIDE * 100:g}-{MAX_LONGEST_SIDE * 100:g} cm{_suggest_scale(longest, scale)}",
        )
    if not m.is_watertight:
        # Sound repairs only: close small holes with fan triangles and reconcile winding.
        trimesh.repair.fill_holes(m)
        m.merge_vertices()
        m.remove_unreferenced_vertices()
    trimesh.repair.fix_winding(m)
    trimesh.repair.fix_inversion(m)
    trimesh.repair.fix_normals(m)
    if require_watertight and not m.is_watertight:
        raise _fail(
            name, "open (non-watertight) mesh that could not be repaired; a soft body needs a closed surface"
        )
    if m.is_watertight:
        vol = float(m.volume)
        hull_vol = float(m.convex_hull.volume)
        if not (vol > 1e-9 and vol > 1e-4 * hull_vol):
            raise _fail(name, f"degenerate mesh (enclosed volume {vol:.3g} m^3)")
    else:
        try:
            hull_vol = float(m.convex_hull.volume)
        except Exception:
            raise _fail(name, "degenerate mesh (points are coplanar)") from None
        if hull_vol <= 1e-9:
            raise _fail(name, f"degenerate mesh (convex hull volume {hull_vol:.3g} m^3)")
    return m


def load_and_check(
    path: str | Path, *, scale: float = 1.0, require_watertight: bool = False
) -> trimesh.Trimesh:
    """:func:`load_mesh_file` followed by :func:`check_mesh` with the file's name in errors."""
    return check_mesh(load_mesh_file(path), Path(path), scale=scale, require_watertight=require_watertight)
