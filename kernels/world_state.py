"""Per-world reads of the simulation state shared by the task's kernels, and the gather of the reward
kernels' inputs.

A world's object state is its rigid body's (``body_q``, ``body_qd`` at ``object_body``) or, for a
soft object, the deformable pose's (``soft_*`` at the world's ``soft_slot``; -1 for a rigid world).
``finite`` is ``torch.nan_to_num``: the environment's torch code, the reference of these kernels,
zeroes non-finite values with it.

:func:`gather_reward_inputs` fills the reward kernels' per-step inputs (``kernels/rewards.py``'s
``RewardInputs``) and the scoring's object position and finiteness from the state after a control
step (one thread a world). Its reference is ``reference_reward_inputs`` in
``d3grasp/envs/mdp/rewards.py``: the torch operations it replaces.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp

__all__ = ["RewardGather", "RewardGatherParams", "gather_reward_inputs", "finite", "object_state"]

FLOAT32_MAX = wp.constant(3.4028234663852886e38)


@wp.func
def finite(x: float) -> float:
    """torch.nan_to_num: NaN -> 0, +-inf -> +-the largest float32."""
    if wp.isnan(x):
        return 0.0
    if wp.isinf(x):
        if x > 0.0:
            return FLOAT32_MAX
        return -FLOAT32_MAX
    return x


@wp.func
def finite3(v: wp.vec3) -> wp.vec3:
    return wp.vec3(finite(v[0]), finite(v[1]), finite(v[2]))


@wp.func
def object_state(
    w: int,
    soft_slot: wp.array(dtype=wp.int32),
    object_body: wp.array(dtype=wp.int32),
    body_q: wp.array(dtype=wp.transform),
    body_qd: wp.array(dtype=wp.spatial_vector),
    soft_com: wp.array(dtype=wp.vec3),
    soft_quat: wp.array(dtype=wp.quat),
    soft_lin_vel: wp.array(dtype=wp.vec3),
    soft_ang_vel: wp.array(dtype=wp.vec3),
):
    """World ``w``'s object position, orientation (xyzw), linear and angular velocity."""
    slot = soft_slot[w]
    if slot >= 0:
        return soft_com[slot], soft_quat[slot], soft_lin_vel[slot], soft_ang_vel[slot]
    qb = body_q[object_body[w]]
    vb = body_qd[object_body[w]]
    lin = wp.vec3(vb[0], vb[1], vb[2])
    ang = wp.vec3(vb[3], vb[4], vb[5])
    return wp.transform_get_translation(qb), wp.transform_get_rotation(qb), lin, ang


@wp.func
def phase_of(
    t: int, lift_start: int, phase_table: wp.array(dtype=wp.int32), last_row: int, grasp: int, lift: int
):
    """The phase of a world at step ``t``: the schedule table's, the lift from its own (touch-timed)
    start on."""
    ph = phase_table[wp.clamp(t, 0, last_row)]
    if ph == grasp and t >= lift_start:
        ph = lift
    return ph


@wp.struct
class RewardGatherParams:
    table_height: float
    finger_half_thickness: float  # m: hand-to-table distances are link heights above the table minus this
    last_row: int  # the schedule tables' last row
    grasp_phase: int
    lift_phase: int


@dataclass
class RewardGather:
    """What :func:`gather_reward_inputs` reads: the step count ``t`` and lift starts (W,) int64, the
    schedule's ``phase`` table (int32), the state's ``joint_q``, ``joint_qd``, ``body_q``, ``body_qd``,
    the fingers' (W, 16) ``finger_q`` and ``finger_dof``, the (W, L) ``link_bodies``, ``object_body`` and
    ``soft_slot`` (W,) (int32), the soft objects' pose, ``soft_eps`` and ``soft_node_count``, and the
    objects' start positions (W,) vec3."""

    t: wp.array
    lift_start: wp.array
    phase: wp.array
    joint_q: wp.array
    joint_qd: wp.array
    body_q: wp.array
    body_qd: wp.array
    finger_q: wp.array
    finger_dof: wp.array
    link_bodies: wp.array
    object_body: wp.array
    soft_slot: wp.array
    soft_com: wp.array
    soft_quat: wp.array
    soft_lin_vel: wp.array
    soft_ang_vel: wp.array
    soft_eps: wp.array
    soft_node_count: wp.array
    object_start: wp.array


