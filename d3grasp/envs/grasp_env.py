"""The reach-grasp-lift-disturb environment: N worlds in one Newton model, an rsl-rl 5.5 VecEnv.

This file wires the parts together; each lives in a file of its own:

- ``scene.py``: the multi-world model from the manifest (objects per world, hand, table);
- ``physics.py``: SolverVBD, the collision pipeline and the substeps of one control step;
- ``sensors.py``: joint readings, tactile pads, strain and the deformable pose (Warp kernels);
- ``script.py``: the episode's phases, the scripted palm path and the pushes;
- ``mdp/actions.py``, ``mdp/observations.py``, ``mdp/rewards.py``, ``mdp/terminations.py`` and
  ``mdp/events.py``: how actions become targets, the observation groups, the reward, success and
  terminations, and the reset with its randomisation.

One control step (60 Hz) runs on the device, captured as one Warp graph: the physics substeps,
then the sensors. The reward terms, the success scoring and the observation groups are Warp kernels
too, each replayed as a graph of its own. The host side (torch) maps actions to joint targets,
commands the palm, fills the kernels' inputs and resets finished worlds.
"""

from __future__ import annotations

import gc
import os
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

import numpy as np
import torch
import warp as wp
from tensordict import TensorDict

from d3grasp.authoring.manifest import resolve_asset_path
from d3grasp.dexhand13 import ABDUCTION_JOINTS
from d3grasp.envs.baseline import RuleBasedController, rest_targets
from d3grasp.envs.config import ACTION_MODES, CLOSING_PRIORS, GRASP_SOURCES, PERCEPTION_MODES, GraspEnvConfig
from d3grasp.envs.grasp_file import environment_record, load_grasp_plan, warn_changed_settings, without_prior
from d3grasp.envs.mdp import actions as mdp_actions
from d3grasp.envs.mdp import events, observations, rewards, terminations
from d3grasp.envs.parts import (
    Actions,
    Draw,
    Grasp,
    Indices,
    Joints,
    Kernel,
    Nominal,
    PalmPath,
    Planning,
    Record,
    Views,
)
from d3grasp.envs.physics import Physics
from d3grasp.envs.scene import (
    HAND_ANCHOR_QUAT,
    apply_soft_damping,
    build_scene,
    select_world_objects,
)
from d3grasp.envs.script import EpisodeScript
from d3grasp.envs.sensors import Sensors
from d3grasp.geometry import quat_xyzw_to_matrix
from d3grasp.kernels import world_state as ws
from d3grasp.vision.estimators import EstimatorScene, estimator_name, make_pose_estimator
from d3grasp.vocabulary import GRASP_TYPES, METRICS, PHASES

__all__ = ["PHASES", "GraspEnv"]


