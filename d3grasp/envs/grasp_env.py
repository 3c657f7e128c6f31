"""The reach-grasp-lift-disturb environment: N worlds in one Newton model, an rsl-rl 5.5 VecEnv.

One control step (60 Hz) runs, on the device and captured as one Warp graph:
``substeps x (clear forces, apply disturbance, collide, SolverVBD step)``, then inverse
kinematics for the joint readings, the tactile kernels (pad forces in pad frames, noise,
contacts), the strain and deformable-pose kernels for soft objects, and the reward kernels. The
host side (torch) maps actions to joint targets, scripts the root through the episode's phases,
builds the observation groups, scores the success metrics and resets finished worlds.

Episode phases (seconds from ``PhaseConfig``): approach (the palm moves from the pre-grasp to the
grasp pose), grasp (root still), lift (root rises ``lift_height`` on a cosine profile), hold,
disturb (2.5 N on the object along each sampled direction; all six in evaluation), release.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any

import newton
import numpy as np
import torch
import warp as wp
from tensordict import TensorDict

from d3grasp.authoring import hand as hand_def
from d3grasp.authoring.hand import quat_xyzw_to_matrix
from d3grasp.authoring.manifest import AssetEntry, read_manifest, resolve_asset_path
from d3grasp.envs.config import ACTION_MODES, PERCEPTION_MODES, GraspEnvConfig
from d3grasp.envs.grasps import GRASP_NAMES, GRASP_TYPES, choose_grasp, grasp_pose, rot_z
from d3grasp.envs.scene import (
    HAND_ANCHOR_QUAT,
    OBJECT_SOFT,
    build_scene,
    palm_world_pose_to_free_q,
    palm_world_pose_to_root_q,
)
from d3grasp.kernels import rewards as rk
from d3grasp.kernels import rotation as rot_k
from d3grasp.kernels import strain as strain_k
from d3grasp.kernels import tactile as tac_k
from d3grasp.paths import default_manifest

NUM_FINGER_JOINTS = 16
NUM_FINGERS = 4  # joints 4f..4f+3 are finger f's: abduction (4f) then three flexion joints
NUM_PADS = 11
NUM_LINKS = len(hand_def.LINK_NAMES)
PHASES = ("approach", "grasp", "lift", "hold", "disturb", "release")
DISTURB_DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float32
)
GRASP_CONTACT_FORCE = 0.3  # N: a pad "in contact" for s_grasp
LIFT_TOLERANCE = 0.02  # m: s_lift needs the object raised by lift_height - this during the hold
DISTURB_TOLERANCE = 0.02  # m: s_disturb allows this much motion relative to the palm per push


@wp.kernel
def _apply_object_force_kernel(
    force: wp.array(dtype=wp.vec3),
    object_body: wp.array(dtype=wp.int32),
    particle_start: wp.array(dtype=wp.int32),
    particle_count: wp.array(dtype=wp.int32),
    body_f: wp.array(dtype=wp.spatial_vector),
    particle_f: wp.array(dtype=wp.vec3),
):
    # One thread per world: the disturbance acts at the rigid body's frame origin (its bounding-box
    # centre, within millimetres of the centre of mass) or is spread evenly over a soft object's nodes.
    w = wp.tid()
    f = force[w]
    b = object_body[w]
    if b >= 0:
        body_f[b] = body_f[b] + wp.spatial_vector(f, wp.vec3(0.0, 0.0, 0.0))
    n = particle_count[w]
    if n > 0:
        share = f / float(n)
        p0 = particle_start[w]
        for i in range(n):
            particle_f[p0 + i] = particle_f[p0 + i] + share


@wp.kernel
def _set_palm_pose_kernel(
    palm_body: wp.array(dtype=wp.int32),
    pos_start: wp.array(dtype=wp.vec3),
    pos_end: wp.array(dtype=wp.vec3),
    quat: wp.array(dtype=wp.quat),
    alpha: float,
    body_q: wp.array(dtype=wp.transform),
):
    # One thread per world: the kinematic palm at fraction ``alpha`` of the control step, on the
    # straight line from where it was to the commanded position. SolverVBD takes its velocity from
    # the change against its previous pose, so contacts see the true palm motion.
    w = wp.tid()
    p = pos_start[w] + alpha * (pos_end[w] - pos_start[w])
    body_q[palm_body[w]] = wp.transform(p, quat[w])


def _wp_view(a: wp.array) -> torch.Tensor:
    return wp.to_torch(a, requires_grad=False)


class GraspEnv:
    """Vectorised D3Grasp environment (rsl-rl ``VecEnv`` interface, duck-typed)."""

    def __init__(self, cfg: GraspEnvConfig, task_name: str = "") -> None:
        self.cfg = cfg
        self.task_name = task_name
        self.num_envs = int(cfg.num_envs)
        if self.num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {self.num_envs}")
        self.num_actions = NUM_FINGERS if cfg.action_mode == "synergy" else NUM_FINGER_JOINTS
        self.device = cfg.device
        self.wp_device = wp.get_device("cpu" if cfg.device == "cpu" else cfg.device)
        self.torch_device = torch.device(cfg.device)
        self.rng = np.random.default_rng(cfg.seed)
        self.torch_gen = torch.Generator(device="cpu").manual_seed(cfg.seed)
        for g in cfg.grasp_types:
            if g not in GRASP_TYPES:
                raise ValueError(f"unknown grasp type '{g}'; known: {list(GRASP_NAMES)}")

        sim = cfg.sim
        self.dt = 1.0 / sim.control_hz
        self.sim_dt = self.dt / sim.substeps
        ph = cfg.phases
        self.phase_steps = {
            "approach": max(1, round(ph.approach / self.dt)),
            "grasp": max(1, round(ph.grasp / self.dt)),
            "lift": max(1, round(ph.lift / self.dt)),
            "hold": max(1, round(ph.hold / self.dt)),
        }
        self.disturb_dirs = 6 if cfg.eval_mode else max(0, int(ph.train_disturb_directions))
        self.steps_per_push = max(1, round(ph.disturb_per_direction / self.dt))
        self.phase_steps["disturb"] = self.disturb_dirs * self.steps_per_push
        self.phase_steps["release"] = round(ph.release / self.dt)
        bounds = np.cumsum([0] + [self.phase_steps[p] for p in PHASES])
        self.phase_start = {p: int(bounds[i]) for i, p in enumerate(PHASES)}
        self.max_episode_length = int(bounds[-1])

        if cfg.action_mode not in ACTION_MODES:
            raise ValueError(f"unknown action_mode '{cfg.action_mode}'; known: {list(ACTION_MODES)}")
        if not 0.0 < cfg.residual_smoothing <= 1.0:
            raise ValueError(f"residual_smoothing must be in (0, 1], got {cfg.residual_smoothing}")
        if not 0.0 <= cfg.residual_rate <= 1.0:
            raise ValueError(f"residual_rate must be in [0, 1], got {cfg.residual_rate}")
        if cfg.perception not in PERCEPTION_MODES:
            raise ValueError(f"unknown perception '{cfg.perception}'; known: {list(PERCEPTION_MODES)}")
        self._load_objects()
        self._build()
        self._allocate_buffers()
        # Camera perception: the grasp planner reads the object's pose and size from a depth image.
        self.perception = None
        self.loc_records: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if cfg.perception == "camera":
            from d3grasp.vision.perception import CameraPerception

            self.perception = CameraPerception(
                self.model, self.model.body_world.numpy(), self.layout.object_body, cfg.camera, cfg.seed
            )
        # Residual mode: the rule-based controller runs inside the env and the policy's actions are
        # offsets on its joint targets (imported here: baseline.py imports this module).
        self.residual_base = None
        if cfg.action_mode in ("residual", "synergy"):
            from d3grasp.envs.baseline import RuleBasedController

            self.residual_base = RuleBasedController(self)
        # Place every world before the first (uncaptured) step, so nothing starts interpenetrating.
        self.reset_all()
        self._capture()
        self.reset_all()

    # ------------------------------------------------------------------------------------------
    # Construction
    # ------------------------------------------------------------------------------------------

    def _load_objects(self) -> None:
        oc = self.cfg.objects
        manifest = Path(oc.manifest) if oc.manifest else default_manifest()
        if not manifest.is_file():
            raise FileNotFoundError(f"object manifest not found: {manifest}")
        entries = read_manifest(manifest)
        if oc.ids:
            by_id = {e.id: e for e in entries}
            missing = [i for i in oc.ids if i not in by_id]
            if missing:
                raise ValueError(f"{manifest}: unknown asset ids {missing}")
            # Explicit ids fill the worlds in the given order (cycled), e.g. for evaluation.
            self.manifest_path = manifest
            self.world_entries = [by_id[oc.ids[i % len(oc.ids)]] for i in range(self.num_envs)]
            return
        else:
            chosen = [
                e
                for e in entries
                if e.kind in oc.kinds
                and e.size_bin in oc.size_bins
                and (oc.split == "all" or e.split == oc.split)
            ]
        if not chosen:
            raise ValueError(
                f"{manifest}: no asset matches kinds={oc.kinds} split={oc.split} size_bins={oc.size_bins}"
            )
        rigid = [e for e in chosen if e.kind == "rigid"]
        soft = [e for e in chosen if e.kind == "deformable"]
        order = self.rng.permutation
        rigid = [rigid[i] for i in order(len(rigid))]
        soft = [soft[i] for i in order(len(soft))]
        n_soft = 0
        if soft and rigid:
            n_soft = int(round(oc.soft_fraction * self.num_envs))
            n_soft = min(max(n_soft, 1 if self.num_envs > 1 else 0), self.num_envs - 1)
        elif soft:
            n_soft = self.num_envs
        world_entries: list[AssetEntry] = [soft[i % len(soft)] for i in range(n_soft)]
        world_entries += [rigid[i % len(rigid)] for i in range(self.num_envs - n_soft)]
        self.manifest_path = manifest
        self.world_entries = world_entries

    def _build(self) -> None:
        sim = self.cfg.sim
        pairs = [(e, resolve_asset_path(self.manifest_path, e)) for e in self.world_entries]
        with wp.ScopedDevice(self.wp_device):
            self.model, self.layout = build_scene(
                pairs,
                shape_mu=sim.shape_mu,
                particle_radius=sim.particle_radius,
                table_height=sim.table_height,
                kinematic_palm=sim.kinematic_palm,
                device=self.wp_device,
            )
        model, lay = self.model, self.layout
        model.soft_contact_ke = sim.soft_contact_ke
        model.soft_contact_kd = sim.soft_contact_kd
        model.soft_contact_mu = sim.soft_contact_mu
        # Tet damping is not read from USD: apply each object's recorded damping (DESIGN.md §3).
        if model.tet_count:
            mats = model.tet_materials.numpy()
            for w, e in enumerate(self.world_entries):
                if e.kind == "deformable":
                    d = (
                        sim.soft_damping
                        if sim.soft_damping is not None
                        else float(e.material.get("damping", 0.0))
                    )
                    mats[lay.tet_start[w] : lay.tet_start[w] + lay.tet_count[w], 2] = d
            model.tet_materials.assign(mats)
        self.nominal_tet_materials = model.tet_materials.numpy().copy() if model.tet_count else None
        self.nominal_body_mass = model.body_mass.numpy().copy()
        self.nominal_body_inv_mass = model.body_inv_mass.numpy().copy()
        self.nominal_shape_mu = model.shape_material_mu.numpy().copy()
        self.nominal_ke = model.joint_target_ke.numpy().copy()
        self.nominal_kd = model.joint_target_kd.numpy().copy()

        with wp.ScopedDevice(self.wp_device):
            self.state_0 = model.state()
            self.state_1 = model.state()
            self.control = model.control()
            # The default capacity (~1300 per world here) sizes several per-substep kernels that run
            # over the whole buffer; grasps use < 100 contacts per world.
            self.pipeline = newton.CollisionPipeline(
                model,
                contact_matching="sticky",
                soft_contact_gap=sim.soft_contact_gap,
                rigid_contact_max=sim.rigid_contacts_per_world * self.num_envs,
            )
            self.contacts = self.pipeline.contacts()
            self.solver = newton.solvers.SolverVBD(
                model,
                iterations=sim.iterations,
                rigid_contact_history=True,
                particle_enable_self_contact=False,
                rigid_body_contact_buffer_size=sim.body_contact_buffer,
            )
            self.observables = self.solver.observables(kinds={"contact_f"}, contacts=self.contacts)

        W = self.num_envs
        # Tactile layout: pad slots of the pad shapes, pad frame = pad collider frame (the collider
        # has no rotation inside its pad frame prim).
        shape_pad = np.full(model.shape_count, -1, dtype=np.int64)
        for w in range(W):
            shape_pad[lay.pad_shapes[w]] = np.arange(NUM_PADS)
        st = model.shape_transform.numpy()
        self.tactile_layout = tac_k.TactileLayout.from_arrays(
            shape_pad,
            model.shape_world.numpy(),
            model.shape_body.numpy(),
            st[:, 3:7],
            W,
            device=self.wp_device,
        )
        self.tactile_layout.set_noise_seed(self.cfg.seed)
        self.tactile_cfg = tac_k.TactileConfig(
            saturation=self.cfg.tactile.saturation,
            noise_std=self.cfg.randomization.tactile_noise_std if self.cfg.randomization.enabled else 0.0,
            contact_threshold=self.cfg.tactile.contact_threshold,
        )
        self.true_tactile_cfg = tac_k.TactileConfig(
            saturation=(0.0, 0.0, 0.0), noise_std=0.0, contact_threshold=self.cfg.tactile.contact_threshold
        )
        # Soft objects: strain / pose layout with one object slot per soft world.
        soft_worlds = np.nonzero(lay.object_kind == OBJECT_SOFT)[0]
        self.soft_worlds = soft_worlds
        self.world_soft_slot = np.full(W, -1, dtype=np.int64)
        self.world_soft_slot[soft_worlds] = np.arange(len(soft_worlds))
        if len(soft_worlds):
            tets = model.tet_indices.numpy()
            tet_obj = np.empty(len(tets), dtype=np.int64)
            for slot, w in enumerate(soft_worlds):
                tet_obj[lay.tet_start[w] : lay.tet_start[w] + lay.tet_count[w]] = slot
            self.strain_layout = strain_k.StrainLayout.from_arrays(
                lay.rest_particle_q, tets, tet_obj, object_world=soft_worlds, device=self.wp_device
            )
            self.strain_buf = strain_k.StrainBuffers.allocate(self.strain_layout)
            self.pose_buf = rot_k.ObjectPoseBuffers.allocate(self.strain_layout, model.particle_mass)
        else:
            self.strain_layout = None

    def _allocate_buffers(self) -> None:
        W, dev, tdev = self.num_envs, self.wp_device, self.torch_device
        lay = self.layout
        f32 = torch.float32
        self.pad_world_force = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=dev)
        self.pad_force = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=dev)
        self.pad_contact = wp.zeros((W, NUM_PADS), dtype=float, device=dev)
        self.pad_force_true = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=dev)
        self.pad_contact_true = wp.zeros((W, NUM_PADS), dtype=float, device=dev)
        self.object_force = wp.zeros(W, dtype=wp.vec3, device=dev)
        self.wp_object_body = wp.array(lay.object_body, dtype=wp.int32, device=dev)
        self.wp_particle_start = wp.array(lay.particle_start, dtype=wp.int32, device=dev)
        self.wp_particle_count = wp.array(lay.particle_count, dtype=wp.int32, device=dev)
        # Kinematic palm: position at the start and end of the control step, fixed orientation.
        self.wp_palm_body = wp.array(lay.palm_body, dtype=wp.int32, device=dev)
        self.palm_pos_start = wp.zeros(W, dtype=wp.vec3, device=dev)
        self.palm_pos_end = wp.zeros(W, dtype=wp.vec3, device=dev)
        self.palm_quat = wp.zeros(W, dtype=wp.quat, device=dev)

        # Reward inputs, filled from torch views before each reward launch.
        K = NUM_LINKS
        self.rw_in = rk.RewardInputs(
            alive=wp.zeros(W, dtype=float, device=dev),
            joint_q=wp.zeros((W, NUM_FINGER_JOINTS), dtype=float, device=dev),
            joint_q_ref=wp.zeros((W, NUM_FINGER_JOINTS), dtype=float, device=dev),
            joint_qd=wp.zeros((W, NUM_FINGER_JOINTS), dtype=float, device=dev),
            link_pos=wp.zeros((W, NUM_LINKS), dtype=wp.vec3, device=dev),
            object_com=wp.zeros(W, dtype=wp.vec3, device=dev),
            pad_force=self.pad_force_true,
            pad_contact=self.pad_contact_true,
            obj_lin_vel=wp.zeros(W, dtype=wp.vec3, device=dev),
            obj_ang_vel=wp.zeros(W, dtype=wp.vec3, device=dev),
            env_dist=wp.zeros((W, K), dtype=float, device=dev),
            eps_bar=wp.zeros(W, dtype=float, device=dev),
            node_count=wp.zeros(W, dtype=float, device=dev),
            is_deformable=wp.array(
                (lay.object_kind == OBJECT_SOFT).astype(np.int32), dtype=wp.int32, device=dev
            ),
            object_rise=wp.zeros(W, dtype=float, device=dev),
        )
        self.rw_out = rk.RewardBuffers.allocate(self.cfg.rewards, W, NUM_LINKS, NUM_PADS, device=dev)

        # Torch views of device arrays (zero-copy).
        self.t_joint_q = _wp_view(self.state_0.joint_q)
        self.t_joint_qd = _wp_view(self.state_0.joint_qd)
        self.t_target = _wp_view(self.control.joint_target_q)
        self.t_object_force = _wp_view(self.object_force)
        self.t_palm_pos_start = _wp_view(self.palm_pos_start)
        self.t_palm_pos_end = _wp_view(self.palm_pos_end)
        self.t_palm_quat = _wp_view(self.palm_quat)
        self.t_pad_force = _wp_view(self.pad_force)
        self.t_pad_contact = _wp_view(self.pad_contact)
        self.t_pad_force_true = _wp_view(self.pad_force_true)
        self.t_pad_contact_true = _wp_view(self.pad_contact_true)
        self.t_reward_terms = _wp_view(self.rw_out.terms)
        self.t_reward_total = _wp_view(self.rw_out.total)
        self.t_rw = {
            name: _wp_view(getattr(self.rw_in, name))
            for name in (
                "alive",
                "joint_q",
                "joint_qd",
                "link_pos",
                "object_com",
                "obj_lin_vel",
                "obj_ang_vel",
                "env_dist",
                "eps_bar",
                "node_count",
                "object_rise",
            )
        }

        self.i_finger_q = torch.as_tensor(lay.finger_q, dtype=torch.long, device=tdev)
        self.i_finger_dof = torch.as_tensor(lay.finger_dof, dtype=torch.long, device=tdev)
        self.i_root_q = torch.as_tensor(lay.root_q, dtype=torch.long, device=tdev)
        self.i_link_bodies = torch.as_tensor(lay.link_bodies, dtype=torch.long, device=tdev)
        self.i_palm = torch.as_tensor(lay.palm_body, dtype=torch.long, device=tdev)
        self.i_obj_body = torch.as_tensor(np.maximum(lay.object_body, 0), dtype=torch.long, device=tdev)
        self.is_soft = torch.as_tensor(lay.object_kind == OBJECT_SOFT, device=tdev)
        self.lower = torch.as_tensor(lay.finger_lower, dtype=f32, device=tdev)
        self.upper = torch.as_tensor(lay.finger_upper, dtype=f32, device=tdev)
        # The open hand: flexion at its lower limit, abduction centred (all zeros on DexHand13).
        self.open_pose = self.lower.clone()
        abduction = torch.arange(0, NUM_FINGER_JOINTS, 4)
        self.open_pose[abduction] = 0.5 * (self.lower[abduction] + self.upper[abduction])
        self.open_action = self.normalize_joints(self.open_pose)

        H = self.cfg.obs.action_history
        self.episode_length_buf = torch.zeros(W, dtype=torch.long, device=tdev)
        A = self.num_actions
        self.actions = torch.zeros(W, A, dtype=f32, device=tdev)
        self.action_hist = torch.zeros(W, H, A, dtype=f32, device=tdev)
        # Synergy mode: (16, 4) map from the per-finger squeeze actions to joint residuals.
        self.synergy = torch.zeros(NUM_FINGER_JOINTS, NUM_FINGERS, dtype=f32, device=tdev)
        for f in range(NUM_FINGERS):
            self.synergy[4 * f + 1 : 4 * f + 4, f] = 1.0
        # What an action history starts from: the open hand (absolute) or the zero residual (the rule).
        self.reset_action = (
            self.open_action if self.cfg.action_mode == "absolute" else torch.zeros(A, device=tdev)
        )
        self.finger_target = torch.zeros(W, NUM_FINGER_JOINTS, dtype=f32, device=tdev)
        # The residual applied per joint, in [-1, 1] (low-passed or integrated actions).
        self.residual = torch.zeros(W, NUM_FINGER_JOINTS, dtype=f32, device=tdev)
        self.latency = torch.zeros(W, dtype=torch.long, device=tdev)
        self.grasp_id = torch.zeros(W, dtype=torch.long, device=tdev)
        self.grasp_palm_pos = torch.zeros(W, 3, dtype=f32, device=tdev)
        self.grasp_palm_quat = torch.zeros(W, 4, dtype=f32, device=tdev)
        self.approach_dir = torch.zeros(W, 3, dtype=f32, device=tdev)
        self.root_cmd_pos = torch.zeros(W, 3, dtype=f32, device=tdev)
        self.root_q_cmd = torch.zeros(W, lay.root_q.shape[1], dtype=f32, device=tdev)
        # p_anchor = R_a^T p  <=>  row vector p @ R_a
        self.anchor_rot = torch.as_tensor(quat_xyzw_to_matrix(HAND_ANCHOR_QUAT), dtype=f32, device=tdev)
        self.object_start = torch.zeros(W, 3, dtype=f32, device=tdev)
        self.disturb_order = torch.zeros(W, 6, dtype=torch.long, device=tdev)
        self.push_ref = torch.zeros(W, 3, dtype=f32, device=tdev)
        # Per-episode outcome bookkeeping.
        self.s_grasp = torch.zeros(W, dtype=torch.bool, device=tdev)
        self.lift_ok = torch.ones(W, dtype=torch.bool, device=tdev)
        self.disturb_ok = torch.ones(W, dtype=torch.bool, device=tdev)
        self.max_strain = torch.zeros(W, dtype=f32, device=tdev)
        self.episode_return = torch.zeros(W, dtype=f32, device=tdev)
        self.failure = ["" for _ in range(W)]
        self.object_mass = torch.as_tensor([e.mass for e in self.world_entries], dtype=f32, device=tdev)
        self.object_friction = torch.as_tensor(
            [float(e.material.get("friction", 1.0)) for e in self.world_entries], dtype=f32, device=tdev
        )
        self.object_log_e = torch.as_tensor(
            [
                math.log10(float(e.material["youngs_modulus"])) if e.kind == "deformable" else 0.0
                for e in self.world_entries
            ],
            dtype=f32,
            device=tdev,
        )
        self.nonfinite_resets = 0
        self._obs: TensorDict | None = None

    # ------------------------------------------------------------------------------------------
    # The captured control step
    # ------------------------------------------------------------------------------------------

    def _physics(self) -> None:
        sim = self.cfg.sim
        for i in range(sim.substeps):
            self.state_0.clear_forces()
            if self.layout.kinematic_palm:
                wp.launch(
                    _set_palm_pose_kernel,
                    dim=self.num_envs,
                    inputs=[
                        self.wp_palm_body,
                        self.palm_pos_start,
                        self.palm_pos_end,
                        self.palm_quat,
                        float(i + 1) / float(sim.substeps),
                    ],
                    outputs=[self.state_0.body_q],
                    device=self.wp_device,
                )
            wp.launch(
                _apply_object_force_kernel,
                dim=self.num_envs,
                inputs=[
                    self.object_force,
                    self.wp_object_body,
                    self.wp_particle_start,
                    self.wp_particle_count,
                ],
                outputs=[self.state_0.body_f, self.state_0.particle_f],
                device=self.wp_device,
            )
            # Contacts are stored in body frames and re-evaluated every solver iteration, so detecting
            # every other substep loses little (the gap covers the motion in between).
            if i % max(1, sim.collide_every) == 0:
                self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(
                self.state_0,
                self.state_1,
                self.control,
                self.contacts,
                self.sim_dt,
                observables=self.observables,
            )
            self.state_0, self.state_1 = self.state_1, self.state_0

    def _sensors(self) -> None:
        newton.eval_ik(self.model, self.state_0, self.state_0.joint_q, self.state_0.joint_qd)
        cf = self.observables.contact_f
        tac_k.accumulate_pad_forces(self.tactile_layout, self.contacts, cf, self.pad_world_force)
        tac_k.pad_frame_forces(
            self.tactile_layout,
            self.pad_world_force,
            self.state_0.body_q,
            self.tactile_cfg,
            self.pad_force,
            self.pad_contact,
        )
        tac_k.pad_frame_forces(
            self.tactile_layout,
            self.pad_world_force,
            self.state_0.body_q,
            self.true_tactile_cfg,
            self.pad_force_true,
            self.pad_contact_true,
        )
        if self.strain_layout is not None:
            strain_k.compute_strain(self.strain_layout, self.state_0.particle_q, self.strain_buf)
            strain_k.compute_sigma(self.strain_layout, self.state_0.particle_q, self.strain_buf)
            rot_k.compute_object_pose(
                self.strain_layout, self.state_0.particle_q, self.strain_buf.sigma, self.pose_buf
            )
            rot_k.update_object_velocity(self.pose_buf, self.dt)

    def _control_step(self) -> None:
        self._physics()
        self._sensors()

    def _capture(self) -> None:
        if self.cfg.sim.substeps % 2:
            raise ValueError("sim.substeps must be even: the captured step swaps two states")
        # One uncaptured step allocates the solver's lazily sized buffers (contact history etc.).
        self._control_step()
        self.graph = None
        if self.cfg.sim.use_graph:
            with wp.ScopedDevice(self.wp_device), wp.ScopedCapture() as capture:
                self._control_step()
            self.graph = capture.graph

    def _launch_step(self) -> None:
        if self.graph is not None:
            wp.capture_launch(self.graph)
        else:
            self._control_step()

    # ------------------------------------------------------------------------------------------
    # Reset
    # ------------------------------------------------------------------------------------------

    def reset_all(self) -> None:
        self._reset(torch.arange(self.num_envs, device=self.torch_device))
        self._obs = self._compute_observations()

    def _sample_grasp(self, w: int, extents: np.ndarray) -> str:
        allowed = tuple(self.cfg.grasp_types)
        if self.cfg.grasp_mode == "sample":
            return allowed[int(self.rng.integers(len(allowed)))]
        return choose_grasp(extents, allowed, self.cfg.sim.table_height)

    def _reset(self, env_ids: torch.Tensor) -> None:
        if len(env_ids) == 0:
            return
        ids = env_ids.cpu().numpy()
        cfg, rnd, lay = self.cfg, self.cfg.randomization, self.layout
        rand = rnd.enabled and not cfg.eval_mode
        jq = self.model.joint_q.numpy()
        tgt = self.control.joint_target_q.numpy()
        pq = self.state_0.particle_q.numpy() if self.model.particle_count else None
        mats = self.model.tet_materials.numpy() if self.model.tet_count else None
        body_mass = self.model.body_mass.numpy()
        inv_mass = self.model.body_inv_mass.numpy()
        shape_mu = self.model.shape_material_mu.numpy()
        ke = self.model.joint_target_ke.numpy()
        kd = self.model.joint_target_kd.numpy()
        table = cfg.sim.table_height
        for w in ids:
            e = self.world_entries[w]
            ex = np.asarray(e.extents, dtype=np.float64)
            xy = self.rng.uniform(-rnd.object_xy, rnd.object_xy, 2) if rnd.enabled else np.zeros(2)
            yaw = float(self.rng.uniform(-rnd.object_yaw, rnd.object_yaw)) if rnd.enabled else 0.0
            obj_pos = np.array([xy[0], xy[1], table + 0.5 * ex[2] + 0.001])
            qz = np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])
            soft = lay.object_kind[w] == OBJECT_SOFT
            p0, n = int(lay.particle_start[w]), int(lay.particle_count[w])
            # A soft body's nodes at the new pose (its rest shape turned by the yaw).
            placed = lay.rest_particle_q[p0 : p0 + n] @ rot_z(yaw).T + obj_pos if soft else None
            plan_pos, plan_yaw, plan_ex = obj_pos, yaw, ex
            if self.perception is not None:
                # The planner sees the camera's estimate; the truth only scores its error.
                plan_pos, plan_yaw, plan_ex = self._perceive(w, obj_pos, qz, yaw, ex, placed)
            grasp = self._sample_grasp(w, plan_ex)
            gp = grasp_pose(grasp, plan_pos, plan_yaw, plan_ex, table)
            pre = gp.palm_pos - cfg.phases.pregrasp_clearance * gp.approach_dir
            root = (
                palm_world_pose_to_free_q(pre, gp.palm_quat)
                if lay.kinematic_palm
                else palm_world_pose_to_root_q(pre, gp.palm_quat)
            )
            jq[lay.root_q[w]] = root
            if not lay.kinematic_palm:
                tgt[lay.root_q[w]] = root
            self.root_q_cmd[w] = torch.as_tensor(root, dtype=torch.float32)
            jq[lay.finger_q[w]] = self.open_pose.cpu().numpy()
            tgt[lay.finger_q[w]] = self.open_pose.cpu().numpy()
            self.grasp_id[w] = GRASP_NAMES.index(grasp)
            self.grasp_palm_pos[w] = torch.as_tensor(gp.palm_pos, dtype=torch.float32)
            self.grasp_palm_quat[w] = torch.as_tensor(gp.palm_quat, dtype=torch.float32)
            self.approach_dir[w] = torch.as_tensor(gp.approach_dir, dtype=torch.float32)
            self.root_cmd_pos[w] = torch.as_tensor(pre, dtype=torch.float32)
            self.t_palm_pos_start[w] = torch.as_tensor(pre, dtype=torch.float32)
            self.t_palm_pos_end[w] = torch.as_tensor(pre, dtype=torch.float32)
            self.t_palm_quat[w] = torch.as_tensor(gp.palm_quat, dtype=torch.float32)
            self.object_start[w] = torch.as_tensor(obj_pos, dtype=torch.float32)
            if not soft:
                q0 = lay.object_joint_q[w]
                jq[q0 : q0 + 7] = [*obj_pos, *qz]
                b = lay.object_body[w]
                scale = self.rng.uniform(*rnd.object_mass_scale) if rand else 1.0
                body_mass[b] = self.nominal_body_mass[b] * scale
                inv_mass[b] = self.nominal_body_inv_mass[b] / scale
            else:
                pq[p0 : p0 + n] = placed
                t0, nt = lay.tet_start[w], lay.tet_count[w]
                scale = self.rng.uniform(*rnd.youngs_modulus_scale) if rand else 1.0
                mats[t0 : t0 + nt, :2] = self.nominal_tet_materials[t0 : t0 + nt, :2] * scale
            mu = self.rng.uniform(*rnd.friction) if rand else 1.0
            shapes = np.concatenate([lay.hand_shapes[w], lay.object_shapes[w]])
            shape_mu[shapes] = self.nominal_shape_mu[shapes] * mu
            gain = self.rng.uniform(*rnd.drive_gain_scale) if rand else 1.0
            dofs = lay.finger_dof[w]
            ke[dofs] = self.nominal_ke[dofs] * gain
            kd[dofs] = self.nominal_kd[dofs] * gain
            self.latency[w] = (
                int(self.rng.integers(rnd.action_latency_steps[0], rnd.action_latency_steps[1] + 1))
                if rand
                else 0
            )
            if cfg.eval_mode:
                self.disturb_order[w] = torch.arange(6)
            else:
                self.disturb_order[w] = torch.as_tensor(self.rng.permutation(6))
            self.failure[w] = ""

        self.model.joint_q.assign(jq)
        self.control.joint_target_q.assign(tgt)
        self.model.body_mass.assign(body_mass)
        self.model.body_inv_mass.assign(inv_mass)
        # SolverVBD keeps its own inverse masses (zero for kinematic bodies): refresh them.
        self.solver.notify_model_changed(newton.ModelFlags.BODY_INERTIAL_PROPERTIES)
        self.model.shape_material_mu.assign(shape_mu)
        self.model.joint_target_ke.assign(ke)
        self.model.joint_target_kd.assign(kd)
        if mats is not None:
            self.model.tet_materials.assign(mats)
        # Forward kinematics for the reset worlds' articulations only (others keep their state).
        art_mask = np.isin(lay.articulation_world, ids)
        mask = wp.array(art_mask, dtype=wp.bool, device=self.wp_device)
        for st in (self.state_0, self.state_1):
            newton.eval_fk(self.model, self.model.joint_q, self.model.joint_qd, st, mask=mask)
        # Joint readings of the reset worlds (the others keep theirs until the next step's IK).
        q_idx = np.concatenate([np.concatenate([lay.root_q[w], lay.finger_q[w]]) for w in ids])
        self.t_joint_q[torch.as_tensor(q_idx, dtype=torch.long)] = torch.as_tensor(
            jq[q_idx], dtype=torch.float32
        )
        dof_idx = np.concatenate([np.concatenate([lay.root_dof[w], lay.finger_dof[w]]) for w in ids])
        self.t_joint_qd[torch.as_tensor(dof_idx, dtype=torch.long)] = 0.0
        bqd = self.state_0.body_qd.numpy()
        world_of_body = self.model.body_world.numpy()
        bqd[np.isin(world_of_body, ids)] = 0.0
        for st in (self.state_0, self.state_1):
            st.body_qd.assign(bqd)
        if pq is not None:
            pqd = self.state_0.particle_qd.numpy()
            for w in ids:
                p0, n = lay.particle_start[w], lay.particle_count[w]
                pqd[p0 : p0 + n] = 0.0
            for st in (self.state_0, self.state_1):
                st.particle_q.assign(pq)
                st.particle_qd.assign(pqd)
            if self.strain_layout is not None:
                # The episode's reference nodes p_ref: the placed rest shape.
                self.strain_layout.rest_points.assign(pq.astype(np.float32))
                slots = self.world_soft_slot[ids]
                slots = slots[slots >= 0]
                if len(slots):
                    rot_k.compute_object_pose(
                        self.strain_layout, self.state_0.particle_q, self.strain_buf.sigma, self.pose_buf
                    )
                    m = np.zeros(self.strain_layout.object_count, dtype=np.int32)
                    m[slots] = 1
                    rot_k.reset_object_history(
                        self.pose_buf, wp.array(m, dtype=wp.int32, device=self.wp_device)
                    )

        # Clear the solver's rigid history (previous poses, joint winding, contact warm starts) and
        # the collision pipeline's sticky contacts for the reset worlds: without it the teleported
        # bodies look like they moved in one substep.
        world_mask = np.zeros(self.model.world_count + 1, dtype=bool)
        world_mask[ids] = True
        wmask = wp.array(world_mask, dtype=wp.bool, device=self.wp_device)
        self.solver.reset(self.state_0, wmask, flags=0)
        self.pipeline.reset_contact_matching(wmask)

        env_ids = env_ids.to(self.torch_device)
        self.episode_length_buf[env_ids] = 0
        self.actions[env_ids] = self.reset_action
        self.action_hist[env_ids] = self.reset_action
        self.finger_target[env_ids] = self.open_pose
        self.residual[env_ids] = 0.0
        if self.residual_base is not None:
            self.residual_base.reset(env_ids)
        self.t_object_force[env_ids] = 0.0
        self.s_grasp[env_ids] = False
        self.lift_ok[env_ids] = True
        self.disturb_ok[env_ids] = True
        self.max_strain[env_ids] = 0.0
        self.episode_return[env_ids] = 0.0

    def _perceive(
        self,
        w: int,
        obj_pos: np.ndarray,
        qz: np.ndarray,
        yaw: float,
        ex: np.ndarray,
        placed_particles: np.ndarray | None,
    ) -> tuple[np.ndarray, float, np.ndarray]:
        """Camera estimate (centre, yaw, extents) of world ``w``'s freshly placed object; logs its error.

        ``placed_particles``: a soft object's nodes at the new pose (None for a rigid object).
        """
        from d3grasp.vision.perception import localisation_error

        lay = self.layout
        soft = placed_particles is not None
        est = self.perception.observe(
            self.state_0,
            w,
            int(lay.object_body[w]),
            None if soft else np.concatenate([obj_pos, qz]),
            (int(lay.particle_start[w]), placed_particles) if soft else None,
            fallback_extents=np.full(3, 0.06),
        )
        err = localisation_error(est, obj_pos, yaw, ex)
        self.loc_records[w] = {"perception": "camera", "loc_ok": bool(est.ok), **err.as_record()}
        return est.centre, est.yaw, est.extents

    # ------------------------------------------------------------------------------------------
    # Phases and the scripted root
    # ------------------------------------------------------------------------------------------

    def phase_of(self, t: torch.Tensor) -> torch.Tensor:
        """Phase index (into :data:`PHASES`) of every world at step ``t``."""
        starts = torch.as_tensor([self.phase_start[p] for p in PHASES[1:]], device=t.device)
        return torch.bucketize(t, starts, right=True)

    def _root_command(self, t: torch.Tensor) -> torch.Tensor:
        """Palm position command (W,3) at step ``t`` (orientation stays the grasp orientation)."""
        ph = self.cfg.phases
        ta = t.float() / self.phase_steps["approach"]
        s_app = 0.5 - 0.5 * torch.cos(math.pi * ta.clamp(0.0, 1.0))
        pos = self.grasp_palm_pos - (1.0 - s_app)[:, None] * ph.pregrasp_clearance * self.approach_dir
        tl = (t - self.phase_start["lift"]).float() / self.phase_steps["lift"]
        s_lift = 0.5 - 0.5 * torch.cos(math.pi * tl.clamp(0.0, 1.0))
        pos = pos.clone()
        pos[:, 2] += ph.lift_height * s_lift
        return pos

    def _write_root_targets(self, pos: torch.Tensor) -> None:
        if self.layout.kinematic_palm:
            # The captured substeps move the palm from its current position to ``pos``.
            self.t_palm_pos_start[:] = _wp_view(self.state_0.body_q)[self.i_palm, :3]
            self.t_palm_pos_end[:] = pos
            self.t_palm_quat[:] = self.grasp_palm_quat
            return
        # The orientation is fixed per episode (root angles set at reset); the prismatic part of the
        # root chain is the palm position expressed in the anchor frame.
        self.root_q_cmd[:, :3] = pos @ self.anchor_rot
        self.t_target[self.i_root_q] = self.root_q_cmd

    # ------------------------------------------------------------------------------------------
    # Step
    # ------------------------------------------------------------------------------------------

    def normalize_joints(self, q: torch.Tensor) -> torch.Tensor:
        """Finger joint positions -> [-1, 1] over their limits (the absolute action scale)."""
        return 2.0 * (q - self.lower) / (self.upper - self.lower) - 1.0

    def get_observations(self) -> TensorDict:
        assert self._obs is not None
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        cfg = self.cfg
        actions = actions.to(self.torch_device, torch.float32).clamp(-1.0, 1.0)
        if actions.shape != (self.num_envs, self.num_actions):
            raise ValueError(
                f"actions must have shape ({self.num_envs}, {self.num_actions}), got {tuple(actions.shape)}"
            )
        # Action latency: a world with latency k applies the action of k steps ago.
        hist = (
            torch.cat([actions[:, None], self.action_hist[:, :-1]], dim=1)
            if self.action_hist.shape[1]
            else actions[:, None]
        )
        lat = self.latency.clamp(max=hist.shape[1] - 1)
        applied = hist[torch.arange(self.num_envs), lat]
        if self.residual_base is not None:
            self.residual_base.act()  # advances the rule on the current touch readings
            if cfg.action_mode == "synergy":
                applied = applied @ self.synergy.T
            if cfg.residual_rate > 0.0:
                self.residual = (self.residual + cfg.residual_rate * applied).clamp(-1.0, 1.0)
            else:
                b = cfg.residual_smoothing
                self.residual = b * applied + (1.0 - b) * self.residual
            desired = self.residual_base.target + cfg.residual_scale * self.residual
            desired = torch.minimum(torch.maximum(desired, self.lower), self.upper)
        else:
            desired = self.lower + 0.5 * (applied + 1.0) * (self.upper - self.lower)
        a = cfg.action_smoothing
        self.finger_target = a * desired + (1.0 - a) * self.finger_target
        self.t_target[self.i_finger_q] = self.finger_target
        self.actions = actions
        if self.action_hist.shape[1]:
            self.action_hist = hist

        t = self.episode_length_buf
        self.root_cmd_pos = self._root_command(t + 1)
        self._write_root_targets(self.root_cmd_pos)
        phase = self.phase_of(t + 1)
        push = self._disturbance(t + 1, phase)
        self.t_object_force[:] = push

        self._launch_step()
        self.episode_length_buf = self.episode_length_buf + 1
        t = self.episode_length_buf

        obj_pos, obj_quat, obj_lin, obj_ang = self._object_state()
        finite = torch.isfinite(obj_pos).all(-1) & torch.isfinite(self.t_joint_q[self.i_finger_q]).all(-1)
        rew = self._rewards(obj_pos, obj_lin, obj_ang, finite)
        done, time_out = self._score(t, phase, obj_pos, finite)
        self.episode_return += rew

        extras: dict[str, Any] = {"time_outs": time_out, "log": {}}
        terms = self.t_reward_terms
        for k, name in enumerate(rk.TERM_NAMES):
            extras["log"][f"Reward/{name}"] = terms[:, k].mean()
        finished = torch.nonzero(done).flatten()
        if len(finished):
            episodes = self._episode_records(finished)
            extras["episodes"] = episodes
            for key in ("s_grasp", "s_lift", "s_disturb"):
                extras["log"][f"Metrics/{key}"] = float(np.mean([ep[key] for ep in episodes]))
            self._reset(finished)
        extras["log"]["Env/nonfinite_resets"] = float(self.nonfinite_resets)
        self._obs = self._compute_observations()
        return self._obs, rew, done, extras

    def _disturbance(self, t: torch.Tensor, phase: torch.Tensor) -> torch.Tensor:
        in_push = phase == PHASES.index("disturb")
        k = ((t - self.phase_start["disturb"]).clamp(min=0) // self.steps_per_push).clamp(max=5)
        dir_idx = self.disturb_order[torch.arange(self.num_envs), k]
        dirs = torch.as_tensor(DISTURB_DIRECTIONS, device=self.torch_device)[dir_idx]
        return dirs * self.cfg.phases.disturb_force * in_push[:, None].float()

    def _object_state(self) -> tuple[torch.Tensor, ...]:
        W, tdev = self.num_envs, self.torch_device
        bq = _wp_view(self.state_0.body_q)
        bqd = _wp_view(self.state_0.body_qd)
        pos = bq[self.i_obj_body, :3].clone()
        quat = bq[self.i_obj_body, 3:7].clone()
        lin = bqd[self.i_obj_body, :3].clone()
        ang = bqd[self.i_obj_body, 3:6].clone()
        if self.strain_layout is not None:
            sw = torch.as_tensor(self.soft_worlds, device=tdev)
            pos[sw] = _wp_view(self.pose_buf.com)
            quat[sw] = _wp_view(self.pose_buf.quat)
            lin[sw] = _wp_view(self.pose_buf.lin_vel)
            ang[sw] = _wp_view(self.pose_buf.ang_vel)
        del W
        return pos, quat, lin, ang

    def _soft_scalar(self, buf: wp.array) -> torch.Tensor:
        out = torch.zeros(self.num_envs, device=self.torch_device)
        if self.strain_layout is not None:
            out[torch.as_tensor(self.soft_worlds, device=self.torch_device)] = _wp_view(buf)
        return out

    def _rewards(self, obj_pos, obj_lin, obj_ang, finite) -> torch.Tensor:
        bq = _wp_view(self.state_0.body_q)
        links = bq[self.i_link_bodies, :3]
        r = self.t_rw
        r["alive"][:] = finite.float()
        r["joint_q"][:] = torch.nan_to_num(self.t_joint_q[self.i_finger_q])
        r["joint_qd"][:] = torch.nan_to_num(self.t_joint_qd[self.i_finger_dof])
        r["link_pos"][:] = torch.nan_to_num(links)
        r["object_com"][:] = torch.nan_to_num(obj_pos)
        r["obj_lin_vel"][:] = torch.nan_to_num(obj_lin)
        r["obj_ang_vel"][:] = torch.nan_to_num(obj_ang)
        # Hand-to-table distances: link frame heights above the table minus the finger half-thickness.
        r["env_dist"][:] = torch.nan_to_num(links[..., 2] - self.cfg.sim.table_height - 0.012).clamp(min=0.0)
        r["eps_bar"][:] = (
            self._soft_scalar(self.strain_buf.object_eps) if self.strain_layout is not None else 0.0
        )
        nodes = torch.zeros(self.num_envs, device=self.torch_device)
        if self.strain_layout is not None:
            nodes[torch.as_tensor(self.soft_worlds)] = torch.as_tensor(
                self.strain_layout.node_counts, dtype=torch.float32
            )
        r["node_count"][:] = nodes
        # Rise above the resting height, counted from the lift phase on (the kernel clamps it).
        lifting = self.phase_of(self.episode_length_buf) >= PHASES.index("lift")
        rise = torch.nan_to_num(obj_pos[:, 2] - self.object_start[:, 2])
        r["object_rise"][:] = torch.where(lifting, rise, torch.zeros_like(rise))
        rk.compute_rewards(self.rw_in, self.rw_out)
        total = torch.nan_to_num(self.t_reward_total.clone(), nan=0.0, posinf=0.0, neginf=0.0)
        clip = self.cfg.reward_clip
        return total.clamp(-clip, clip) if clip > 0 else total

    def _score(self, t, phase_before, obj_pos, finite) -> tuple[torch.Tensor, torch.Tensor]:
        """Update the success metrics of every world; return (done, time_out)."""
        ph = self.cfg.phases
        palm = _wp_view(self.state_0.body_q)[self.i_palm, :3]
        rise = obj_pos[:, 2] - self.object_start[:, 2]
        if self.strain_layout is not None:
            self.max_strain = torch.maximum(self.max_strain, self._soft_scalar(self.strain_buf.object_eps))
        # s_grasp: at the end of the grasp phase, a thumb pad and an opposing finger pad in contact.
        end_grasp = t == self.phase_start["lift"]
        f = torch.linalg.norm(self.t_pad_force_true, dim=-1)
        thumb = (f[:, 9:] > GRASP_CONTACT_FORCE).any(-1)
        opposing = (f[:, :9] > GRASP_CONTACT_FORCE).any(-1)
        self.s_grasp = torch.where(end_grasp, thumb & opposing, self.s_grasp)
        # s_lift: raised by lift_height (within tolerance) through the whole hold phase.
        in_hold = (t > self.phase_start["hold"]) & (t <= self.phase_start["disturb"])
        self.lift_ok &= ~(in_hold & (rise < ph.lift_height - LIFT_TOLERANCE))
        # s_disturb: under each push, object motion relative to the palm below the tolerance.
        rel = obj_pos - palm
        k_in = (t - self.phase_start["disturb"] - 1).clamp(min=0) % self.steps_per_push
        in_dist = (t > self.phase_start["disturb"]) & (t <= self.phase_start["release"])
        start_push = in_dist & (k_in == 0)
        self.push_ref = torch.where(start_push[:, None], rel, self.push_ref)
        moved = torch.linalg.norm(rel - self.push_ref, dim=-1)
        self.disturb_ok &= ~(in_dist & (moved > DISTURB_TOLERANCE))

        # Terminations.
        horizontal = torch.linalg.norm(obj_pos[:, :2] - self.object_start[:, :2], dim=-1)
        pushed_off = horizontal > 0.25
        after_lift = t > self.phase_start["hold"]
        dropped = after_lift & (rise < 0.5 * ph.lift_height)
        blowup = torch.linalg.norm(self.t_pad_force_true, dim=-1).max(-1).values > 500.0
        nonfinite = ~finite
        self.nonfinite_resets += int(nonfinite.sum())
        time_out = t >= self.max_episode_length
        done = pushed_off | dropped | blowup | nonfinite | time_out
        for w in torch.nonzero(done & ~time_out).flatten().tolist():
            if self.failure[w] and not nonfinite[w]:
                continue  # evaluation runs on after a failure: keep the first cause
            self.failure[w] = (
                "non-finite state"
                if nonfinite[w]
                else "contact blow-up"
                if blowup[w]
                else "pushed off the table"
                if pushed_off[w]
                else "dropped"
            )
        if self.cfg.eval_mode:
            # Evaluation scores whole episodes: only a broken simulation ends one early.
            done = nonfinite | time_out
        return done, time_out & ~nonfinite

    def _episode_records(self, finished: torch.Tensor) -> list[dict[str, Any]]:
        records = []
        t = self.episode_length_buf
        for w in finished.tolist():
            e = self.world_entries[w]
            reached_hold_end = int(t[w]) >= self.phase_start["disturb"]
            reached_disturb_end = int(t[w]) >= self.phase_start["release"]
            s_lift = bool(self.lift_ok[w]) and reached_hold_end
            s_disturb = s_lift and bool(self.disturb_ok[w]) and reached_disturb_end and self.disturb_dirs > 0
            failure = self.failure[w] or None
            if failure is None:
                failure = (
                    None
                    if s_disturb
                    else "moved under disturbance"
                    if s_lift
                    else "not lifted"
                    if bool(self.s_grasp[w])
                    else "no grasp"
                )
            records.append(
                {
                    "env": w,
                    "object": e.id,
                    "kind": e.kind,
                    "family": e.family,
                    "size_bin": e.size_bin,
                    "grasp_type": GRASP_NAMES[int(self.grasp_id[w])],
                    "s_grasp": bool(self.s_grasp[w]),
                    "s_lift": s_lift,
                    "s_disturb": s_disturb,
                    "failure": failure,
                    "max_strain": float(self.max_strain[w]),
                    "return": float(self.episode_return[w]),
                    "length": int(t[w]),
                    **self.loc_records[w],  # camera perception: the episode's localisation error
                }
            )
        return records

    # ------------------------------------------------------------------------------------------
    # Observations
    # ------------------------------------------------------------------------------------------

    def _compute_observations(self) -> TensorDict:
        W, tdev = self.num_envs, self.torch_device
        t = self.episode_length_buf.float()
        T = float(self.max_episode_length)
        q = torch.nan_to_num(self.t_joint_q[self.i_finger_q])
        qd = torch.nan_to_num(self.t_joint_qd[self.i_finger_dof])
        q_norm = self.normalize_joints(q)
        phase = self.phase_of(self.episode_length_buf)
        parts = []
        if self.cfg.tactile_obs:
            parts += [torch.nan_to_num(self.t_pad_force).reshape(W, -1) / 10.0, self.t_pad_contact]
        parts += [
            q_norm,
            0.1 * qd,
            self.action_hist.reshape(W, -1),
            (t / T)[:, None],
            torch.sin(2.0 * math.pi * t / T)[:, None],
            torch.cos(2.0 * math.pi * t / T)[:, None],
            torch.nn.functional.one_hot(self.grasp_id, len(GRASP_NAMES)).float(),
            torch.nn.functional.one_hot(phase, len(PHASES)).float(),
            (self.root_cmd_pos - self.grasp_palm_pos) * 10.0,
            self.grasp_palm_quat,
        ]
        if self.residual_base is not None:
            # The rule's current targets: what the residual is added to.
            parts.append(self.normalize_joints(self.residual_base.target))
            parts.append(self.residual)  # the residual now applied (per joint)
        policy = torch.cat(parts, dim=-1)

        obj_pos, obj_quat, obj_lin, obj_ang = self._object_state()
        bq = _wp_view(self.state_0.body_q)
        palm = bq[self.i_palm, :3]
        links = bq[self.i_link_bodies, :3]
        dist = torch.linalg.norm(links - obj_pos[:, None], dim=-1)
        eps = (
            self._soft_scalar(self.strain_buf.object_eps)
            if self.strain_layout is not None
            else torch.zeros(W)
        )
        sig = self._soft_scalar(self.strain_buf.sigma) if self.strain_layout is not None else torch.zeros(W)
        priv = torch.cat(
            [
                (obj_pos - palm) * 10.0,
                obj_quat,
                obj_lin,
                0.1 * obj_ang,
                dist * 10.0,
                eps[:, None],
                sig[:, None] * 100.0,
                self.object_mass[:, None],
                self.object_friction[:, None],
                self.object_log_e[:, None] / 6.0,
                torch.nan_to_num(self.t_pad_force_true).reshape(W, -1) / 10.0,
            ],
            dim=-1,
        )
        obs = TensorDict(
            {"policy": torch.nan_to_num(policy), "privileged": torch.nan_to_num(priv)},
            batch_size=[W],
            device=tdev,
        )
        return obs

    # ------------------------------------------------------------------------------------------

    def describe(self) -> dict[str, Any]:
        """Resolved configuration and scene summary (for logs)."""
        return {
            "task": self.task_name,
            "config": asdict(self.cfg),
            "objects": [e.id for e in self.world_entries],
            "max_episode_length": self.max_episode_length,
            "phase_start": self.phase_start,
        }

    def close(self) -> None:
        self.graph = None


os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")