@wp.kernel
def _gather_kernel(
    prm: RewardGatherParams,
    t_step: wp.array(dtype=wp.int64),
    lift_start: wp.array(dtype=wp.int64),
    phase_table: wp.array(dtype=wp.int32),
    joint_q: wp.array(dtype=float),
    joint_qd: wp.array(dtype=float),
    body_q: wp.array(dtype=wp.transform),
    body_qd: wp.array(dtype=wp.spatial_vector),
    finger_q: wp.array2d(dtype=wp.int32),
    finger_dof: wp.array2d(dtype=wp.int32),
    link_bodies: wp.array2d(dtype=wp.int32),
    object_body: wp.array(dtype=wp.int32),
    soft_slot: wp.array(dtype=wp.int32),
    soft_com: wp.array(dtype=wp.vec3),
    soft_quat: wp.array(dtype=wp.quat),
    soft_lin_vel: wp.array(dtype=wp.vec3),
    soft_ang_vel: wp.array(dtype=wp.vec3),
    soft_eps: wp.array(dtype=float),
    soft_node_count: wp.array(dtype=float),
    object_start: wp.array(dtype=wp.vec3),
    alive: wp.array(dtype=float),
    joint_q_out: wp.array2d(dtype=float),
    joint_qd_out: wp.array2d(dtype=float),
    link_pos: wp.array2d(dtype=wp.vec3),
    object_com: wp.array(dtype=wp.vec3),
    obj_lin_vel: wp.array(dtype=wp.vec3),
    obj_ang_vel: wp.array(dtype=wp.vec3),
    env_dist: wp.array2d(dtype=float),
    eps_bar: wp.array(dtype=float),
    node_count: wp.array(dtype=float),
    object_rise: wp.array(dtype=float),
    obj_pos_out: wp.array(dtype=wp.vec3),
    finite_out: wp.array(dtype=wp.bool),
):
    w = wp.tid()
    pos, rot, lin, ang = object_state(
        w, soft_slot, object_body, body_q, body_qd, soft_com, soft_quat, soft_lin_vel, soft_ang_vel
    )
    ok = wp.isfinite(pos)
    for j in range(finger_q.shape[1]):
        q = joint_q[finger_q[w, j]]
        if not wp.isfinite(q):
            ok = False
        joint_q_out[w, j] = finite(q)
        joint_qd_out[w, j] = finite(joint_qd[finger_dof[w, j]])
    alive[w] = wp.where(ok, 1.0, 0.0)
    finite_out[w] = ok
    obj_pos_out[w] = pos
    for i in range(link_bodies.shape[1]):
        p = wp.transform_get_translation(body_q[link_bodies[w, i]])
        link_pos[w, i] = finite3(p)
        height = p[2] - prm.table_height - prm.finger_half_thickness
        env_dist[w, i] = wp.max(finite(height), 0.0)
    object_com[w] = finite3(pos)
    obj_lin_vel[w] = finite3(lin)
    obj_ang_vel[w] = finite3(ang)
    slot = soft_slot[w]
    eps = float(0.0)  # noqa: UP018  (a typed variable: Warp mutates no literal in a branch)
    nodes = float(0.0)  # noqa: UP018
    if slot >= 0:
        eps = soft_eps[slot]
        nodes = soft_node_count[slot]
    eps_bar[w] = eps
    node_count[w] = nodes
    # The rise above the resting height, counted from the lift phase on.
    ph = phase_of(
        int(t_step[w]), int(lift_start[w]), phase_table, prm.last_row, prm.grasp_phase, prm.lift_phase
    )
    rise = float(0.0)  # noqa: UP018
    if ph >= prm.lift_phase:
        rise = finite(pos[2] - object_start[w][2])
    object_rise[w] = rise


def gather_reward_inputs(
    prm: RewardGatherParams, src: RewardGather, rw_in, obj_pos: wp.array, ok: wp.array
) -> None:
    """Fill ``rw_in`` (a ``kernels.rewards.RewardInputs``: alive, joint_q, joint_qd, link_pos, object_com,
    obj_lin_vel, obj_ang_vel, env_dist, eps_bar, node_count, object_rise) and the raw object position
    ``obj_pos`` and finiteness ``ok`` (W,) from the state (one launch: graph-capturable)."""
    wp.launch(
        _gather_kernel,
        dim=src.t.shape[0],
        inputs=[prm, *(getattr(src, name) for name in RewardGather.__dataclass_fields__)],
        outputs=[
            rw_in.alive,
            rw_in.joint_q,
            rw_in.joint_qd,
            rw_in.link_pos,
            rw_in.object_com,
            rw_in.obj_lin_vel,
            rw_in.obj_ang_vel,
            rw_in.env_dist,
            rw_in.eps_bar,
            rw_in.node_count,
            rw_in.object_rise,
            obj_pos,
            ok,
        ],
        device=obj_pos.device,
    )
