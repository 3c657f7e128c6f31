"""The environment's per-world state in named parts, each a small dataclass of tensors with a row
per world (``GraspEnv`` holds one of each; the scoring's, the observation's and the reward's own
parts are in their ``mdp`` modules: ``env.scoring``, ``env.observation``, ``env.reward``).

========== ================= ==========================================================================
attribute  part              written by / read by
========== ================= ==========================================================================
``view``   :class:`Views`    torch views of the physics state and the pads' readings (zero-copy)
``index``  :class:`Indices`  each world's finger joints, links, palm and object body in the state
``nominal``:class:`Nominal`  the model's values the episode's randomisation scales (``mdp.events``)
``draw``   :class:`Draw`     the episode's draw and the object's properties (``mdp.events``; the critic)
``grasp``  :class:`Grasp`    the episode's planned grasp (``mdp.events``; the palm path, the rule)
``palm``   :class:`PalmPath` the scripted palm path's endpoints and command (``mdp.events``, ``step``)
``act``    :class:`Actions`  the policy's actions, their history and what they set (``mdp.actions``)
``joints`` :class:`Joints`   the finger joints' limits and the open hand
``record`` :class:`Record`   what an episode's record adds: its return, its strain, its localisation
``kernel`` :class:`Kernel`   what the task's Warp kernels read of every world (made once)
``planning``:class:`Planning` the library's grasps, the planner's override and the pose estimator
========== ================= ==========================================================================
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from d3grasp.dexhand13 import NUM_FINGER_JOINTS, NUM_FINGERS
from d3grasp.envs.sensors import wp_view


@dataclass
class Views:
    """Torch views of the physics state, the drive targets, the push force and the pads' readings
    (``state_0`` is the same object after every control step: an even number of substeps swap it)."""

    joint_q: torch.Tensor
    joint_qd: torch.Tensor
    body_q: torch.Tensor
    body_qd: torch.Tensor
    target: torch.Tensor  # the drives' joint targets
    object_force: torch.Tensor  # the push on each world's object
    pad_force: torch.Tensor  # (W, 11, 3) measured (noise, saturation), every contact
    pad_contact: torch.Tensor
    pad_force_true: torch.Tensor  # without noise or saturation
    pad_force_object: torch.Tensor  # measured, the object's contacts only

    @classmethod
    def of(cls, physics: Any, sensors: Any) -> Views:
        st = physics.state_0
        return cls(
            joint_q=wp_view(st.joint_q),
            joint_qd=wp_view(st.joint_qd),
            body_q=wp_view(st.body_q),
            body_qd=wp_view(st.body_qd),
            target=wp_view(physics.control.joint_target_q),
            object_force=wp_view(physics.object_force),
            pad_force=wp_view(sensors.pad_force),
            pad_contact=wp_view(sensors.pad_contact),
            pad_force_true=wp_view(sensors.pad_force_true),
            pad_force_object=wp_view(sensors.pad_force_object),
        )


@dataclass
class Indices:
    """Each world's entries in the state: finger joint coordinates and dofs, the hand's root
    coordinates, its link bodies, its palm body and the object's body (0 for a soft object)."""

    finger_q: torch.Tensor
    finger_dof: torch.Tensor
    root_q: torch.Tensor
    link_bodies: torch.Tensor
    palm: torch.Tensor
    obj_body: torch.Tensor

    @classmethod
    def of(cls, layout: Any, device: torch.device | str) -> Indices:
        def index(a: np.ndarray) -> torch.Tensor:
            return torch.as_tensor(a, dtype=torch.long, device=device)

        return cls(
            finger_q=index(layout.finger_q),
            finger_dof=index(layout.finger_dof),
            root_q=index(layout.root_q),
            link_bodies=index(layout.link_bodies),
            palm=index(layout.palm_body),
            obj_body=index(np.maximum(layout.object_body, 0)),
        )


