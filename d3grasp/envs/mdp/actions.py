"""How the policy's actions in [-1, 1] become finger joint targets (``GraspEnvConfig.action_mode``).

``absolute`` maps each of 16 actions onto its joint's range. ``residual`` and ``synergy`` run the
rule-based controller inside the environment and offset its targets by up to ``residual_scale``
rad: per joint (16 actions), or per finger on its three flexion joints (4 actions). The residual
follows the actions as a low-pass (``residual_smoothing``) or as a clipped integrator
(``residual_rate`` > 0). A world with action latency k applies the action of k steps ago. With a
wrist (``palm_offset_limit`` / ``palm_yaw_limit`` > 0) 4 more actions offset the scripted palm path.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from d3grasp.dexhand13 import NUM_FINGER_JOINTS, NUM_FINGERS, finger_joints
from d3grasp.vocabulary import PHASES

if TYPE_CHECKING:
    from d3grasp.envs.config import GraspEnvConfig
    from d3grasp.envs.grasp_env import GraspEnv


def synergy_matrix(device: torch.device | str = "cpu") -> torch.Tensor:
    """(16, 4): action f moves every flexion joint of finger f by the same amount, abduction none."""
    s = torch.zeros(NUM_FINGER_JOINTS, NUM_FINGERS, dtype=torch.float32, device=device)
    for f in range(NUM_FINGERS):
        s[list(finger_joints(f))[1:], f] = 1.0
    return s


WRIST_ACTIONS = 4  # palm offset along x, y, z (world) and about the vertical (GraspEnvConfig.palm_*)


def has_wrist(cfg: GraspEnvConfig) -> bool:
    """Whether the policy moves the palm too (4 actions after the fingers')."""
    return cfg.palm_offset_limit > 0.0 or cfg.palm_yaw_limit > 0.0


def num_actions(cfg: GraspEnvConfig) -> int:
    fingers = NUM_FINGERS if cfg.action_mode == "synergy" else NUM_FINGER_JOINTS
    return fingers + (WRIST_ACTIONS if has_wrist(cfg) else 0)


def fingers_acting(env: GraspEnv) -> torch.Tensor:
    """(W,) bool: the worlds whose finger actions act at the coming step. In the residual modes the
    rule alone drives the fingers before ``residual_start`` (e.g. through the scripted approach)."""
    if env.residual_base is None:
        return torch.ones(env.num_envs, dtype=torch.bool, device=env.torch_device)
    return env.phase_of(env.episode_length_buf) >= PHASES.index(env.cfg.residual_start)


def wrist_acting(env: GraspEnv) -> torch.Tensor:
    """(W,) bool: the worlds whose wrist moves at the coming step: from the approach through the lift
    (the offset is held from the hold on, through the pushes)."""
    if not has_wrist(env.cfg):
        return torch.zeros(env.num_envs, dtype=torch.bool, device=env.torch_device)
    return env.phase_of(env.episode_length_buf) <= PHASES.index("lift")


def acting(env: GraspEnv) -> torch.Tensor:
    """(W,) bool: the worlds where some part of the action acts at the coming step."""
    return fingers_acting(env) | wrist_acting(env)


def hold_decisions(env: GraspEnv, actions: torch.Tensor) -> torch.Tensor:
    """The actions the worlds apply at the coming step under ``decision_steps`` k: a world takes the
    policy's action at the first step its actions act and every k-th step after, and holds it in
    between (``env.act.actions`` is the action held). Residual modes only: in the absolute mode the
    actions are the whole controller (the rule-based baseline among them) and act every step."""
    k = env.cfg.decision_steps
    if k == 1 or env.residual_base is None:
        return actions
    now = acting(env)
    decide = now & (env.act.decision_age % k == 0)
    env.act.decision_age = torch.where(now, env.act.decision_age + 1, torch.zeros_like(env.act.decision_age))
    return torch.where(decide[:, None], actions, env.act.actions)


def apply_actions(env: GraspEnv, actions: torch.Tensor) -> None:
    """Turn one step's actions into the finger joint targets of every world (writes the control)."""
    cfg = env.cfg
    actions = hold_decisions(env, actions)
    # Action latency: a world with latency k applies the action of k steps ago.
    hist = (
        torch.cat([actions[:, None], env.act.history[:, :-1]], dim=1)
        if env.act.history.shape[1]
        else actions[:, None]
    )
    lat = env.draw.latency.clamp(max=hist.shape[1] - 1)
    applied = hist[torch.arange(env.num_envs), lat]
    if has_wrist(cfg):
        move_wrist(env, applied[:, -WRIST_ACTIONS:])
        applied = applied[:, :-WRIST_ACTIONS]
    if env.residual_base is not None:
        env.residual_base.act()  # advances the rule on the current touch readings
        if cfg.action_mode == "synergy":
            applied = applied @ env.act.synergy.T
        if cfg.residual_rate > 0.0:
            env.act.residual = (env.act.residual + cfg.residual_rate * applied).clamp(-1.0, 1.0)
        else:
            b = cfg.residual_smoothing
            env.act.residual = b * applied + (1.0 - b) * env.act.residual
        # Before cfg.residual_start (e.g. the scripted approach) the rule alone drives the fingers.
        if PHASES.index(cfg.residual_start) > 0:  # from the first phase on there is nothing to wait for
            env.act.residual = env.act.residual * fingers_acting(env)[:, None]
        desired = env.residual_base.target + cfg.residual_scale * env.act.residual
        desired = torch.minimum(torch.maximum(desired, env.joints.lower), env.joints.upper)
    else:
        desired = env.joints.lower + 0.5 * (applied + 1.0) * (env.joints.upper - env.joints.lower)
    a = cfg.action_smoothing
    env.act.finger_target = a * desired + (1.0 - a) * env.act.finger_target
    env.view.target[env.index.finger_q] = env.act.finger_target
    env.act.actions = actions
    if env.act.history.shape[1]:
        env.act.history = hist


def move_wrist(env: GraspEnv, wrist: torch.Tensor) -> None:
    """Move every world's palm offset (``env.act.palm_offset`` m, ``env.act.palm_yaw`` rad) towards the wrist
    actions (W, 4) x their limits, at no more than the configured rates per axis; held outside the
    phases the wrist acts in. The env adds the offset to the scripted palm path."""
    cfg = env.cfg
    moving = wrist_acting(env)
    max_step, max_turn = cfg.palm_offset_rate * env.dt, cfg.palm_yaw_rate * env.dt
    step = (wrist[:, :3] * cfg.palm_offset_limit - env.act.palm_offset).clamp(-max_step, max_step)
    turn = (wrist[:, 3] * cfg.palm_yaw_limit - env.act.palm_yaw).clamp(-max_turn, max_turn)
    env.act.palm_offset = env.act.palm_offset + step * moving[:, None]
    env.act.palm_yaw = env.act.palm_yaw + turn * moving
