"""The DexHand13 in Newton: :func:`add_hand` appends the authored hand USD to a ``newton.ModelBuilder``
and returns :class:`HandIndices`, where its joints, bodies and pads landed.

The USD is written by :mod:`d3grasp.authoring.hand_usd`; prim names and frame conventions are those
of :mod:`d3grasp.authoring.hand_spec`.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from d3grasp.authoring.hand_spec import HAND_PRIM, PAD_COLLIDER
from d3grasp.dexhand13 import (
    FINGER_JOINT_NAMES,
    LINK_NAMES,
    PAD_NAMES,
    PALM_LINK,
    ROOT_JOINT_NAMES,
    ROOT_LINK_NAMES,
)
from d3grasp.geometry import matrix_to_quat_xyzw_nonneg_w


@dataclass(frozen=True)
class HandIndices:
    """Where one imported hand lives inside a ``newton.ModelBuilder`` (and the finalized model).

    Index arrays follow the fixed orders of :mod:`d3grasp.dexhand13`: ``finger_*`` follow
    :data:`FINGER_JOINT_NAMES`, ``root_*`` follow :data:`ROOT_JOINT_NAMES`, ``pad_*`` follow
    :data:`PAD_NAMES`. ``*_q`` index ``joint_q``/``control.joint_target_q`` and ``*_dof`` index
    ``joint_qd``, ``joint_target_ke`` and the other per-DoF arrays.
    """

    joint_range: tuple[int, int]
    body_range: tuple[int, int]
    shape_range: tuple[int, int]
    finger_joints: np.ndarray
    finger_q: np.ndarray
    finger_dof: np.ndarray
    root_joints: np.ndarray
    root_q: np.ndarray
    root_dof: np.ndarray
    palm_body: int
    link_bodies: dict[str, int]
    pad_shapes: np.ndarray
    pad_bodies: np.ndarray
    pad_xform_in_body: np.ndarray
    """(11, 7) pad frame in its body's frame: position, quaternion (x, y, z, w)."""


def _suffix_index(labels: Sequence[str], start: int, end: int, suffix: str, what: str) -> int:
    hits = [i for i in range(start, end) if labels[i].endswith(suffix)]
    if len(hits) != 1:
        raise ValueError(f"expected one {what} ending in {suffix!r} in the imported hand, found {len(hits)}")
    return hits[0]