@dataclass
class Nominal:
    """The model's values before any episode's draw, which the randomisation scales (``mdp.events``)."""

    tet_materials: np.ndarray | None  # soft objects' (E, nu, damping); None without soft objects
    body_mass: np.ndarray
    body_inv_mass: np.ndarray
    shape_mu: np.ndarray
    ke: np.ndarray  # drive stiffness per dof
    kd: np.ndarray  # drive damping per dof

    @classmethod
    def of(cls, model: Any) -> Nominal:
        return cls(
            tet_materials=model.tet_materials.numpy().copy() if model.tet_count else None,
            body_mass=model.body_mass.numpy().copy(),
            body_inv_mass=model.body_inv_mass.numpy().copy(),
            shape_mu=model.shape_material_mu.numpy().copy(),
            ke=model.joint_target_ke.numpy().copy(),
            kd=model.joint_target_kd.numpy().copy(),
        )


@dataclass
class Draw:
    """Each world's episode draw and its object's manifest properties (what the critic reads)."""

    # Mass (rigid) or Young's modulus (soft) scale, friction scale, drive gain scale, action latency
    # (steps); all 1 / 0 without randomisation.
    dynamics: torch.Tensor
    latency: torch.Tensor  # (W,) long: control steps an action waits
    object_start: torch.Tensor  # (W, 3) where the object was placed
    disturb_order: torch.Tensor  # (W, 6) long: the order of the six pushes
    object_mass: torch.Tensor  # kg, the manifest's
    object_friction: torch.Tensor  # the material's coefficient
    object_log_e: torch.Tensor  # log10 of a soft object's Young's modulus (0 for rigid)
    object_soft: torch.Tensor  # (W,) bool: a FEM soft body

    @classmethod
    def zeros(cls, entries: Sequence[Any], device: torch.device | str) -> Draw:
        W, f32 = len(entries), torch.float32
        return cls(
            dynamics=torch.tensor([[1.0, 1.0, 1.0, 0.0]], device=device).repeat(W, 1),
            latency=torch.zeros(W, dtype=torch.long, device=device),
            object_start=torch.zeros(W, 3, device=device),
            disturb_order=torch.zeros(W, 6, dtype=torch.long, device=device),
            object_mass=torch.as_tensor([e.mass for e in entries], dtype=f32, device=device),
            object_friction=torch.as_tensor(
                [float(e.material.get("friction", 1.0)) for e in entries], dtype=f32, device=device
            ),
            object_log_e=torch.as_tensor(
                [
                    math.log10(float(e.material["youngs_modulus"])) if e.kind == "deformable" else 0.0
                    for e in entries
                ],
                dtype=f32,
                device=device,
            ),
            object_soft=torch.as_tensor([e.kind == "deformable" for e in entries], device=device),
        )


@dataclass
class Grasp:
    """Each world's grasp this episode: its type, the fingers' pre-shape, the palm's grasp pose and
    approach, and what moves a grasp planned at the camera's estimate onto the true pose's."""

    type_id: torch.Tensor  # (W,) long: index into GRASP_TYPES
    preshape: torch.Tensor  # (W, 4) abduction of each finger's first joint (rad)
    palm_pos: torch.Tensor  # (W, 3)
    palm_quat: torch.Tensor  # (W, 4) xyzw
    approach_dir: torch.Tensor  # (W, 3)
    # Palm offset (m) and turn (rad) on the wrist's axes; zero with the oracle pose (mdp.events).
    pose_correction: torch.Tensor
    # The same grasp moved by the camera's centre error only, its yaw kept (m, world): what an object
    # that looks the same turned needs (a cylinder's yaw error moves the grasp by cm).
    centre_correction: torch.Tensor

    @classmethod
    def zeros(cls, num_worlds: int, device: torch.device | str) -> Grasp:
        W = num_worlds
        z = torch.zeros
        return cls(
            type_id=z(W, dtype=torch.long, device=device),
            preshape=z(W, NUM_FINGERS, device=device),
            palm_pos=z(W, 3, device=device),
            palm_quat=z(W, 4, device=device),
            approach_dir=z(W, 3, device=device),
            pose_correction=z(W, 4, device=device),
            centre_correction=z(W, 3, device=device),
        )


