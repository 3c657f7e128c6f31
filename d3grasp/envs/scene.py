"""The multi-world grasp scene: one ``newton.Model`` with a table, a DexHand13 and one object per world.

Worlds do not collide with each other in Newton, so every world sits at the same place: the
table is one global ground plane (world -1) at ``SimConfig.table_height``. Each hand's root chain
is anchored at the world origin, rotated so that zero root angles mean *palm facing down*
(:data:`HAND_ANCHOR_QUAT`): SolverVBD's angular drives wrap their error to ±π, so a target of
exactly π (palm down from a palm-up anchor) is unstable; from a palm-down anchor every grasp
type's orientation stays well inside ±π/2.

:class:`SceneLayout` holds every index the environment needs, one row per world, as NumPy arrays
(and Warp copies where kernels read them).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import newton
import numpy as np
import warp as wp

from d3grasp.authoring import hand as hand_def
from d3grasp.authoring.manifest import AssetEntry

HAND_ANCHOR_QUAT = (1.0, 0.0, 0.0, 0.0)
"""Rotation (x, y, z, w) of the root chain's anchor: π about world x, so the palm faces down."""

_ANCHOR_R = hand_def.quat_xyzw_to_matrix(HAND_ANCHOR_QUAT)

OBJECT_RIGID = 0
OBJECT_SOFT = 1


