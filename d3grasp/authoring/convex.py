"""Convex decomposition of object meshes into collision hulls (coacd, MIT licence).

Newton collides convex hulls far faster and more robustly than triangle meshes, so every rigid
object is stored as a set of convex hulls: one hull when the shape is (nearly) convex, a coacd
decomposition otherwise. Hull count and vertices per hull are capped because contact cost in
the solver grows with both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

# A shape whose volume fills at least this share of its convex hull is treated as convex: the
# hull's extra volume is then a thin film that no finger can feel.
CONVEX_VOLUME_RATIO = 0.97
MAX_HULLS = 16
MAX_HULL_VERTICES = 64
# Hulls holding less than this share of the decomposition's volume are dropped as slivers.
SLIVER_VOLUME_FRACTION = 1e-4


@dataclass
class Hull:
    """One convex collision piece: vertices (V, 3) and outward triangles (F, 3)."""

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def volume(self) -> float:
        return float(trimesh.Trimesh(self.vertices, self.faces, process=False).volume)


def _greedy_hull_subset(points: np.ndarray, k: int) -> np.ndarray:
    """Indices of at most ``k`` points whose hull approximates the hull of ``points`` closely.

    Greedy outer approximation (as in quickhull, stopped early): start from an extreme
    tetrahedron, then repeatedly add the point farthest outside the current hull. Deterministic,
    and the error shrinks fastest where the hull is worst, unlike uniform subsampling.
    """
    p = np.asarray(points, dtype=np.float64)
    c = p.mean(axis=0)
    i0 = int(np.argmax(np.linalg.norm(p - c, axis=1)))
    i1 = int(np.argmax(np.linalg.norm(p - p[i0], axis=1)))
    d = p[i1] - p[i0]
    line = np.linalg.norm(np.cross(p - p[i0], d), axis=1)
    i2 = int(np.argmax(line))
    n = np.cross(p[i1] - p[i0], p[i2] - p[i0])
    i3 = int(np.argmax(np.abs((p - p[i0]) @ n)))
    chosen = list(dict.fromkeys([i0, i1, i2, i3]))
    while len(chosen) < k:
        try:
            h = trimesh.convex.convex_hull(p[chosen])
        except Exception:  # still flat: add the farthest remaining point and retry
            rest = np.linalg.norm(p - p[chosen].mean(axis=0), axis=1)
            rest[chosen] = -1.0
            chosen.append(int(np.argmax(rest)))
            continue
        normals = np.asarray(h.face_normals)
        offsets = np.einsum("ij,ij->i", normals, np.asarray(h.triangles_center))
        outside = (p @ normals.T - offsets).max(axis=1)
        outside[chosen] = -np.inf
        j = int(np.argmax(outside))
        if outside[j] <= 1e-9:
            break
        chosen.append(j)
    return np.asarray(chosen)


def hull_of(points: np.ndarray, max_vertices: int = MAX_HULL_VERTICES) -> Hull:
    """Convex hull of ``points`` with at most ``max_vertices`` vertices.

    Hulls with more vertices are rebuilt from a greedy subset of their vertices: a hull of a
    subset lies inside the original, so this never makes an object collide early.
    """
    hull = trimesh.convex.convex_hull(np.asarray(points, dtype=np.float64))
    if len(hull.vertices) > max_vertices:
        keep = _greedy_hull_subset(np.asarray(hull.vertices), max_vertices)
        hull = trimesh.convex.convex_hull(np.asarray(hull.vertices)[keep])
    trimesh.repair.fix_normals(hull)
    return Hull(np.asarray(hull.vertices, dtype=np.float64), np.asarray(hull.faces, dtype=np.int64))


def is_nearly_convex(mesh: trimesh.Trimesh, ratio: float = CONVEX_VOLUME_RATIO) -> bool:
    """Whether ``mesh`` fills at least ``ratio`` of its convex hull's volume (open meshes: no)."""
    if not mesh.is_watertight:
        return False
    return float(mesh.volume) >= ratio * float(mesh.convex_hull.volume)


