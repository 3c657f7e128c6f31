"""Reset events: where each world's object is put, which grasp is planned for it, the episode's
domain randomisation, and the restart of the state, the solver's history and the bookkeeping.

The random draws per world are made in a fixed order (object pose, grasp, mass or stiffness,
friction, drive gains, latency, push order) from the environment's generator: same seed, same
episodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import newton
import numpy as np
import torch
import warp as wp

from d3grasp.envs.grasps import GraspPose, choose_grasp, grasp_pose, rest_height
from d3grasp.envs.scene import OBJECT_SOFT, palm_world_pose_to_free_q, palm_world_pose_to_root_q
from d3grasp.geometry import rot_z, wrap_angle
from d3grasp.vision.estimators import PlacedObject
from d3grasp.vocabulary import GRASP_TYPES

if TYPE_CHECKING:
    from d3grasp.envs.grasp_env import GraspEnv


@dataclass
class ModelArrays:
    """Host copies of the model arrays a reset rewrites (read once, written back once)."""

    joint_q: np.ndarray
    joint_target: np.ndarray
    particle_q: np.ndarray | None
    tet_materials: np.ndarray | None
    body_mass: np.ndarray
    body_inv_mass: np.ndarray
    shape_mu: np.ndarray
    drive_ke: np.ndarray
    drive_kd: np.ndarray

    @classmethod
    def read(cls, env: GraspEnv) -> ModelArrays:
        m = env.model
        return cls(
            joint_q=m.joint_q.numpy(),
            joint_target=env.control.joint_target_q.numpy(),
            particle_q=env.state_0.particle_q.numpy() if m.particle_count else None,
            tet_materials=m.tet_materials.numpy() if m.tet_count else None,
            body_mass=m.body_mass.numpy(),
            body_inv_mass=m.body_inv_mass.numpy(),
            shape_mu=m.shape_material_mu.numpy(),
            drive_ke=m.joint_target_ke.numpy(),
            drive_kd=m.joint_target_kd.numpy(),
        )

    def write(self, env: GraspEnv) -> None:
        m = env.model
        m.joint_q.assign(self.joint_q)
        env.control.joint_target_q.assign(self.joint_target)
        m.body_mass.assign(self.body_mass)
        m.body_inv_mass.assign(self.body_inv_mass)
        # SolverVBD keeps its own inverse masses (zero for kinematic bodies): refresh them.
        env.solver.notify_model_changed(newton.ModelFlags.BODY_INERTIAL_PROPERTIES)
        m.shape_material_mu.assign(self.shape_mu)
        m.joint_target_ke.assign(self.drive_ke)
        m.joint_target_kd.assign(self.drive_kd)
        if self.tet_materials is not None:
            m.tet_materials.assign(self.tet_materials)


def reset_worlds(env: GraspEnv, env_ids: torch.Tensor) -> None:
    """Start a new episode in the worlds ``env_ids``."""
    if len(env_ids) == 0:
        return
    ids = env_ids.cpu().numpy()
    arrays = ModelArrays.read(env)
    for w in ids:
        _place_object_and_hand(env, w, arrays)
        _randomise_dynamics(env, w, arrays)
    arrays.write(env)
    _restart_state(env, ids, arrays)
    env.physics.forget_history(ids)
    _reset_bookkeeping(env, env_ids.to(env.torch_device))


def _place_object_and_hand(env: GraspEnv, w: int, arrays: ModelArrays) -> None:
    """Put world ``w``'s object on the table (random offset and yaw), plan the grasp from what the
    planner sees of it, and set the hand open at the pre-grasp pose."""
    cfg, rnd, lay = env.cfg, env.cfg.randomization, env.layout
    rand = rnd.enabled and not cfg.eval_mode
    table = cfg.sim.table_height
    e = env.world_entries[w]
    ex = np.asarray(e.extents, dtype=np.float64)
    xy = env.rng.uniform(-rnd.object_xy, rnd.object_xy, 2) if rnd.enabled else np.zeros(2)
    xy = xy + np.asarray(cfg.scene_shift, dtype=np.float64)  # the draws stay the same
    yaw = float(env.rng.uniform(-rnd.object_yaw, rnd.object_yaw)) if rnd.enabled else 0.0
    obj_pos = np.array([xy[0], xy[1], table + rest_height(ex)])
    qz = np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])
    soft = lay.object_kind[w] == OBJECT_SOFT
    p0, n = int(lay.particle_start[w]), int(lay.particle_count[w])
    # A soft body's nodes at the new pose (its rest shape turned by the yaw).
    placed = lay.rest_particle_q[p0 : p0 + n] @ rot_z(yaw).T + obj_pos if soft else None
    # The planner sees the estimator's pose (vision/estimators.py); the truth only scores its error.
    particles = (p0, placed) if soft else None
    seen = env.planning.estimator.estimate(
        env.state_0, PlacedObject(w, int(lay.object_body[w]), obj_pos, qz, yaw, ex, particles)
    )
    plan_pos, plan_yaw, plan_ex = seen.pos, seen.yaw, seen.extents
    estimated, registered = seen.estimated, seen.registered
    if estimated:
        env.record.localisation[w] = seen.record
    pose, used_yaw, place = _plan_grasp(
        env,
        w,
        e.id,
        plan_pos,
        plan_yaw + cfg.plan_yaw_offset,
        plan_ex,
        estimated=estimated and not registered,
    )
    _set_hand(env, w, arrays, pose)
    env.grasp.pose_correction[w] = 0.0
    env.grasp.centre_correction[w] = 0.0
    if estimated:
        true_yaw = _nearer_end(yaw, used_yaw)
        corr = _pose_correction(pose, used_yaw, place(obj_pos, true_yaw, ex), true_yaw)
        centre = np.asarray(obj_pos, dtype=np.float64) - np.asarray(plan_pos, dtype=np.float64)
        env.grasp.pose_correction[w] = torch.as_tensor(corr, dtype=torch.float32)
        env.grasp.centre_correction[w] = torch.as_tensor(centre, dtype=torch.float32)
        env.record.localisation[w].update(
            loc_correction=float(np.linalg.norm(corr[:3])),
            loc_correction_yaw=float(abs(corr[3])),
            loc_correction_centre=float(np.linalg.norm(centre)),
        )
    env.grasp.type_id[w] = GRASP_TYPES.index(pose.grasp)
    env.draw.object_start[w] = torch.as_tensor(obj_pos, dtype=torch.float32)
    if not soft:
        q0 = lay.object_joint_q[w]
        arrays.joint_q[q0 : q0 + 7] = [*obj_pos, *qz]
        b = lay.object_body[w]
        scale = env.rng.uniform(*rnd.object_mass_scale) if rand else 1.0
        arrays.body_mass[b] = env.nominal.body_mass[b] * scale
        arrays.body_inv_mass[b] = env.nominal.body_inv_mass[b] / scale
        env.draw.dynamics[w, 0] = scale
    else:
        arrays.particle_q[p0 : p0 + n] = placed
        t0, nt = lay.tet_start[w], lay.tet_count[w]
        scale = env.rng.uniform(*rnd.youngs_modulus_scale) if rand else 1.0
        arrays.tet_materials[t0 : t0 + nt, :2] = env.nominal.tet_materials[t0 : t0 + nt, :2] * scale
        env.draw.dynamics[w, 0] = scale


def _plan_grasp(
    env: GraspEnv, w: int, object_id: str, pos: np.ndarray, yaw: float, extents: np.ndarray, estimated: bool
) -> tuple[GraspPose, float, Callable[[np.ndarray, float, np.ndarray], GraspPose]]:
    """World ``w``'s grasp, the object yaw it was placed at, and the chosen grasp as a placer (the
    same grasp at another object pose): the planner's override for this world
    (``env.planning.override``, as the grasp planner scores its candidates), else the object's stored
    grasp of the library's grasp file (``env.planning.plan``: the best measured of the allowed types, or
    a random allowed type in ``grasp_mode="sample"``), else the geometric rule on the object's size."""
    allowed = tuple(env.cfg.grasp_types)
    override = env.planning.override[w] if env.planning.override is not None else None
    place: Callable[[np.ndarray, float, np.ndarray], GraspPose]
    if override is not None:
        place = lambda p, y, ex: override.place(p, y)  # noqa: E731
        return place(pos, yaw, extents), yaw, place
    stored = env.planning.plan.get(object_id) if env.planning.plan is not None else None
    name = stored.best(allowed) if stored else None
    if name is not None:
        if env.cfg.grasp_mode == "sample":
            types = [g for g in allowed if g in stored.grasps]
            name = types[int(env.rng.integers(len(types)))]
        if estimated:
            yaw = stored.align_yaw(yaw, extents)
        grasp = stored.grasps[name]
        place = lambda p, y, ex: grasp.place(p, y)  # noqa: E731
        return place(pos, yaw, extents), yaw, place
    if env.cfg.grasp_mode == "sample":
        kind = allowed[int(env.rng.integers(len(allowed)))]
    else:
        kind = choose_grasp(extents, allowed, env.cfg.sim.table_height)
    place = lambda p, y, ex: grasp_pose(kind, p, y, ex, env.cfg.sim.table_height)  # noqa: E731
    return place(pos, yaw, extents), yaw, place


