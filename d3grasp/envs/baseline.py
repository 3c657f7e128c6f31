"""The paper's rule-based baseline: joints close at constant speed until the pads feel the object.

From the start of the grasp phase every flexion joint of the fingers the grasp type uses advances
its target at ``close_speed`` (rad/s). A joint stops advancing once a pad on its own link or on a
link distal to it reads more than ``force_threshold`` (N): a finger whose proximal link meets the
object keeps curling its distal links around it, one whose tip meets it stops entirely. This is
the "close at constant speed until the pads exceed a force threshold" rule applied per joint,
which is what an under-actuated gripper does mechanically; ``per_joint=False`` stops a whole
finger at its first touch instead. A stopped joint keeps a small extra squeeze (``squeeze`` rad
beyond where it stopped, i.e. ``squeeze * ke`` of drive torque; ``squeeze_deformable`` on a soft
object) and holds it through lift, hold and disturbance. Abduction joints stay at the middle of
their range; fingers the grasp type does not use stay open. The thumb's first flexion link carries
no pad: its joint stops with the thumb's pads.

:func:`rule_step` is the rule as a function of tensors (pad forces, joint positions, whether the
hand is closing, the grasp type) with its state in :class:`RuleState`; it knows nothing of the
environment. :class:`RuleBasedController` runs it on an environment's sensor readings and acts
through the same interface as a policy (normalised joint targets), so it runs wherever a policy
does. It reads the pad sensors directly rather than the observation (a policy's observation may
leave touch out; the Base ablation's env sets ``rule.stop_on`` "stall", and its rule reads no pad).
It reads the pads' contacts with the object only (``Sensors.pad_force_object``): each finger stops
on the object, not on the table (measured before: a fingertip pressing the table stopped its finger
in about a fifth of the failed train-split grasps, with no force on the object at all).

``stop_on="stall"`` is the rule without touch, the closing prior of the paper's Base ablation
(proprioception only): a joint stops where its drive lags its target by more than ``stall_lag``,
i.e. where something holds the link back, whatever touches it. Free closing at ``close_speed``
1.5 rad/s lags ~0.05 rad (measured on the test split's first 8 rigid objects: 0.05 rad at
1.1-1.2 rad/s of joint speed); the default 0.8 rad was chosen on the train split
(``BaselineConfig.stall_lag``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from d3grasp.dexhand13 import (
    ABDUCTION_JOINTS,
    FINGER_PADS,
    FLEXION_JOINTS,
    JOINTS_PER_FINGER,
    NUM_FINGER_JOINTS,
    NUM_PADS,
    PAD_LINK,
    finger_joints,
)
from d3grasp.envs.config import BaselineConfig
from d3grasp.envs.grasps import GRASPS
from d3grasp.vocabulary import GRASP_TYPES, PHASES


def stop_matrix(per_joint: bool = True) -> torch.Tensor:
    """(16, 11) bool: which pads stop which finger joint (abduction joints never stop: never advance)."""
    s = torch.zeros(NUM_FINGER_JOINTS, NUM_PADS, dtype=torch.bool)
    for f, pads in enumerate(FINGER_PADS):
        for j in range(1, JOINTS_PER_FINGER):
            for p in pads:
                if not per_joint or PAD_LINK[p] >= j:
                    s[JOINTS_PER_FINGER * f + j, p] = True
    return s


def grasp_closing_joints() -> torch.Tensor:
    """(grasp types, 16) bool: the flexion joints each grasp type closes (its ``baseline_fingers``)."""
    uses = torch.zeros(len(GRASP_TYPES), NUM_FINGER_JOINTS, dtype=torch.bool)
    for g, name in enumerate(GRASP_TYPES):
        for f in GRASPS[name].baseline_fingers:
            uses[g, list(finger_joints(f))] = True
    flex = torch.zeros(NUM_FINGER_JOINTS, dtype=torch.bool)
    flex[list(FLEXION_JOINTS)] = True
    return uses & flex


def rest_targets(lower: torch.Tensor, upper: torch.Tensor) -> torch.Tensor:
    """(16,) the open hand the rule starts from: flexion at the lower limit, abduction centred."""
    rest = lower.clone()
    abd = list(ABDUCTION_JOINTS)
    rest[abd] = (0.5 * (lower + upper))[abd]
    return rest


def rule_settled(state: RuleState, tables: RuleTables, grasp_id: torch.Tensor) -> torch.Tensor:
    """(W,) bool: every joint the world's grasp type closes has stopped on touch: the hand has closed
    as far as the object lets it."""
    uses = tables.grasp_uses[grasp_id]
    return (state.stopped | ~uses).all(-1)


@dataclass
class RuleState:
    """Per world: the joint targets and which joints have stopped on touch."""

    target: torch.Tensor  # (W, 16) rad
    stopped: torch.Tensor  # (W, 16) bool

    @classmethod
    def open(cls, num_worlds: int, rest: torch.Tensor) -> RuleState:
        return cls(
            target=rest.expand(num_worlds, -1).clone(),
            stopped=torch.zeros(num_worlds, NUM_FINGER_JOINTS, dtype=torch.bool, device=rest.device),
        )

    def restart(self, worlds: torch.Tensor, rest: torch.Tensor) -> None:
        self.target[worlds] = rest
        self.stopped[worlds] = False


@dataclass(frozen=True)
class RuleTables:
    """The rule's fixed tables on a device: what stops what, and what each grasp type closes."""

    stops: torch.Tensor  # (16, 11) float
    grasp_uses: torch.Tensor  # (grasp types, 16) bool
    upper: torch.Tensor  # (16,) joint upper limits

    @classmethod
    def make(cls, cfg: BaselineConfig, upper: torch.Tensor) -> RuleTables:
        dev = upper.device
        return cls(stop_matrix(cfg.per_joint).to(dev).float(), grasp_closing_joints().to(dev), upper)


