"""Candidate grasps of one object, in its frame, from its geometry.

For each of the three grasp types the type's geometric placement (``d3grasp.envs.grasps``) is the
first candidate; the others vary what decides whether a closing hand holds the object:

- which horizontal side the fingers wrap (the short one, or the long one);
- where the object sits in the hand: from deep under the palm, its top just off the palm face (a
  power grasp, which large objects need: the fingers reach 10 cm past the palm), to just in front
  of the palm's front face (the hook), and across the palm towards the thumb;
- the hand's pitch, for objects lower than the curling finger tips reach (< 5 cm): a palm-down hand
  tipped by up to 0.35 rad keeps its finger tips off the table while they close;
- the pre-shape (abduction of the fingers' first joints): fingers spread or together, the thumb
  rotated towards or away from the fingers;
- for an object made of several collision pieces (its convex hulls), each type's placement on each
  of the largest pieces as if it were the object: a composite's bounding box can be mostly air (the
  16 pybullet random_urdfs meshes fill 3-16% of it where none lifted), and a hand closed on the
  box's centre closes on nothing.

Candidates are drawn from a generator seeded by the planner's seed and the object's id, so a plan is
the same on every run and does not depend on which other objects are planned with it.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from d3grasp.envs.grasps import GRASPS, PALM_FACE_Z, PALM_FRONT_X, ObjectGrasp, object_grasp, rest_height
from d3grasp.vocabulary import GRASP_TYPES

LOW_OBJECT = 0.05  # m: below this height the curling finger tips meet the table (envs/grasps.py)
MAX_PITCH = 0.35  # rad
MAX_SPREAD = 0.35  # rad: the abduction joints' range (DexHand13: +-0.35)


@dataclass(frozen=True)
class CandidateConfig:
    """How many candidates per grasp type and where they put the object in the hand."""

    per_type: int = 10  # the geometric placement and per_type - 1 drawn ones
    # Soft objects: a step of a FEM body costs ~20x a rigid one's (246-1026 tets, 20 solver
    # iterations: d3grasp.eval.evaluate.SOFT_COST), and a squeeze
    # conforms to the hand, so fewer placements are drawn.
    per_type_soft: int = 4
    types: tuple[str, ...] = GRASP_TYPES
    # The object's near face along the fingers (palm-frame x): from deep under the palm (a power
    # grasp against the palm face) to just in front of the palm's front face (the hook).
    under_palm: float = 0.8  # at most this share of the object's length under the palm
    front_gap: float = 0.02  # m, at most this far in front of the palm's front face
    lateral: tuple[float, float] = (-0.045, 0.0)  # m, object centre across the palm (- thumb side)
    # Object's face nearest the palm (palm-frame z) when under the palm: just off the palm face.
    under_top: tuple[float, float] = (PALM_FACE_Z + 0.0015, PALM_FACE_Z + 0.012)
    front_top: tuple[float, float] = (0.0, 0.03)  # m, in front of the palm (the front face backs it)
    max_pieces: int = 4  # composite objects: placements on this many of the largest pieces
    min_piece: float = 0.02  # m: a piece's longest side below this is too small to close on
    # Rigid objects: per type, this many grasps synthesised by descent on the force-closure energy
    # over the object's convex hull (d3grasp.planner.synthesis), from synthesis_starts starts.
    synthesised: int = 0
    synthesis_starts: int = 32
    synthesis_steps: int = 300


def object_seed(seed: int, object_id: str) -> int:
    """A generator seed for one object: the planner's seed and the object's id, nothing else."""
    digest = hashlib.sha256(f"{seed}:{object_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def candidates(
    object_id: str,
    extents: np.ndarray,
    seed: int = 0,
    cfg: CandidateConfig | None = None,
    soft: bool = False,
    pieces: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    hull: tuple[np.ndarray, np.ndarray] | None = None,
) -> list[ObjectGrasp]:
    """The candidate grasps of an object of ``extents`` (its bounding box, object frame), in order:
    per type the geometric placement first, then the drawn ones, then those on its pieces, then
    the synthesised ones.

    ``pieces``: (centre, extents) of each collision piece's bounding box in the object frame (the
    frame of ``extents``' box centre), :func:`collision_pieces`; one piece or none adds nothing.
    ``hull``: (points, triangles) of the object's convex hull in that frame (:func:`convex_hull`),
    which ``cfg.synthesised`` needs (a soft object gets none)."""
    cfg = cfg or CandidateConfig()
    per_type = cfg.per_type_soft if soft else cfg.per_type
    ex = np.asarray(extents, dtype=np.float64)
    rng = np.random.default_rng(object_seed(seed, object_id))
    h = rest_height(ex)
    low = float(ex[2]) < LOW_OBJECT
    out: list[ObjectGrasp] = []
    for grasp in cfg.types:
        vertical = GRASPS[grasp].palm_vertical
        if vertical and not object_grasp(grasp, ex, h).feasible:
            continue  # the side wrap's lower edge would meet the table
        out.append(object_grasp(grasp, ex, h))
        drawn = 0
        while drawn < per_type - 1:
            long_side = bool(rng.random() < 0.3) and abs(float(ex[0] - ex[1])) > 0.005
            along = float(min(ex[0], ex[1]) if not long_side else max(ex[0], ex[1]))
            near_x = float(rng.uniform(PALM_FRONT_X - cfg.under_palm * along, PALM_FRONT_X + cfg.front_gap))
            under = near_x < PALM_FRONT_X - 0.002
            top = float(rng.uniform(*(cfg.under_top if under else cfg.front_top)))
            lateral = float(rng.uniform(*cfg.lateral))
            pitch = float(rng.uniform(0.0, MAX_PITCH)) if low and not vertical else 0.0
            spread = float(rng.uniform(-0.5, 0.5)) * MAX_SPREAD
            thumb = float(rng.uniform(-1.0, 1.0)) * MAX_SPREAD
            preshape = (-spread, 0.0, spread, thumb)  # index and ring fan out (or in) symmetrically
            g = object_grasp(
                grasp,
                ex,
                h,
                long_side=long_side,
                near_face_x=near_x,
                lateral_y=lateral,
                top_z=top,
                pitch=pitch,
                preshape=preshape,
            )
            drawn += 1
            if g.feasible:
                out.append(g)
        out += _piece_grasps(grasp, ex, h, pieces, cfg)
        if cfg.synthesised and not soft and hull is not None:
            out += _synthesised_grasps(grasp, hull, object_seed(seed, object_id), cfg)
    return out


def _synthesised_grasps(
    grasp: str, hull: tuple[np.ndarray, np.ndarray], seed: int, cfg: CandidateConfig
) -> list[ObjectGrasp]:
    """The ``cfg.synthesised`` lowest-energy grasps of the type on the hull (the table under it)."""
    from d3grasp.planner.synthesis import synthesise

    found = synthesise(
        "mesh",
        None,
        grasp,
        starts=cfg.synthesis_starts,
        steps=cfg.synthesis_steps,
        seed=seed % (2**32),
        keep=cfg.synthesised,
        mesh=hull,
    )
    return [g.to_object_grasp() for g in found]


def convex_hull(usd_path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(points, triangles) of the convex hull of a rigid object's collision meshes, object frame."""
    from scipy.spatial import ConvexHull

    every = np.concatenate(_collision_points(usd_path))
    hull = ConvexHull(every)
    used = np.unique(hull.simplices)
    remap = np.full(len(every), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    faces = remap[hull.simplices]
    # Outward winding: each triangle's normal points away from the hull's centre.
    centre = every[used].mean(axis=0)
    a, b, c = (every[hull.simplices[:, k]] for k in range(3))
    flip = np.einsum("ij,ij->i", np.cross(b - a, c - a), a - centre) < 0.0
    faces[flip] = faces[flip][:, [0, 2, 1]]
    return every[used], faces.astype(np.int32)


def _piece_grasps(
    grasp: str,
    extents: np.ndarray,
    rest_h: float,
    pieces: Sequence[tuple[np.ndarray, np.ndarray]],
    cfg: CandidateConfig,
) -> list[ObjectGrasp]:
    """The type's geometric placement on each of the largest ``cfg.max_pieces`` pieces."""
    if len(pieces) < 2:
        return []
    vertical = GRASPS[grasp].palm_vertical
    big = sorted(
        (p for p in pieces if float(np.max(p[1])) >= cfg.min_piece),
        key=lambda p: (-float(np.prod(p[1])), *np.round(p[0], 6)),
    )[: cfg.max_pieces]
    out: list[ObjectGrasp] = []
    for centre, ex in big:
        c = np.asarray(centre, dtype=np.float64)
        ex = np.asarray(ex, dtype=np.float64)
        h = rest_h + float(c[2])  # the piece's centre above the table
        low = h + 0.5 * float(ex[2]) < LOW_OBJECT  # its top lower than the curling tips reach
        pitch = 0.5 * MAX_PITCH if low and not vertical else 0.0
        g = object_grasp(grasp, ex, h, pitch=pitch)
        if g.feasible:
            out.append(replace(g, palm_pos=np.asarray(g.palm_pos) + c))
    return out


def collision_pieces(usd_path: str | Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(centre, extents) of the bounding box of each collision hull of a rigid object's USD file, in
    the object frame (the authoring tools centre the object's box at the origin)."""
    out = []
    for pts in _collision_points(usd_path):
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        out.append((0.5 * (lo + hi), hi - lo))
    return out


def _collision_points(usd_path: str | Path) -> list[np.ndarray]:
    """The points (n, 3) of each non-empty collision mesh of a rigid object's USD file, object frame."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(usd_path))
    out = []
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Mesh) and prim.GetParent().GetName() == "collision":
            pts = np.asarray(UsdGeom.Mesh(prim).GetPointsAttr().Get(), dtype=np.float64)
            if len(pts):
                out.append(pts)
    return out


def perturbed(grasp: ObjectGrasp, offset_xy: tuple[float, float], yaw: float) -> ObjectGrasp:
    """``grasp`` for an object found ``offset_xy`` (m) and ``yaw`` (rad) away from where it is: the
    planner's robustness trials (a perception error of the camera's class, ~5 mm). The grasp placed
    at that pose in the object's own frame is the displaced grasp, still in the object's frame."""
    pose = grasp.place(np.array([offset_xy[0], offset_xy[1], 0.0]), yaw)
    return ObjectGrasp(
        grasp=grasp.grasp,
        palm_pos=pose.palm_pos,
        palm_quat=pose.palm_quat,
        approach_dir=pose.approach_dir,
        feasible=grasp.feasible,
        preshape=grasp.preshape,
    )
