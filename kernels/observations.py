"""The two observation groups for all worlds, one thread a world.

``policy`` (what a real hand has), in this order: the pad readings (``pad_force_per_unit`` per unit,
3 per pad) and contact flags (with ``tactile``), the finger joints' positions over their limits to
[-1, 1] and their velocities (x ``joint_vel_scale``), the action history, the episode clock (a row of
the script's table), the grasp type and the phase as one-hot codes, the palm command relative to the
grasp pose (x ``palm_offset_scale``), the grasp orientation, and (with ``residual_terms``) the rule's
joint targets over the limits and the residual.

``privileged`` (the critic's extra group): the object's position relative to the palm (x
``object_offset_scale``), its orientation (xyzw), linear and angular (x ``object_ang_vel_scale``)
velocity, the hand links' distances to it (x ``link_distance_scale``), its strain and sigma (x
``sigma_scale``; 0 for a rigid object), mass, friction, log10 Young's modulus / ``log_youngs_per_unit``
and the true pad forces. A rigid object's state is its body's; a soft object's, the deformable pose's
(its slot in the soft objects' arrays, -1 for a rigid world).

Non-finite values become 0 and +-the largest float32 (``world_state.finite``), where the
environment's torch terms (``d3grasp.envs.mdp.observations``, the reference this kernel is tested
against) apply ``torch.nan_to_num``.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp
from d3grasp.kernels.world_state import WorldArrays, finite, object_state, phase_of, soft_strain

__all__ = ["ObservationInputs", "ObservationParams", "compute_observations"]


@wp.struct
class ObservationParams:
    pad_force_per_unit: float
    joint_vel_scale: float
    palm_offset_scale: float
    object_offset_scale: float
    object_ang_vel_scale: float
    link_distance_scale: float
    sigma_scale: float
    log_youngs_per_unit: float
    tactile: int  # 1: the pad terms lead the policy group
    residual_terms: int  # 1: the rule's targets and the residual end it
    grasp_phase: int  # phase indices: a world whose lift started early is in the lift phase
    lift_phase: int
    num_grasp_types: int
    num_phases: int


@dataclass
class ObservationInputs:
    """Per world (W), what the groups read besides the state (``world_state.WorldArrays``): the step
    count ``t`` (int64); pads (W, P): ``pad_force``, ``pad_force_true`` vec3, ``pad_contact`` float;
    the fingers' joint limits ``lower``, ``upper`` (16,); ``action_hist`` (W, H * A) float; the
    schedule's ``clock`` (rows, 3) float; ``grasp_id`` (W,) int64; ``palm_cmd``, ``grasp_palm_pos``
    vec3, ``grasp_palm_quat`` (W, 4) float; ``rule_target``, ``residual`` (W, 16) float; the object's
    ``mass``, ``friction`` and ``log_e`` (W,) float."""

    t: wp.array
    pad_force: wp.array
    pad_contact: wp.array
    pad_force_true: wp.array
    lower: wp.array
    upper: wp.array
    action_hist: wp.array
    clock: wp.array
    grasp_id: wp.array
    palm_cmd: wp.array
    grasp_palm_pos: wp.array
    grasp_palm_quat: wp.array
    rule_target: wp.array
    residual: wp.array
    mass: wp.array
    friction: wp.array
    log_e: wp.array


@wp.func
def _normalized(q: float, lo: float, hi: float) -> float:
    return 2.0 * (q - lo) / (hi - lo) - 1.0


@wp.func
def _privileged_group(
    prm: ObservationParams,
    world: WorldArrays,
    w: int,
    num_pads: int,
    pad_force_true: wp.array2d(dtype=wp.vec3),
    mass: wp.array(dtype=float),
    friction: wp.array(dtype=float),
    log_e: wp.array(dtype=float),
    privileged: wp.array2d(dtype=float),
):
    """World ``w``'s row of the privileged group (the critic's), in the order of the module docstring."""
    pos, rot, lin, ang = object_state(world, w)
    eps, sigma, _nodes = soft_strain(world, w)
    palm = wp.transform_get_translation(world.body_q[world.palm_body[w]])
    o = int(0)  # noqa: UP018  (a typed variable: Warp mutates no literal in a loop)
    rel = pos - palm
    for k in range(3):
        privileged[w, o] = finite(rel[k] * prm.object_offset_scale)
        o += 1
    for k in range(4):
        privileged[w, o] = finite(rot[k])
        o += 1
    for k in range(3):
        privileged[w, o] = finite(lin[k])
        o += 1
    for k in range(3):
        privileged[w, o] = finite(prm.object_ang_vel_scale * ang[k])
        o += 1
    for i in range(world.link_bodies.shape[1]):
        d = wp.transform_get_translation(world.body_q[world.link_bodies[w, i]]) - pos
        privileged[w, o] = finite(wp.length(d) * prm.link_distance_scale)
        o += 1
    privileged[w, o] = finite(eps)
    privileged[w, o + 1] = finite(sigma * prm.sigma_scale)
    privileged[w, o + 2] = finite(mass[w])
    privileged[w, o + 3] = finite(friction[w])
    privileged[w, o + 4] = finite(log_e[w] / prm.log_youngs_per_unit)
    o += 5
    for p in range(num_pads):
        f = pad_force_true[w, p]
        for k in range(3):
            privileged[w, o] = finite(finite(f[k]) / prm.pad_force_per_unit)
            o += 1


@wp.kernel
def _observation_kernel(
    prm: ObservationParams,
    world: WorldArrays,
    t_step: wp.array(dtype=wp.int64),
    pad_force: wp.array2d(dtype=wp.vec3),
    pad_contact: wp.array2d(dtype=float),
    pad_force_true: wp.array2d(dtype=wp.vec3),
    lower: wp.array(dtype=float),
    upper: wp.array(dtype=float),
    action_hist: wp.array2d(dtype=float),
    clock: wp.array2d(dtype=float),
    grasp_id: wp.array(dtype=wp.int64),
    palm_cmd: wp.array(dtype=wp.vec3),
    grasp_palm_pos: wp.array(dtype=wp.vec3),
    grasp_palm_quat: wp.array2d(dtype=float),
    rule_target: wp.array2d(dtype=float),
    residual: wp.array2d(dtype=float),
    mass: wp.array(dtype=float),
    friction: wp.array(dtype=float),
    log_e: wp.array(dtype=float),
    policy: wp.array2d(dtype=float),
    privileged: wp.array2d(dtype=float),
):
    w = wp.tid()
    o = int(0)  # noqa: UP018  (a typed variable: Warp mutates no literal in a loop)
    num_pads = pad_force.shape[1]
    num_joints = world.finger_q.shape[1]
    if prm.tactile != 0:
        for p in range(num_pads):
            f = pad_force[w, p]
            for k in range(3):
                policy[w, o] = finite(finite(f[k]) / prm.pad_force_per_unit)
                o += 1
        for p in range(num_pads):
            policy[w, o] = finite(pad_contact[w, p])
            o += 1
    for j in range(num_joints):
        q = finite(world.joint_q[world.finger_q[w, j]])
        policy[w, o] = finite(_normalized(q, lower[j], upper[j]))
        o += 1
    for j in range(num_joints):
        policy[w, o] = finite(prm.joint_vel_scale * finite(world.joint_qd[world.finger_dof[w, j]]))
        o += 1
    for k in range(action_hist.shape[1]):
        policy[w, o] = finite(action_hist[w, k])
        o += 1
    t = int(t_step[w])
    row = wp.clamp(t, 0, world.last_row)
    for k in range(3):
        policy[w, o] = finite(clock[row, k])
        o += 1
    g = int(grasp_id[w])
    for k in range(prm.num_grasp_types):
        policy[w, o] = wp.where(k == g, 1.0, 0.0)
        o += 1
    ph = phase_of(world, w, t, prm.grasp_phase, prm.lift_phase)
    for k in range(prm.num_phases):
        policy[w, o] = wp.where(k == ph, 1.0, 0.0)
        o += 1
    offset = palm_cmd[w] - grasp_palm_pos[w]
    for k in range(3):
        policy[w, o] = finite(offset[k] * prm.palm_offset_scale)
        o += 1
    for k in range(4):
        policy[w, o] = finite(grasp_palm_quat[w, k])
        o += 1
    if prm.residual_terms != 0:
        for j in range(num_joints):
            policy[w, o] = finite(_normalized(rule_target[w, j], lower[j], upper[j]))
            o += 1
        for j in range(num_joints):
            policy[w, o] = finite(residual[w, j])
            o += 1

    # The privileged group.
    _privileged_group(prm, world, w, num_pads, pad_force_true, mass, friction, log_e, privileged)


def compute_observations(
    prm: ObservationParams, world: WorldArrays, inp: ObservationInputs, policy: wp.array, privileged: wp.array
) -> None:
    """Both groups of every world into ``policy`` (W, P) and ``privileged`` (W, Q) (one launch, no
    host sync: graph-capturable)."""
    wp.launch(
        _observation_kernel,
        dim=policy.shape[0],
        inputs=[prm, world, *(getattr(inp, name) for name in ObservationInputs.__dataclass_fields__)],
        outputs=[policy, privileged],
        device=policy.device,
    )