class GraspEnv:
    """Vectorised D3Grasp environment (rsl-rl ``VecEnv`` interface, duck-typed)."""

    def __init__(self, cfg: GraspEnvConfig, task_name: str = "") -> None:
        self.cfg = cfg
        self.task_name = task_name
        self.num_envs = int(cfg.num_envs)
        _check_config(cfg, self.num_envs)
        self.num_actions = mdp_actions.num_actions(cfg)
        self.wp_device = wp.get_device("cpu" if cfg.device == "cpu" else cfg.device)
        self.torch_device = torch.device(cfg.device)
        self.rng = np.random.default_rng(cfg.seed)
        self.script = EpisodeScript(cfg.phases, cfg.sim.control_hz, cfg.eval_mode, cfg.obs.clock_period)
        self.max_episode_length = self.script.max_episode_length

        self.manifest_path, self.world_entries = select_world_objects(cfg.objects, self.num_envs, self.rng)
        # Grasps: the library's grasp file (the planner's measured grasps per object), if it has one
        # and the config asks for it; the planner itself sets a per-world override to score candidates.
        self.planning = Planning(load_grasp_plan(self.manifest_path) if cfg.grasp_source == "file" else None)
        if self.planning.plan:
            current = without_prior(environment_record(cfg.sim, cfg.rule))
            warn_changed_settings(self.planning.plan, self.world_entries, current)
        self._build()
        self._allocate_buffers()
        # What the planner is told of each placed object: the true pose or the camera's estimate
        # (vision/estimators.py).
        scene = EstimatorScene(
            self.model, self.layout, [e.id for e in self.world_entries], cfg.camera, cfg.seed
        )
        name = estimator_name(cfg.perception, cfg.camera.register_footprint, cfg.pose_estimator)
        self.planning.estimator = make_pose_estimator(name, scene)
        # Residual modes: the rule-based controller runs inside the env and the policy's actions are
        # offsets on its joint targets.
        self.residual_base = None
        if cfg.action_mode in ("residual", "synergy"):
            self.residual_base = RuleBasedController(self)
        observations.allocate(self)
        # Place every world before the first (uncaptured) step, so nothing starts interpenetrating.
        self.reset_all()
        self.physics.capture(self._control_step)
        self.reset_all()

    # ------------------------------------------------------------------------------------------
    # Construction
    # ------------------------------------------------------------------------------------------

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
        model = self.model
        model.soft_contact_ke = sim.soft_contact_ke
        model.soft_contact_kd = sim.soft_contact_kd
        model.soft_contact_mu = sim.soft_contact_mu
        apply_soft_damping(model, self.layout, sim.soft_damping)
        # What the per-episode randomisation scales (events.py).
        self.nominal = Nominal.of(model)
        self.physics = Physics(model, self.layout, sim, self.wp_device)
        self.sensors = Sensors(model, self.layout, self.cfg, self.wp_device)

    def _allocate_buffers(self) -> None:
        tdev, lay, f32 = self.torch_device, self.layout, torch.float32
        ph, se = self.physics, self.sensors
        self.view = Views.of(ph, se)  # torch views of device arrays (zero-copy)
        self.index = Indices.of(lay, tdev)
        lower = torch.as_tensor(lay.finger_lower, dtype=f32, device=tdev)
        upper = torch.as_tensor(lay.finger_upper, dtype=f32, device=tdev)
        self.joints = Joints(lower, upper, rest_targets(lower, upper))
        self._allocate_episode_buffers()  # the scoring's state among them
        self._allocate_kernel_tables()
        rewards.allocate(self)

    def _allocate_kernel_tables(self) -> None:
        """What the task's Warp kernels (reward gather, observations) read of every world, made once
        (``kernels.world_state.WorldArrays``): the state, each world's finger joints, links, palm,
        object body and soft-object slot, the soft objects' pose and strain, the lift starts (the
        scoring's) and the schedule's phase table; with the schedule's clock table."""
        lay, se, dev, ph = self.layout, self.sensors, self.wp_device, self.physics

        def index(a: np.ndarray) -> wp.array:
            return wp.array(np.asarray(a, dtype=np.int32), dtype=wp.int32, device=dev)

        def soft(buf, name: str, dtype=float) -> wp.array:  # one-element stand-in without soft objects
            return (
                getattr(buf, name) if se.strain_layout is not None else wp.zeros(1, dtype=dtype, device=dev)
            )

        tab = self.script.tables(self.torch_device)
        # Kept here: a Warp array made from a torch tensor does not own its memory.
        tables = {"phase": tab.phase.to(torch.int32), "clock": tab.clock.contiguous()}
        wa = ws.WorldArrays()
        wa.joint_q, wa.joint_qd = ph.state_0.joint_q, ph.state_0.joint_qd
        wa.body_q, wa.body_qd = ph.state_0.body_q, ph.state_0.body_qd
        wa.finger_q, wa.finger_dof = index(lay.finger_q), index(lay.finger_dof)
        wa.link_bodies, wa.palm_body = index(lay.link_bodies), self.scoring.inputs.palm_body  # one palm index
        wa.object_body, wa.soft_slot = index(np.maximum(lay.object_body, 0)), index(se.world_soft_slot)
        pose = getattr(se, "pose_buf", None)
        wa.soft_com, wa.soft_quat = soft(pose, "com", wp.vec3), soft(pose, "quat", wp.quat)
        wa.soft_lin_vel, wa.soft_ang_vel = soft(pose, "lin_vel", wp.vec3), soft(pose, "ang_vel", wp.vec3)
        strain = getattr(se, "strain_buf", None)
        wa.soft_eps, wa.soft_sigma = soft(strain, "object_eps"), soft(strain, "sigma")
        wa.soft_node_count = soft(se.strain_layout, "object_node_count")
        wa.lift_start = self.scoring.state.lift_start
        wa.phase = wp.from_torch(tables["phase"])
        wa.last_row = self.script.max_episode_length + 1
        self.kernel = Kernel(tables, wa)

    def _allocate_episode_buffers(self) -> None:
        W, A, tdev = self.num_envs, self.num_actions, self.torch_device
        self.episode_length_buf = torch.zeros(W, dtype=torch.long, device=tdev)
        self.act = Actions.zeros(
            W,
            A,
            self.cfg.obs.action_history,
            mdp_actions.synergy_matrix(tdev),
            self.normalize_joints(self.joints.open_pose),
            absolute=self.cfg.action_mode == "absolute",
        )
        self.draw = Draw.zeros(self.world_entries, tdev)
        self.grasp = Grasp.zeros(W, tdev)
        anchor = torch.as_tensor(quat_xyzw_to_matrix(HAND_ANCHOR_QUAT), dtype=torch.float32, device=tdev)
        self.palm = PalmPath.of(self.physics, W, self.layout.root_q.shape[1], anchor)
        self.record = Record.zeros(W, tdev)
        self._obs: TensorDict | None = None
        # The scoring's state (lift start, s_grasp, s_lift, s_disturb, failure causes, ...) as torch
        # views of the scoring kernel's buffers: written in place only.
        terminations.allocate(self)

    # ------------------------------------------------------------------------------------------
    # The parts, by the names the rest of the package reads
    # ------------------------------------------------------------------------------------------

    @property
    def device(self) -> str:
        """The configured device (rsl-rl's VecEnv reads it)."""
        return self.cfg.device

    @property
    def dt(self) -> float:
        """Seconds of one control step."""
        return 1.0 / self.cfg.sim.control_hz

    @property
    def state_0(self):
        return self.physics.state_0

    @property
    def control(self):
        return self.physics.control

    @property
    def solver(self):
        return self.physics.solver

    @property
    def contacts(self):
        return self.physics.contacts

    @property
    def observables(self):
        return self.physics.observables

    @property
    def graph(self):
        return self.physics.graph

    @property
    def nonfinite_resets(self) -> int:
        """Worlds reset for a non-finite state since the environment was made."""
        return int(self.scoring.now.nonfinite_count[0])

    def phase_of(self, t: torch.Tensor) -> torch.Tensor:
        """Phase index (into :data:`PHASES`) of every world at step ``t`` (its own lift start)."""
        return self.script.phase_of(t, self.scoring.now.lift_start)

    def action_takes_effect(self) -> torch.Tensor:
        """(W,) bool: whether the action of the coming step moves anything. In the residual modes the
        actions are ignored before ``residual_start`` (the residual is held at 0 there), and with
        ``decision_steps`` k > 1 only every k-th action from there on is taken (and held); PPO leaves
        the other steps out of its policy loss (d3grasp.train.ppo)."""
        if self.residual_base is None:  # absolute mode: every action acts (mdp.actions.hold_decisions)
            return torch.ones(self.num_envs, dtype=torch.bool, device=self.torch_device)
        return mdp_actions.acting(self) & (self.act.decision_age % self.cfg.decision_steps == 0)

    def open_pose_of(self, worlds: torch.Tensor) -> torch.Tensor:
        """(len(worlds), 16) the open hand of each world: the rule's rest pose with the abduction
        joints at the world's grasp pre-shape."""
        pose = self.joints.open_pose.expand(len(worlds), -1).clone()
        pose[:, list(ABDUCTION_JOINTS)] = torch.minimum(
            torch.maximum(self.grasp.preshape[worlds], self.joints.lower[list(ABDUCTION_JOINTS)]),
            self.joints.upper[list(ABDUCTION_JOINTS)],
        )
        return pose

    def normalize_joints(self, q: torch.Tensor) -> torch.Tensor:
        """Finger joint positions -> [-1, 1] over their limits (the absolute action scale)."""
        return 2.0 * (q - self.joints.lower) / (self.joints.upper - self.joints.lower) - 1.0

    def object_state(self) -> tuple[torch.Tensor, ...]:
        """Every world's object position, orientation (xyzw), linear and angular velocity."""
        return self.sensors.object_state(self.view.body_q, self.view.body_qd, self.index.obj_body)

    # ------------------------------------------------------------------------------------------
    # The control step
    # ------------------------------------------------------------------------------------------

    def _sense(self) -> None:
        self.sensors.update(self.state_0, self.contacts, self.observables)

    def _control_step(self) -> None:
        self.physics.substeps()
        self._sense()

    # A caller's launch of the control step inside ``step`` (None: the env's own, ``launch_step``). It
    # must launch the same kernels in the same order as the captured graph, physics substeps then
    # sensors (``physics.substeps()``, ``sensors.update(...)``), so the episode stays the env's; the
    # env benchmark sets one that runs them as two graphs and times each.
    step_launcher: Callable[[], None] | None = None

    def launch_step(self) -> None:
        """One control step of the physics and the sensors (the captured graph, or the kernels one by
        one without ``sim.use_graph``): what ``step`` launches between the actions and the rewards."""
        self.physics.launch(self._control_step)

    def _launch_step(self) -> None:
        (self.step_launcher or self.launch_step)()

    def _command_palm(self, pos: torch.Tensor) -> None:
        if self.layout.kinematic_palm:
            # The captured substeps move the palm from its current position to ``pos``.
            self.palm.pos_start[:] = self.view.body_q[self.index.palm, :3]
            self.palm.pos_end[:] = pos
            self.palm.quat[:] = self.grasp.palm_quat
            self.palm.yaw_start[:] = self.palm.yaw_end
            self.palm.yaw_end[:] = self.act.palm_yaw
            return
        # The orientation is fixed per episode (root angles set at reset); the prismatic part of the
        # root chain is the palm position expressed in the anchor frame.
        self.palm.root_q_cmd[:, :3] = pos @ self.palm.anchor_rot
        self.view.target[self.index.root_q] = self.palm.root_q_cmd

    # ------------------------------------------------------------------------------------------
    # VecEnv
    # ------------------------------------------------------------------------------------------

    def reset_all(self) -> None:
        self.reset_worlds(torch.arange(self.num_envs, device=self.torch_device))
        self._obs = observations.compute_observations(self)

    def reset_worlds(self, env_ids: torch.Tensor) -> None:
        """Start new episodes in ``env_ids`` (their observations follow with the next step)."""
        events.reset_worlds(self, env_ids)

    def get_observations(self) -> TensorDict:
        assert self._obs is not None
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        actions = actions.to(self.torch_device, torch.float32).clamp(-1.0, 1.0)
        if actions.shape != (self.num_envs, self.num_actions):
            raise ValueError(
                f"actions must have shape ({self.num_envs}, {self.num_actions}), got {tuple(actions.shape)}"
            )
        mdp_actions.apply_actions(self, actions)
        t = self.episode_length_buf
        self.palm.cmd_pos = (
            self.script.palm_command(
                t + 1, self.grasp.palm_pos, self.grasp.approach_dir, self.scoring.now.lift_start
            )
            + self.act.palm_offset
        )
        self._command_palm(self.palm.cmd_pos)
        # The push tests an object the hand holds: once it has failed the lift or left the grip under
        # a push its test is over and the push stops. Pushed on, a lost 1.5 g sponge (sponge_cube_s)
        # reached kilometres in the remaining pushes and the simulation broke (measured).
        push = self.script.disturbance(t + 1, self.draw.disturb_order)
        self.view.object_force[:] = push * (self.scoring.now.lift_ok & self.scoring.now.disturb_ok)[:, None]

        self._launch_step()
        self.episode_length_buf = self.episode_length_buf + 1

        # The reward's launches gather the state the scoring reads too (step, object, finiteness).
        rew = rewards.compute_rewards(self)
        done = terminations.score(self)
        self.record.returns += rew

        # No step is a time-out for PPO: the episode's horizon is fixed and its clock observed, so
        # its end (the scored last push) is a true terminal. Reported as a time-out, rsl-rl added
        # gamma * V(s) to the last reward, a bootstrap past the outcome that had just been scored.
        extras: dict[str, Any] = {"time_outs": torch.zeros_like(done), "log": rewards.reward_log(self)}
        finished = torch.nonzero(done).flatten()
        if len(finished):
            episodes = terminations.episode_records(self, finished)
            extras["episodes"] = episodes
            extras["log"].update(rewards.pay_episode_terms(self, rew, finished, episodes))
            for key in METRICS:
                extras["log"][f"Metrics/{key}"] = float(np.mean([ep[key] for ep in episodes]))
            self.reset_worlds(finished)
        extras["log"]["Env/nonfinite_resets"] = float(self.nonfinite_resets)
        self._obs = observations.compute_observations(self)
        return self._obs, rew, done, extras

    # ------------------------------------------------------------------------------------------

    def describe(self) -> dict[str, Any]:
        """Resolved configuration and scene summary (for logs)."""
        return {
            "task": self.task_name,
            "config": asdict(self.cfg),
            "objects": [e.id for e in self.world_entries],
            "max_episode_length": self.max_episode_length,
            "phase_start": self.script.phase_start,
        }

    def close(self) -> None:
        """Free the worlds now: the model, states, graphs, buffers and controllers are let go. A
        closed env keeps only what says which it was (config, task, sizes, objects); it cannot step.

        The env's parts refer back to it (the rule's controller, the task kernels' launch closures)
        and to each other (Newton's model and solver), so a closed env lived on until Python's next
        full garbage collection, which came every 4 to 7 rebuilds: rebuilding 16 worlds as the soak
        and training do, up to 7 closed envs were alive at once and the RSS rose 746 -> 962 MB over
        14 builds (measured). Hence the parts are let go here (the caller may still hold the env,
        as the training runner does while it builds the next) and collected at once (~0.4 s): the
        same 14 builds then go 746 -> 774 MB, level from the sixth."""
        keep = {
            "cfg", "task_name", "num_envs", "num_actions", "wp_device", "torch_device",
            "max_episode_length", "manifest_path", "world_entries",
        }  # fmt: skip
        for name in [n for n in vars(self) if n not in keep]:
            delattr(self, name)
        gc.collect()


