"""What the worlds sense after each control step, through the Warp kernels: joint readings, the
11 pads' three-axis forces (as the sensor reports them and as they truly are), and for soft
objects the nodal strain and the deformable pose of the paper's adaptive rotation."""

from __future__ import annotations

import newton
import numpy as np
import torch
import warp as wp

from d3grasp.dexhand13 import NUM_PADS
from d3grasp.envs.config import GraspEnvConfig
from d3grasp.envs.scene import OBJECT_SOFT, SceneLayout
from d3grasp.kernels import rotation as rot_k
from d3grasp.kernels import strain as strain_k
from d3grasp.kernels import tactile as tac_k


def wp_view(a: wp.array) -> torch.Tensor:
    """A zero-copy torch view of a Warp array."""
    return wp.to_torch(a, requires_grad=False)


class Sensors:
    """Tactile pads of every world and the strain and pose of every soft object."""

    def __init__(
        self, model: newton.Model, layout: SceneLayout, cfg: GraspEnvConfig, device: wp.context.Device
    ):
        self.model, self.layout, self.device = model, layout, device
        self.dt = 1.0 / cfg.sim.control_hz
        W = layout.num_worlds
        # Tactile layout: pad slots of the pad shapes, pad frame = pad collider frame (the collider
        # has no rotation inside its pad frame prim).
        shape_pad = np.full(model.shape_count, -1, dtype=np.int64)
        for w in range(W):
            shape_pad[layout.pad_shapes[w]] = np.arange(NUM_PADS)
        shape_is_object = np.zeros(model.shape_count, dtype=bool)
        for shapes in layout.object_shapes:
            shape_is_object[shapes] = True
        st = model.shape_transform.numpy()
        self.tactile_layout = tac_k.TactileLayout.from_arrays(
            shape_pad,
            model.shape_world.numpy(),
            model.shape_body.numpy(),
            st[:, 3:7],
            W,
            device=device,
            shape_is_object=shape_is_object,
        )
        self.tactile_layout.set_noise_seed(cfg.seed)
        rnd = cfg.randomization
        self.tactile_cfg = tac_k.TactileConfig(
            saturation=cfg.tactile.saturation,
            noise_std=rnd.tactile_noise_std if rnd.enabled else 0.0,
            contact_threshold=cfg.tactile.contact_threshold,
        )
        # The truth behind the readings (no saturation, no noise), every contact: the privileged
        # observation and the blow-up check.
        self.true_tactile_cfg = tac_k.TactileConfig(
            saturation=(0.0, 0.0, 0.0), noise_std=0.0, contact_threshold=cfg.tactile.contact_threshold
        )
        self.pad_world_force = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=device)
        self.pad_force = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=device)
        self.pad_contact = wp.zeros((W, NUM_PADS), dtype=float, device=device)
        self.pad_force_true = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=device)
        self.pad_contact_true = wp.zeros((W, NUM_PADS), dtype=float, device=device)
        # The pads' touch of the object alone (contacts with the table or the hand left out), true
        # values in the pad frames: what s_grasp, the closing rule, the lift trigger and the contact
        # and symmetry rewards read.
        self.pad_object_world_force = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=device)
        self.pad_force_object = wp.zeros((W, NUM_PADS), dtype=wp.vec3, device=device)
        self.pad_contact_object = wp.zeros((W, NUM_PADS), dtype=float, device=device)

        # Soft objects: strain / pose layout with one object slot per soft world.
        soft_worlds = np.nonzero(layout.object_kind == OBJECT_SOFT)[0]
        self.soft_worlds = soft_worlds
        self.world_soft_slot = np.full(W, -1, dtype=np.int64)
        self.world_soft_slot[soft_worlds] = np.arange(len(soft_worlds))
        self.strain_layout = None
        if len(soft_worlds):
            tets = model.tet_indices.numpy()
            tet_obj = np.empty(len(tets), dtype=np.int64)
            for slot, w in enumerate(soft_worlds):
                tet_obj[layout.tet_start[w] : layout.tet_start[w] + layout.tet_count[w]] = slot
            self.strain_layout = strain_k.StrainLayout.from_arrays(
                layout.rest_particle_q, tets, tet_obj, object_world=soft_worlds, device=device
            )
            self.strain_buf = strain_k.StrainBuffers.allocate(self.strain_layout)
            self.pose_buf = rot_k.ObjectPoseBuffers.allocate(self.strain_layout, model.particle_mass)
        # Made once: a torch tensor or view per step is a conversion that costs more than the read.
        self.t_soft_worlds = torch.as_tensor(soft_worlds, dtype=torch.long, device=wp.device_to_torch(device))
        if self.strain_layout is not None:
            pb = self.pose_buf
            self.t_pose = tuple(wp_view(a) for a in (pb.com, pb.quat, pb.lin_vel, pb.ang_vel))

    def update(self, state: newton.State, contacts: newton.Contacts, observables) -> None:
        """Read every sensor from the state after a control step (Warp launches only: capturable)."""
        newton.eval_ik(self.model, state, state.joint_q, state.joint_qd)
        cf = observables.contact_f
        tac_k.accumulate_pad_forces(self.tactile_layout, contacts, cf, self.pad_world_force)
        tac_k.accumulate_pad_forces(
            self.tactile_layout, contacts, cf, self.pad_object_world_force, object_only=True
        )
        for cfg, world_force, force, contact in (
            (self.tactile_cfg, self.pad_world_force, self.pad_force, self.pad_contact),
            (self.true_tactile_cfg, self.pad_world_force, self.pad_force_true, self.pad_contact_true),
            (
                self.true_tactile_cfg,
                self.pad_object_world_force,
                self.pad_force_object,
                self.pad_contact_object,
            ),
        ):
            tac_k.pad_frame_forces(self.tactile_layout, world_force, state.body_q, cfg, force, contact)
        if self.strain_layout is not None:
            strain_k.compute_strain(self.strain_layout, state.particle_q, self.strain_buf)
            strain_k.compute_sigma(self.strain_layout, state.particle_q, self.strain_buf)
            rot_k.compute_object_pose(
                self.strain_layout, state.particle_q, self.strain_buf.sigma, self.pose_buf
            )
            rot_k.update_object_velocity(self.pose_buf, self.dt)

    def restart_soft_objects(
        self, particle_q_host: np.ndarray, state: newton.State, worlds: np.ndarray
    ) -> None:
        """A new episode's reference nodes (the placed rest shape) and pose history for ``worlds``."""
        if self.strain_layout is None:
            return
        self.strain_layout.rest_points.assign(particle_q_host.astype(np.float32))
        slots = self.world_soft_slot[worlds]
        slots = slots[slots >= 0]
        if len(slots):
            rot_k.compute_object_pose(
                self.strain_layout, state.particle_q, self.strain_buf.sigma, self.pose_buf
            )
            m = np.zeros(self.strain_layout.object_count, dtype=np.int32)
            m[slots] = 1
            rot_k.reset_object_history(self.pose_buf, wp.array(m, dtype=wp.int32, device=self.device))

    def soft_scalar(self, buf: wp.array) -> torch.Tensor:
        """A per-soft-object quantity spread onto all worlds (0 where the object is rigid)."""
        out = torch.zeros(self.layout.num_worlds, device=self.t_soft_worlds.device)
        if self.strain_layout is not None:
            out[self.t_soft_worlds] = wp_view(buf)
        return out

    def object_state(
        self, body_q: torch.Tensor, body_qd: torch.Tensor, object_body: torch.Tensor
    ) -> tuple[torch.Tensor, ...]:
        """Every world's object position, orientation (xyzw), linear and angular velocity (W, ...):
        the body's for a rigid object (from the state's ``body_q`` and ``body_qd`` views), the
        deformable pose's for a soft one."""
        # Indexing by a tensor copies: the views of the copies below never alias the state.
        q, qd = body_q[object_body], body_qd[object_body]
        pos, quat, lin, ang = q[:, :3], q[:, 3:7], qd[:, :3], qd[:, 3:6]
        if self.strain_layout is not None:
            sw = self.t_soft_worlds
            for out, view in zip((pos, quat, lin, ang), self.t_pose, strict=True):
                out[sw] = view
        return pos, quat, lin, ang