def _nearer_end(true_yaw: float, planned_yaw: float) -> float:
    """Of the true yaw and its half-turn twin the one nearer the planned yaw: a box fit cannot tell
    an object's two ends apart (GraspPlan.align_yaw), and a wrist that turns by up to a few tenths of
    a radian corrects a small turn, not a half turn."""
    twin = wrap_angle(true_yaw + math.pi)
    return min((true_yaw, twin), key=lambda y: abs(wrap_angle(y - planned_yaw)))


def _pose_correction(planned: GraspPose, planned_yaw: float, true: GraspPose, true_yaw: float) -> np.ndarray:
    """(4,) what moves the grasp planned from the camera's estimate (at object yaw ``planned_yaw``)
    onto the same grasp at the true pose (``true``, at ``true_yaw``, ``_nearer_end``): the palm's
    offset (m, world) and its turn about the vertical (rad), the wrist's axes
    (mdp.actions.move_wrist). The privileged teacher's target."""
    return np.array([*(true.palm_pos - planned.palm_pos), wrap_angle(true_yaw - planned_yaw)])


def _set_hand(env: GraspEnv, w: int, arrays: ModelArrays, gp: GraspPose) -> None:
    """The open hand, in the grasp's pre-shape, at the pre-grasp pose of ``gp`` (the script starts
    from there)."""
    lay = env.layout
    pre = gp.palm_pos - env.cfg.phases.pregrasp_clearance * gp.approach_dir
    root = (
        palm_world_pose_to_free_q(pre, gp.palm_quat)
        if lay.kinematic_palm
        else palm_world_pose_to_root_q(pre, gp.palm_quat)
    )
    arrays.joint_q[lay.root_q[w]] = root
    if not lay.kinematic_palm:
        arrays.joint_target[lay.root_q[w]] = root
    env.palm.root_q_cmd[w] = torch.as_tensor(root, dtype=torch.float32)
    env.grasp.preshape[w] = torch.as_tensor(gp.preshape, dtype=torch.float32)
    open_pose = env.open_pose_of(torch.as_tensor([w], device=env.torch_device))[0].cpu().numpy()
    arrays.joint_q[lay.finger_q[w]] = open_pose
    arrays.joint_target[lay.finger_q[w]] = open_pose
    env.grasp.palm_pos[w] = torch.as_tensor(gp.palm_pos, dtype=torch.float32)
    env.grasp.palm_quat[w] = torch.as_tensor(gp.palm_quat, dtype=torch.float32)
    env.grasp.approach_dir[w] = torch.as_tensor(gp.approach_dir, dtype=torch.float32)
    env.palm.cmd_pos[w] = torch.as_tensor(pre, dtype=torch.float32)
    env.palm.pos_start[w] = torch.as_tensor(pre, dtype=torch.float32)
    env.palm.pos_end[w] = torch.as_tensor(pre, dtype=torch.float32)
    env.palm.quat[w] = torch.as_tensor(gp.palm_quat, dtype=torch.float32)
    env.act.palm_offset[w], env.act.palm_yaw[w] = 0.0, 0.0
    env.palm.yaw_start[w], env.palm.yaw_end[w] = 0.0, 0.0


