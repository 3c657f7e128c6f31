"""Per-world reads of the simulation state shared by the task's kernels, and the gather of the reward
kernels' inputs.

:class:`WorldArrays` holds what they read of every world: the state, each world's indices into it
and the schedule's phase table. A world's object state is its rigid body's (``body_q``, ``body_qd``
at ``object_body``) or, for a soft object, the deformable pose's (``soft_*`` at the world's
``soft_slot``; -1 for a rigid world).
``finite`` is ``torch.nan_to_num``: the environment's torch code, the reference of these kernels,
zeroes non-finite values with it.

:func:`gather_reward_inputs` fills the reward kernels' per-step inputs (``kernels/rewards.py``'s
``RewardInputs``) and the scoring's object position and finiteness from the state after a control
step (one thread a world). Its reference is ``reference_reward_inputs`` in
``d3grasp/envs/mdp/rewards.py``: the torch operations it replaces.
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "RewardGatherParams",
    "WorldArrays",
    "finite",
    "gather_reward_inputs",
    "object_state",
    "phase_of",
    "soft_strain",
]

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


@wp.struct
class WorldArrays:
    """The state and the per-world tables the task's kernels read (W worlds, B bodies)."""

    joint_q: wp.array(dtype=float)
    joint_qd: wp.array(dtype=float)
    body_q: wp.array(dtype=wp.transform)
    body_qd: wp.array(dtype=wp.spatial_vector)
    finger_q: wp.array2d(dtype=wp.int32)  # (W, 16) the fingers' joint coordinates
    finger_dof: wp.array2d(dtype=wp.int32)  # (W, 16) ... and velocities
    link_bodies: wp.array2d(dtype=wp.int32)  # (W, L) the hand's links
    palm_body: wp.array(dtype=wp.int32)
    object_body: wp.array(dtype=wp.int32)  # a soft world's entry is unused
    soft_slot: wp.array(dtype=wp.int32)  # the world's soft object, -1 for a rigid one
    soft_com: wp.array(dtype=wp.vec3)  # per soft object: the deformable pose
    soft_quat: wp.array(dtype=wp.quat)
    soft_lin_vel: wp.array(dtype=wp.vec3)
    soft_ang_vel: wp.array(dtype=wp.vec3)
    soft_eps: wp.array(dtype=float)  # ... its largest nodal strain eps_bar
    soft_sigma: wp.array(dtype=float)  # ... the deformable rotation's sigma
    soft_node_count: wp.array(dtype=float)  # ... its node count N_k
    lift_start: wp.array(dtype=wp.int64)  # the step each world's (touch-timed) lift starts
    phase: wp.array(dtype=wp.int32)  # the schedule's phase by table row
    last_row: int  # the schedule tables' last row (max_episode_length + 1)


@wp.func
def object_state(world: WorldArrays, w: int):
    """World ``w``'s object position, orientation (xyzw), linear and angular velocity."""
    slot = world.soft_slot[w]
    if slot >= 0:
        return world.soft_com[slot], world.soft_quat[slot], world.soft_lin_vel[slot], world.soft_ang_vel[slot]
    qb = world.body_q[world.object_body[w]]
    vb = world.body_qd[world.object_body[w]]
    lin = wp.vec3(vb[0], vb[1], vb[2])
    ang = wp.vec3(vb[3], vb[4], vb[5])
    return wp.transform_get_translation(qb), wp.transform_get_rotation(qb), lin, ang


@wp.func
def soft_strain(world: WorldArrays, w: int):
    """World ``w``'s soft object's largest nodal strain, deformable-rotation sigma and node count
    (zeros for a rigid world)."""
    slot = world.soft_slot[w]
    if slot >= 0:
        return world.soft_eps[slot], world.soft_sigma[slot], world.soft_node_count[slot]
    return 0.0, 0.0, 0.0


@wp.func
def phase_of(world: WorldArrays, w: int, t: int, grasp: int, lift: int):
    """World ``w``'s phase at step ``t``: the schedule table's, the lift from its own (touch-timed)
    start on."""
    ph = world.phase[wp.clamp(t, 0, world.last_row)]
    if ph == grasp and t >= int(world.lift_start[w]):
        ph = lift
    return ph


@wp.struct
class RewardGatherParams:
    table_height: float
    finger_half_thickness: float  # m: hand-to-table distances are link heights above the table minus this
    grasp_phase: int
    lift_phase: int


@wp.kernel
def _gather_kernel(
    prm: RewardGatherParams,
    world: WorldArrays,
    t_step: wp.array(dtype=wp.int64),
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
    pos, rot, lin, ang = object_state(world, w)
    ok = wp.isfinite(pos)
    for j in range(world.finger_q.shape[1]):
        q = world.joint_q[world.finger_q[w, j]]
        if not wp.isfinite(q):
            ok = False
        joint_q_out[w, j] = finite(q)
        joint_qd_out[w, j] = finite(world.joint_qd[world.finger_dof[w, j]])
    alive[w] = wp.where(ok, 1.0, 0.0)
    finite_out[w] = ok
    obj_pos_out[w] = pos
    for i in range(world.link_bodies.shape[1]):
        p = wp.transform_get_translation(world.body_q[world.link_bodies[w, i]])
        link_pos[w, i] = finite3(p)
        height = p[2] - prm.table_height - prm.finger_half_thickness
        env_dist[w, i] = wp.max(finite(height), 0.0)
    object_com[w] = finite3(pos)
    obj_lin_vel[w] = finite3(lin)
    obj_ang_vel[w] = finite3(ang)
    eps, _sigma, nodes = soft_strain(world, w)
    eps_bar[w] = eps
    node_count[w] = nodes
    # The rise above the resting height, counted from the lift phase on.
    ph = phase_of(world, w, int(t_step[w]), prm.grasp_phase, prm.lift_phase)
    rise = float(0.0)  # noqa: UP018
    if ph >= prm.lift_phase:
        rise = finite(pos[2] - object_start[w][2])
    object_rise[w] = rise


def gather_reward_inputs(
    prm: RewardGatherParams,
    world: WorldArrays,
    t: wp.array,
    object_start: wp.array,
    rw_in,
    obj_pos: wp.array,
    ok: wp.array,
) -> None:
    """Fill ``rw_in`` (a ``kernels.rewards.RewardInputs``: alive, joint_q, joint_qd, link_pos,
    object_com, obj_lin_vel, obj_ang_vel, env_dist, eps_bar, node_count, object_rise) and the raw
    object position ``obj_pos`` and finiteness ``ok`` (W,) from ``world`` at steps ``t`` (W,) int64,
    the objects' rise counted from ``object_start`` (W,) vec3 (one launch: graph-capturable)."""
    wp.launch(
        _gather_kernel,
        dim=t.shape[0],
        inputs=[prm, world, t, object_start],
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