def _centroid_key(piece: Hull | trimesh.Trimesh) -> tuple[float, ...]:
    """A deterministic order for collision pieces (coacd's output order and a mesh's body order can
    vary): by the mean of their vertices, rounded so round-off does not reorder them."""
    return tuple(np.round(np.asarray(piece.vertices).mean(axis=0), 6))


def convex_bodies(mesh: trimesh.Trimesh, max_bodies: int = MAX_HULLS) -> list[trimesh.Trimesh] | None:
    """The separate closed bodies of ``mesh`` when it is made of 2 to ``max_bodies`` of them and every
    one is nearly convex (a shape modelled as overlapping primitives), in a fixed order; else None.

    Their hulls are the exact decomposition, where coacd would search the union of intersecting
    shells for one: measured on such meshes (pybullet's random_urdfs, 4-10 overlapping boxes and
    cylinders), coacd ran over 15 minutes on a single 6-body mesh.
    """
    bodies = mesh.split(only_watertight=False)
    if not (2 <= len(bodies) <= max_bodies) or not all(is_nearly_convex(b) for b in bodies):
        return None
    return sorted(bodies, key=_centroid_key)


def convex_decompose(
    mesh: trimesh.Trimesh,
    *,
    threshold: float = 0.08,
    max_hulls: int = MAX_HULLS,
    max_hull_vertices: int = MAX_HULL_VERTICES,
    seed: int = 0,
    force_coacd: bool = False,
) -> list[Hull]:
    """Collision hulls for ``mesh``: its convex hull if it is nearly convex, the hulls of its bodies
    if it is a few separate convex bodies (:func:`convex_bodies`), else coacd pieces.

    ``threshold`` is coacd's concavity tolerance (relative to the bounding-box diagonal): larger
    is faster with fewer hulls. coacd runs with ``preprocess_mode="off"`` (its manifold
    preprocessing remeshes watertight inputs for nothing and costs seconds) and a fixed seed.
    """
    if not force_coacd and is_nearly_convex(mesh):
        return [hull_of(mesh.vertices, max_hull_vertices)]
    if not force_coacd:
        bodies = convex_bodies(mesh, max_hulls)
        if bodies is not None:
            return [hull_of(b.vertices, max_hull_vertices) for b in bodies]
    import coacd  # imported lazily: loading its native library costs time and prints a banner

    coacd.set_log_level("error")
    cmesh = coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
    parts = coacd.run_coacd(
        cmesh,
        threshold=threshold,
        max_convex_hull=max_hulls,
        preprocess_mode="off",
        resolution=1000,
        mcts_nodes=20,
        mcts_iterations=100,
        mcts_max_depth=2,
        merge=True,
        decimate=True,
        max_ch_vertex=max_hull_vertices,
        seed=seed,
    )
    hulls = []
    for verts, _faces in parts:
        verts = np.asarray(verts, dtype=np.float64)
        if len(verts) < 4:
            continue
        try:
            h = hull_of(verts, max_hull_vertices)
        except Exception:  # a flat sliver: qhull cannot build a 3-D hull, and it holds no volume
            continue
        if h.volume > 1e-12:
            hulls.append(h)
    # Drop slivers (coacd leaves a few micrometre-thin cuts): they hold no volume, may flatten
    # when coordinates are rounded for storage, and only cost contact work.
    total = sum(h.volume for h in hulls)
    hulls = [h for h in hulls if h.volume >= SLIVER_VOLUME_FRACTION * total]
    if not hulls:  # coacd failed to split: one hull still gives a usable collider
        hulls = [hull_of(mesh.vertices, max_hull_vertices)]
    # Deterministic order (coacd's output order can vary): sort by centroid.
    hulls.sort(key=_centroid_key)
    return hulls[:max_hulls]