def _randomise_dynamics(env: GraspEnv, w: int, arrays: ModelArrays) -> None:
    """World ``w``'s episode friction, drive gains, action latency and push order (training only)."""
    cfg, rnd, lay = env.cfg, env.cfg.randomization, env.layout
    rand = rnd.enabled and not cfg.eval_mode
    mu = env.rng.uniform(*rnd.friction) if rand else 1.0
    shapes = np.concatenate([lay.hand_shapes[w], lay.object_shapes[w]])
    arrays.shape_mu[shapes] = env.nominal.shape_mu[shapes] * mu
    gain = env.rng.uniform(*rnd.drive_gain_scale) if rand else 1.0
    dofs = lay.finger_dof[w]
    arrays.drive_ke[dofs] = env.nominal.ke[dofs] * gain
    arrays.drive_kd[dofs] = env.nominal.kd[dofs] * gain
    env.draw.latency[w] = (
        int(env.rng.integers(rnd.action_latency_steps[0], rnd.action_latency_steps[1] + 1)) if rand else 0
    )
    # What the critic reads of this episode's draw (privileged group; the mass or stiffness scale is
    # written where it is drawn).
    env.draw.dynamics[w, 1:] = torch.as_tensor([mu, gain, float(env.draw.latency[w])])
    if cfg.eval_mode:
        env.draw.disturb_order[w] = torch.arange(6)
    else:
        env.draw.disturb_order[w] = torch.as_tensor(env.rng.permutation(6))