@dataclass
class PalmPath:
    """The scripted palm path: the physics' per-world endpoints (views), the step's commanded palm
    position and the hand root's commanded coordinates."""

    pos_start: torch.Tensor
    pos_end: torch.Tensor
    quat: torch.Tensor
    yaw_start: torch.Tensor
    yaw_end: torch.Tensor
    cmd_pos: torch.Tensor  # (W, 3) the palm position commanded this step
    root_q_cmd: torch.Tensor  # the hand root's commanded joint coordinates
    anchor_rot: torch.Tensor  # (3, 3): p_anchor = R_a^T p, as row vectors p @ R_a

    @classmethod
    def of(cls, physics: Any, num_worlds: int, root_coords: int, anchor_rot: torch.Tensor) -> PalmPath:
        dev = anchor_rot.device
        return cls(
            pos_start=wp_view(physics.palm_pos_start),
            pos_end=wp_view(physics.palm_pos_end),
            quat=wp_view(physics.palm_quat),
            yaw_start=wp_view(physics.palm_yaw_start),
            yaw_end=wp_view(physics.palm_yaw_end),
            cmd_pos=torch.zeros(num_worlds, 3, device=dev),
            root_q_cmd=torch.zeros(num_worlds, root_coords, device=dev),
            anchor_rot=anchor_rot,
        )


@dataclass
class Actions:
    """The policy's side: its last actions and their history, the steps since they began to act,
    and what they set (finger targets, the residual on the rule's, the wrist's palm offset)."""

    actions: torch.Tensor  # (W, A) the step's, clamped to [-1, 1]
    history: torch.Tensor  # (W, H, A) the last H, newest last
    decision_age: torch.Tensor  # (W,) long: steps since the actions started to act (decision_steps)
    finger_target: torch.Tensor  # (W, 16) rad
    residual: torch.Tensor  # (W, 16) per joint, in [-1, 1]
    palm_offset: torch.Tensor  # (W, 3) the wrist's offset of the scripted palm path (m)
    palm_yaw: torch.Tensor  # (W,) ... and its turn (rad)
    synergy: torch.Tensor  # the synergy mode's action-to-joint matrix
    open_action: torch.Tensor  # the open hand as an absolute action
    reset_action: torch.Tensor  # what a history starts from: the open hand or the zero residual

    @classmethod
    def zeros(
        cls,
        num_worlds: int,
        num_actions: int,
        history: int,
        synergy: torch.Tensor,
        open_action: torch.Tensor,
        absolute: bool,
    ) -> Actions:
        W, A, dev = num_worlds, num_actions, open_action.device
        return cls(
            actions=torch.zeros(W, A, device=dev),
            history=torch.zeros(W, history, A, device=dev),
            decision_age=torch.zeros(W, dtype=torch.long, device=dev),
            finger_target=torch.zeros(W, NUM_FINGER_JOINTS, device=dev),
            residual=torch.zeros(W, NUM_FINGER_JOINTS, device=dev),
            palm_offset=torch.zeros(W, 3, device=dev),
            palm_yaw=torch.zeros(W, device=dev),
            synergy=synergy,
            open_action=open_action,
            reset_action=open_action if absolute else torch.zeros(A, device=dev),
        )


@dataclass
class Joints:
    """The finger joints' limits (rad) and the open hand: flexion at its lower limit, abduction
    centred (all zeros on DexHand13), the pose the rule-based closing starts from."""

    lower: torch.Tensor
    upper: torch.Tensor
    open_pose: torch.Tensor


@dataclass
class Record:
    """What each world's episode record adds to the scoring's: its return so far, the soft object's
    highest strain and the camera's localisation record (empty at the true pose)."""

    returns: torch.Tensor
    max_strain: torch.Tensor
    localisation: list[dict[str, Any]]

    @classmethod
    def zeros(cls, num_worlds: int, device: torch.device | str) -> Record:
        z = torch.zeros(num_worlds, device=device)
        return cls(returns=z, max_strain=z.clone(), localisation=[{} for _ in range(num_worlds)])


@dataclass
class Kernel:
    """What the task's Warp kernels (reward gather, observations) read of every world, made once:
    ``world`` (``kernels.world_state.WorldArrays``) and the schedule's tables it is made from (kept
    here: a Warp array made from a torch tensor does not own its memory)."""

    tables: dict[str, torch.Tensor]
    world: Any


@dataclass
class Planning:
    """Where each episode's grasp comes from: the library's planned grasps (None: the geometric
    rule), the planner's per-world override while it scores candidates, and the pose estimator
    that tells the planner where the object is (d3grasp.vision.estimators)."""

    plan: dict[str, Any] | None
    override: list | None = None
    estimator: Any = None