def palm_world_pose_to_free_q(pos: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Free-joint coordinates (7,) of a kinematic palm at a world pose: position, quaternion x, y, z, w."""
    return np.concatenate([np.asarray(pos, dtype=np.float64), np.asarray(quat_xyzw, dtype=np.float64)])


def palm_world_pose_to_root_q(pos: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Root joint coordinates (6,) that put the palm at a world pose (the anchor sits at the origin)."""
    r_world = hand_def.quat_xyzw_to_matrix(quat_xyzw)
    return hand_def.palm_pose_to_root_q(
        _ANCHOR_R.T @ np.asarray(pos, dtype=np.float64), hand_def.matrix_to_quat_xyzw(_ANCHOR_R.T @ r_world)
    )


@dataclass
class SceneLayout:
    """Per-world indices into the finalized model. Arrays have the world as first axis."""

    num_worlds: int
    entries: list[AssetEntry]
    object_kind: np.ndarray  # (W,) OBJECT_RIGID / OBJECT_SOFT
    object_body: np.ndarray  # (W,) body index, -1 for soft objects
    object_joint_q: np.ndarray  # (W,) start of the free joint's 7 coordinates, -1 for soft
    object_joint_qd: np.ndarray  # (W,) start of the free joint's 6 velocities, -1 for soft
    particle_start: np.ndarray  # (W,) first particle of the soft object (0 for rigid)
    particle_count: np.ndarray  # (W,) 0 for rigid
    tet_start: np.ndarray  # (W,)
    tet_count: np.ndarray  # (W,)
    finger_q: np.ndarray  # (W, 16) joint_q indices of the finger joints
    finger_dof: np.ndarray  # (W, 16)
    root_q: np.ndarray  # (W, 6) root chain angles, or (W, 7) the kinematic palm's free joint
    root_dof: np.ndarray  # (W, 6)
    kinematic_palm: bool  # palm prescribed each substep (no root chain)
    palm_body: np.ndarray  # (W,)
    link_bodies: np.ndarray  # (W, 17) palm + finger links, hand_def.LINK_NAMES order
    hand_shapes: list[np.ndarray]  # per world, every collision shape of the hand
    pad_shapes: np.ndarray  # (W, 11)
    object_shapes: list[np.ndarray]  # per world, collision shapes of a rigid object (empty for soft)
    articulation_world: np.ndarray  # (A,) world of each articulation (for masked FK on reset)
    rest_particle_q: np.ndarray  # (P, 3) particle positions as loaded (objects centred at the origin)
    finger_lower: np.ndarray  # (16,) joint limits (same hand in every world)
    finger_upper: np.ndarray  # (16,)


def build_scene(
    entries: list[tuple[AssetEntry, Path]],
    *,
    shape_mu: float = 1.0,
    particle_radius: float = 0.003,
    table_height: float = 0.0,
    contact_gap: float = 0.005,
    kinematic_palm: bool = False,
    device: str | None = None,
) -> tuple[newton.Model, SceneLayout]:
    """Build and finalize one model with a world per (asset entry, USD path).

    Objects are loaded at the origin in their rest frame; the environment places them on reset.
    ``kinematic_palm`` loads the hand without its root chain (see :func:`hand_def.add_hand`).
    """
    builder = newton.ModelBuilder()
    builder.default_shape_cfg.mu = shape_mu
    # Contacts are generated for shape pairs closer than the gap; Newton's 0.1 m default makes
    # hundreds of far-apart contacts per hand and overflows VBD's per-body contact lists.
    builder.default_shape_cfg.gap = contact_gap
    builder.default_particle_radius = particle_radius
    builder.add_ground_plane(height=table_height)
    anchor = (
        wp.transform_identity()
        if kinematic_palm
        else wp.transform(wp.vec3(0.0, 0.0, 0.0), wp.quat(*HAND_ANCHOR_QUAT))
    )

    kinds, obj_body, obj_jq, obj_jqd = [], [], [], []
    p_start, p_count, t_start, t_count = [], [], [], []
    finger_q, finger_dof, root_q, root_dof, palm, links, pads = [], [], [], [], [], [], []
    hand_shapes, object_shapes = [], []
    for entry, usd_path in entries:
        builder.begin_world(label=f"world_{len(kinds)}")
        hand = hand_def.add_hand(builder, xform=anchor, kinematic_palm=kinematic_palm)
        finger_q.append(hand.finger_q)
        finger_dof.append(hand.finger_dof)
        root_q.append(hand.root_q)
        root_dof.append(hand.root_dof)
        palm.append(hand.palm_body)
        links.append([hand.link_bodies[n] for n in hand_def.LINK_NAMES])
        pads.append(hand.pad_shapes)
        hand_shapes.append(np.arange(*hand.shape_range, dtype=np.int32))

        b0, j0, s0 = builder.body_count, builder.joint_count, builder.shape_count
        n0, t0 = builder.particle_count, builder.tet_count
        try:
            builder.add_usd(str(usd_path), xform=wp.transform_identity())
        except Exception as exc:  # a broken asset must name itself
            raise ValueError(f"{usd_path}: cannot load object '{entry.id}' ({exc})") from exc
        b1, j1, s1 = builder.body_count, builder.joint_count, builder.shape_count
        n1, t1 = builder.particle_count, builder.tet_count
        if entry.kind == "rigid":
            if b1 - b0 != 1 or j1 - j0 != 1:
                raise ValueError(
                    f"{usd_path}: rigid object must add one body and one free joint, "
                    f"added {b1 - b0} bodies and {j1 - j0} joints"
                )
            kinds.append(OBJECT_RIGID)
            obj_body.append(b0)
            obj_jq.append(builder.joint_q_start[j0])
            obj_jqd.append(builder.joint_qd_start[j0])
            object_shapes.append(np.arange(s0, s1, dtype=np.int32))
        else:
            if n1 == n0 or t1 == t0:
                raise ValueError(f"{usd_path}: soft object added no particles or tets")
            kinds.append(OBJECT_SOFT)
            obj_body.append(-1)
            obj_jq.append(-1)
            obj_jqd.append(-1)
            object_shapes.append(np.zeros(0, dtype=np.int32))
        p_start.append(n0)
        p_count.append(n1 - n0)
        t_start.append(t0)
        t_count.append(t1 - t0)
        builder.end_world()

    builder.color()
    model = builder.finalize(device=device)

    art_world = model.articulation_world.numpy() if model.articulation_count else np.zeros(0, np.int32)
    lower = model.joint_limit_lower.numpy()
    upper = model.joint_limit_upper.numpy()
    f_dof0 = np.asarray(finger_dof[0])
    layout = SceneLayout(
        num_worlds=len(entries),
        entries=[e for e, _ in entries],
        object_kind=np.array(kinds, dtype=np.int32),
        object_body=np.array(obj_body, dtype=np.int32),
        object_joint_q=np.array(obj_jq, dtype=np.int32),
        object_joint_qd=np.array(obj_jqd, dtype=np.int32),
        particle_start=np.array(p_start, dtype=np.int32),
        particle_count=np.array(p_count, dtype=np.int32),
        tet_start=np.array(t_start, dtype=np.int32),
        tet_count=np.array(t_count, dtype=np.int32),
        finger_q=np.array(finger_q, dtype=np.int32),
        finger_dof=np.array(finger_dof, dtype=np.int32),
        root_q=np.array(root_q, dtype=np.int32),
        root_dof=np.array(root_dof, dtype=np.int32),
        kinematic_palm=kinematic_palm,
        palm_body=np.array(palm, dtype=np.int32),
        link_bodies=np.array(links, dtype=np.int32),
        hand_shapes=hand_shapes,
        pad_shapes=np.array(pads, dtype=np.int32),
        object_shapes=object_shapes,
        articulation_world=np.asarray(art_world, dtype=np.int32),
        rest_particle_q=model.particle_q.numpy().copy() if model.particle_count else np.zeros((0, 3)),
        finger_lower=lower[f_dof0].astype(np.float64),
        finger_upper=upper[f_dof0].astype(np.float64),
    )
    return model, layout