def _restart_state(env: GraspEnv, ids: np.ndarray, arrays: ModelArrays) -> None:
    """Body and particle states of the reset worlds from the new joint coordinates, at rest."""
    lay, model = env.layout, env.model
    # Forward kinematics for the reset worlds' articulations only (others keep their state).
    mask = wp.array(np.isin(lay.articulation_world, ids), dtype=wp.bool, device=env.wp_device)
    states = (env.physics.state_0, env.physics.state_1)
    for st in states:
        newton.eval_fk(model, model.joint_q, model.joint_qd, st, mask=mask)
    # Joint readings of the reset worlds (the others keep theirs until the next step's IK).
    q_idx = np.concatenate([np.concatenate([lay.root_q[w], lay.finger_q[w]]) for w in ids])
    # Values and index on the tensor's device: index_put_ moves only a scalar value across devices.
    dev = env.view.joint_q.device
    env.view.joint_q[torch.as_tensor(q_idx, dtype=torch.long, device=dev)] = torch.as_tensor(
        arrays.joint_q[q_idx], dtype=torch.float32, device=dev
    )
    dof_idx = np.concatenate([np.concatenate([lay.root_dof[w], lay.finger_dof[w]]) for w in ids])
    env.view.joint_qd[torch.as_tensor(dof_idx, dtype=torch.long, device=dev)] = 0.0
    bqd = env.state_0.body_qd.numpy()
    bqd[np.isin(model.body_world.numpy(), ids)] = 0.0
    for st in states:
        st.body_qd.assign(bqd)
    if arrays.particle_q is None:
        return
    pqd = env.state_0.particle_qd.numpy()
    for w in ids:
        p0, n = lay.particle_start[w], lay.particle_count[w]
        pqd[p0 : p0 + n] = 0.0
    for st in states:
        st.particle_q.assign(arrays.particle_q)
        st.particle_qd.assign(pqd)
    env.sensors.restart_soft_objects(arrays.particle_q, env.state_0, ids)


def _reset_bookkeeping(env: GraspEnv, env_ids: torch.Tensor) -> None:
    env.episode_length_buf[env_ids] = 0
    env.act.actions[env_ids] = env.act.reset_action
    env.act.history[env_ids] = env.act.reset_action
    env.act.decision_age[env_ids] = 0
    env.act.finger_target[env_ids] = env.open_pose_of(env_ids)
    env.act.residual[env_ids] = 0.0
    if env.residual_base is not None:
        env.residual_base.reset(env_ids)
    env.view.object_force[env_ids] = 0.0
    now = env.scoring.now
    now.s_grasp[env_ids] = False
    now.pads_at_lift[env_ids] = False
    now.pads_at_hold[env_ids] = False
    now.lift_start[env_ids] = env.script.phase_start["lift"]
    now.touch_steps[env_ids] = 0
    now.max_rise[env_ids] = 0.0
    now.max_push_motion[env_ids] = 0.0
    now.lift_ok[env_ids] = True
    now.disturb_ok[env_ids] = True
    now.failure[env_ids] = 0
    env.record.max_strain[env_ids] = 0.0
    env.record.returns[env_ids] = 0.0