def _check_config(cfg: GraspEnvConfig, num_envs: int) -> None:
    """One-line errors for settings the environment cannot run."""
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    for g in cfg.grasp_types:
        if g not in GRASP_TYPES:
            raise ValueError(f"unknown grasp type '{g}'; known: {list(GRASP_TYPES)}")
    if cfg.action_mode not in ACTION_MODES:
        raise ValueError(f"unknown action_mode '{cfg.action_mode}'; known: {list(ACTION_MODES)}")
    if not 0.0 < cfg.residual_smoothing <= 1.0:
        raise ValueError(f"residual_smoothing must be in (0, 1], got {cfg.residual_smoothing}")
    if not 0.0 <= cfg.residual_rate <= 1.0:
        raise ValueError(f"residual_rate must be in [0, 1], got {cfg.residual_rate}")
    if (
        min(cfg.palm_offset_limit, cfg.palm_yaw_limit) < 0.0
        or min(cfg.palm_offset_rate, cfg.palm_yaw_rate) <= 0.0
    ):
        raise ValueError("palm_offset_limit and palm_yaw_limit must be >= 0, the palm rates > 0")
    if mdp_actions.has_wrist(cfg) and (cfg.action_mode == "absolute" or not cfg.sim.kinematic_palm):
        raise ValueError(
            "a wrist (palm_offset_limit, palm_yaw_limit) needs a residual action mode and sim.kinematic_palm"
        )
    if cfg.decision_steps < 1:
        raise ValueError(f"decision_steps must be >= 1, got {cfg.decision_steps}")
    if cfg.residual_penalty < 0.0:
        raise ValueError(f"residual_penalty must be >= 0, got {cfg.residual_penalty}")
    if cfg.residual_start not in PHASES:
        raise ValueError(f"unknown residual_start '{cfg.residual_start}'; phases: {list(PHASES)}")
    if cfg.grasp_source not in GRASP_SOURCES:
        raise ValueError(f"unknown grasp_source '{cfg.grasp_source}'; known: {list(GRASP_SOURCES)}")
    if cfg.perception not in PERCEPTION_MODES:
        raise ValueError(f"unknown perception '{cfg.perception}'; known: {list(PERCEPTION_MODES)}")
    estimator_name(cfg.perception, cfg.camera.register_footprint, cfg.pose_estimator)  # a known one
    if cfg.rule.stop_on not in CLOSING_PRIORS:
        raise ValueError(f"unknown rule.stop_on '{cfg.rule.stop_on}'; known: {list(CLOSING_PRIORS)}")


os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")
