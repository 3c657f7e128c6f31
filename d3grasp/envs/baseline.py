"""The paper's rule-based baseline: joints close at constant speed until the pads feel the object.

From the start of the grasp phase every flexion joint of the fingers the grasp type uses advances
its target at ``close_speed`` (rad/s). A joint stops advancing once a pad on its own link or on a
link distal to it reads more than ``force_threshold`` (N): a finger whose proximal link meets the
object keeps curling its distal links around it, one whose tip meets it stops entirely. This is
the "close at constant speed until the pads exceed a force threshold" rule applied per joint,
which is what an under-actuated gripper does mechanically; ``per_joint=False`` stops a whole
finger at its first touch instead. A stopped joint keeps a small extra squeeze (``squeeze`` rad
beyond where it stopped, i.e. ``squeeze * ke`` of drive torque) and holds it through lift, hold and
disturbance. Abduction joints stay at the middle of their range; fingers the grasp type does not
use stay open. It acts through the same action interface as a policy (normalised joint targets),
so it runs wherever a policy does. The thumb's first flexion link carries no pad: its joint stops
with the thumb's pads.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from d3grasp.envs.grasp_env import NUM_FINGER_JOINTS, NUM_PADS, PHASES, GraspEnv
from d3grasp.envs.grasps import GRASP_NAMES, GRASP_TYPES

# Pads per finger and the link (1..3) each sits on (hand.PAD_NAMES order).
FINGER_PADS: tuple[tuple[int, ...], ...] = ((0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10))
PAD_LINK: tuple[int, ...] = (1, 2, 3, 1, 2, 3, 1, 2, 3, 2, 3)
FLEXION_JOINTS: tuple[int, ...] = (1, 2, 3, 5, 6, 7, 9, 10, 11, 13, 14, 15)


@dataclass
class BaselineConfig:
    close_speed: float = 1.5  # rad/s of joint target per flexion joint
    force_threshold: float = 0.5  # N on a pad stops the joints proximal to it
    squeeze: float = 0.1  # rad added beyond the stopping point
    per_joint: bool = True  # False: a finger's first touch stops all of its joints


def stop_matrix(per_joint: bool = True) -> torch.Tensor:
    """(16, 11) bool: which pads stop which finger joint (abduction joints never stop: never advance)."""
    s = torch.zeros(NUM_FINGER_JOINTS, NUM_PADS, dtype=torch.bool)
    for f, pads in enumerate(FINGER_PADS):
        for j in (1, 2, 3):
            for p in pads:
                if not per_joint or PAD_LINK[p] >= j:
                    s[4 * f + j, p] = True
    return s


class RuleBasedController:
    """Tactile-triggered constant-speed closing; ``act(obs)`` returns actions like a policy."""

    def __init__(self, env: GraspEnv, cfg: BaselineConfig | None = None) -> None:
        self.env = env
        self.cfg = cfg or BaselineConfig()
        W, dev = env.num_envs, env.torch_device
        self.target = env.lower.expand(W, -1).clone()
        self.stopped = torch.zeros(W, NUM_FINGER_JOINTS, dtype=torch.bool, device=dev)
        mid = 0.5 * (env.lower + env.upper)
        self.rest = env.lower.clone()
        self.rest[[0, 4, 8, 12]] = mid[[0, 4, 8, 12]]  # abduction joints centred
        self.flex = torch.zeros(NUM_FINGER_JOINTS, dtype=torch.bool, device=dev)
        self.flex[list(FLEXION_JOINTS)] = True
        self.stops = stop_matrix(self.cfg.per_joint).to(dev).float()
        uses = torch.zeros(len(GRASP_NAMES), NUM_FINGER_JOINTS, dtype=torch.bool, device=dev)
        for g, name in enumerate(GRASP_NAMES):
            for f in GRASP_TYPES[name].baseline_fingers:
                uses[g, 4 * f : 4 * f + 4] = True
        self.grasp_uses = uses & self.flex

    def reset(self, env_ids: torch.Tensor) -> None:
        self.target[env_ids] = self.rest
        self.stopped[env_ids] = False

    def act(self, obs: object = None) -> torch.Tensor:
        env, cfg = self.env, self.cfg
        if env.residual_base is not None and env.residual_base is not self:
            # A residual-mode env already runs this rule inside: the baseline is the zero residual.
            return torch.zeros(env.num_envs, env.num_actions, device=env.torch_device)
        t = env.episode_length_buf
        fresh = t == 0
        if fresh.any():
            self.reset(torch.nonzero(fresh).flatten())
        closing = env.phase_of(t) >= PHASES.index("grasp")
        force = torch.linalg.norm(env.t_pad_force, dim=-1)  # (W, 11), the sensor reading
        touched = (force > cfg.force_threshold).float() @ self.stops.T > 0  # (W, 16)
        uses = self.grasp_uses[env.grasp_id]
        newly = touched & uses & ~self.stopped & closing[:, None]
        if newly.any():
            # Hold a stopping joint where it is now, plus the squeeze.
            q = env.t_joint_q[env.i_finger_q]
            squeezed = torch.minimum(q + cfg.squeeze, env.upper)
            self.target = torch.where(newly, squeezed, self.target)
        self.stopped |= newly
        advance = closing[:, None] & uses & ~self.stopped
        step = cfg.close_speed * env.dt
        self.target = torch.where(advance, torch.minimum(self.target + step, env.upper), self.target)
        return env.normalize_joints(self.target)