def squeeze_per_world(cfg: BaselineConfig, object_soft: torch.Tensor) -> torch.Tensor:
    """(W, 1) rad of squeeze beyond the stopping point: ``squeeze_deformable`` where ``object_soft``
    (W,) bool, else ``squeeze``."""
    squeeze = torch.where(object_soft, cfg.squeeze_deformable, cfg.squeeze)
    return squeeze.to(torch.float32)[:, None]


def rule_step(
    state: RuleState,
    tables: RuleTables,
    cfg: BaselineConfig,
    pad_force: torch.Tensor,
    joint_q: torch.Tensor,
    closing: torch.Tensor,
    grasp_id: torch.Tensor,
    dt: float,
    object_soft: torch.Tensor | None = None,
) -> torch.Tensor:
    """Advance the rule by one control step of ``dt`` s and return the joint targets (W, 16).

    ``pad_force`` (W, 11, 3) the pad readings (N; unread with ``cfg.stop_on`` "stall"), ``joint_q``
    (W, 16) the joint positions,
    ``closing`` (W,) whether the grasp phase has begun, ``grasp_id`` (W,) the grasp type,
    ``object_soft`` (W,) bool which worlds hold a soft object (None: none).
    """
    if cfg.stop_on == "stall":
        # Held back: the drive lags its target by more than free closing does. No pad is read.
        touched = state.target - joint_q > cfg.stall_lag
    else:
        force = torch.linalg.norm(pad_force, dim=-1)  # (W, 11)
        touched = (force > cfg.force_threshold).float() @ tables.stops.T > 0  # (W, 16)
    uses = tables.grasp_uses[grasp_id]
    newly = touched & uses & ~state.stopped & closing[:, None]
    if newly.any():
        # Hold a stopping joint where it is now, plus the squeeze.
        if object_soft is None:
            squeeze: torch.Tensor | float = cfg.squeeze
        else:
            squeeze = squeeze_per_world(cfg, object_soft.to(joint_q.device))
        squeezed = torch.minimum(joint_q + squeeze, tables.upper)
        state.target = torch.where(newly, squeezed, state.target)
    state.stopped |= newly
    advance = closing[:, None] & uses & ~state.stopped
    step = cfg.close_speed * dt
    state.target = torch.where(advance, torch.minimum(state.target + step, tables.upper), state.target)
    return state.target


class RuleBasedController:
    """The rule on an environment's readings; ``act(obs)`` returns actions like a policy.

    ``env`` is any object with the environment's readings (``view.pad_force_object``, ``view.joint_q``
    with ``index.finger_q``, ``episode_length_buf``, ``phase_of``, ``grasp.type_id``, ``dt``, joint limits
    ``joints.lower`` / ``joints.upper``, ``normalize_joints``, ``draw.object_soft``); in the
    residual action modes the environment runs the rule itself (``env.residual_base``) and this
    controller's actions are the zero residual.
    """

    def __init__(self, env: Any, cfg: BaselineConfig | None = None) -> None:
        self.env = env
        # The environment's rule settings (GraspEnvConfig.rule) unless a config is given.
        self.cfg = cfg or getattr(getattr(env, "cfg", None), "rule", None) or BaselineConfig()
        self.rest = rest_targets(env.joints.lower, env.joints.upper)
        self.tables = RuleTables.make(self.cfg, env.joints.upper)
        self.state = RuleState.open(env.num_envs, env.joints.lower)  # every world restarts at its first step

    @property
    def target(self) -> torch.Tensor:
        return self.state.target

    def reset(self, env_ids: torch.Tensor) -> None:
        # Each world opens in its grasp's pre-shape (abduction), the environment's open pose.
        open_pose_of = getattr(self.env, "open_pose_of", None)
        self.state.restart(env_ids, self.rest if open_pose_of is None else open_pose_of(env_ids))

    def settled(self) -> torch.Tensor:
        """(W,) bool: every joint the grasp type closes has stopped (:func:`rule_settled`)."""
        return rule_settled(self.state, self.tables, self.env.grasp.type_id)

    def act(self, obs: object = None) -> torch.Tensor:
        env = self.env
        if env.residual_base is not None and env.residual_base is not self:
            # A residual-mode env already runs this rule inside: the baseline is the zero residual.
            return torch.zeros(env.num_envs, env.num_actions, device=env.torch_device)
        t = env.episode_length_buf
        fresh = t == 0
        if fresh.any():
            self.reset(torch.nonzero(fresh).flatten())
        closing = env.phase_of(t) >= PHASES.index("grasp")
        target = rule_step(
            self.state,
            self.tables,
            self.cfg,
            env.view.pad_force_object,
            env.view.joint_q[env.index.finger_q],
            closing,
            env.grasp.type_id,
            env.dt,
            env.draw.object_soft,
        )
        return env.normalize_joints(target)