def add_hand(
    builder: Any,
    usd_path: str | Path | None = None,
    xform: Any = None,
    *,
    kinematic_palm: bool = False,
    **add_usd_kwargs: Any,
) -> HandIndices:
    """Append one DexHand13 to ``builder`` (call inside ``begin_world``/``end_world`` for one hand per world).

    ``xform`` (a ``wp.transform``) is the frame the root chain is anchored to: root joint
    coordinates are the palm pose relative to it (see
    :func:`d3grasp.authoring.hand_spec.palm_pose_to_root_q`). Extra keyword
    arguments go to ``ModelBuilder.add_usd``. Returns the index ranges of what was added.

    ``kinematic_palm=True`` skips the driven root chain (its 6 joints and 5 helper bodies) and makes
    the palm a kinematic root body on a free joint: the caller prescribes the palm pose every
    substep (a real arm is stiff, so exact root tracking is the better model) and SolverVBD derives
    its velocity from the pose change. ``root_*`` then index that free joint (7 coordinates:
    position, quaternion x, y, z, w; 6 DoFs) and ``xform`` should be the identity.
    """
    import newton

    from d3grasp.paths import hand_usd

    usd_path = Path(usd_path) if usd_path is not None else hand_usd()
    if not usd_path.is_file():
        raise FileNotFoundError(f"hand USD not found: {usd_path} (run tools/build_hand.py)")
    if kinematic_palm:
        chain = [f"{HAND_PRIM}/joints/{n}" for n in ROOT_JOINT_NAMES] + [
            f"{HAND_PRIM}/{n}" for n in ROOT_LINK_NAMES
        ]
        add_usd_kwargs["ignore_paths"] = [*add_usd_kwargs.get("ignore_paths", []), *chain]
    j0, b0, s0 = builder.joint_count, builder.body_count, builder.shape_count
    builder.add_usd(str(usd_path), xform=xform, **add_usd_kwargs)
    j1, b1, s1 = builder.joint_count, builder.body_count, builder.shape_count

    jl, bl, sl = builder.joint_label, builder.body_label, builder.shape_label

    def _joints(names: Sequence[str]) -> np.ndarray:
        return np.array([_suffix_index(jl, j0, j1, f"/joints/{n}", "joint") for n in names], dtype=np.int32)

    finger_joints = _joints(FINGER_JOINT_NAMES)
    q_start, qd_start = builder.joint_q_start, builder.joint_qd_start
    bodies = LINK_NAMES if kinematic_palm else (*ROOT_LINK_NAMES, *LINK_NAMES)
    link_bodies = {n: _suffix_index(bl, b0, b1, f"/{n}", "body") for n in bodies}
    if kinematic_palm:
        palm = link_bodies[PALM_LINK]
        root_joints = np.array([j for j in range(j0, j1) if builder.joint_child[j] == palm], dtype=np.int32)
        if len(root_joints) != 1 or builder.joint_parent[int(root_joints[0])] != -1:
            raise ValueError(f"{usd_path}: expected the palm to be a root body on one free joint")
        builder.body_flags[palm] = int(newton.BodyFlags.KINEMATIC)
        j = int(root_joints[0])
        root_q = np.arange(q_start[j], q_start[j] + 7, dtype=np.int32)
        root_dof = np.arange(qd_start[j], qd_start[j] + 6, dtype=np.int32)
    else:
        root_joints = _joints(ROOT_JOINT_NAMES)
        root_q = np.array([q_start[j] for j in root_joints], dtype=np.int32)
        root_dof = np.array([qd_start[j] for j in root_joints], dtype=np.int32)

    pad_shapes, pad_bodies = [], []
    for pad in PAD_NAMES:
        shape = _suffix_index(sl, s0, s1, f"/{pad}/{PAD_COLLIDER}", "pad shape")
        pad_shapes.append(shape)
        pad_bodies.append(builder.shape_body[shape])
    pad_xforms = _read_pad_frames(str(usd_path.resolve()), usd_path.stat().st_mtime_ns)

    return HandIndices(
        joint_range=(j0, j1),
        body_range=(b0, b1),
        shape_range=(s0, s1),
        finger_joints=finger_joints,
        finger_q=np.array([q_start[j] for j in finger_joints], dtype=np.int32),
        finger_dof=np.array([qd_start[j] for j in finger_joints], dtype=np.int32),
        root_joints=root_joints,
        root_q=root_q,
        root_dof=root_dof,
        palm_body=link_bodies[PALM_LINK],
        link_bodies=link_bodies,
        pad_shapes=np.array(pad_shapes, dtype=np.int32),
        pad_bodies=np.array(pad_bodies, dtype=np.int32),
        pad_xform_in_body=pad_xforms.copy(),
    )


@functools.lru_cache(maxsize=8)
def _read_pad_frames(path: str, mtime_ns: int) -> np.ndarray:
    """(11, 7) pad frames relative to their links, read from the USD (cached: one read per file version)."""
    from pxr import Usd, UsdGeom

    del mtime_ns  # part of the cache key only
    stage = Usd.Stage.Open(path)
    cache = UsdGeom.XformCache()
    rows = []
    for pad in PAD_NAMES:
        # The pad frame prim, parent of the (off-centre) pad collider.
        prim = stage.GetPrimAtPath(f"{HAND_PRIM}/{_pad_parent_link(stage, pad)}/{pad}")
        m = np.array(cache.GetLocalTransformation(prim)[0], dtype=np.float64).T
        rows.append(np.concatenate([m[:3, 3], matrix_to_quat_xyzw_nonneg_w(m[:3, :3])]))
    out = np.array(rows)
    out.setflags(write=False)
    return out


def _pad_parent_link(stage: Any, pad: str) -> str:
    for link in LINK_NAMES:
        if stage.GetPrimAtPath(f"{HAND_PRIM}/{link}/{pad}"):
            return link
    raise ValueError(f"pad {pad!r} not found under any link of {HAND_PRIM}")
