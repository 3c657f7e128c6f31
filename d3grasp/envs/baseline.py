"""The paper's rule-based baseline: fingers close at constant joint speed until their pads feel the object.

Per world and finger, from the start of the grasp phase the flexion joints' targets advance at
``close_speed`` (rad/s); when any pad of that finger reads more than ``force_threshold`` the
finger stops advancing and keeps a small extra squeeze (``squeeze`` rad beyond where it stopped),
then holds through lift, hold and disturbance. Abduction joints stay at the middle of their range.
Fingers the grasp type does not use stay open. It acts through the same action interface as a
policy (normalised joint targets), so it runs wherever a policy does.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from d3grasp.envs.grasp_env import PHASES, GraspEnv
from d3grasp.envs.grasps import GRASP_NAMES, GRASP_TYPES

FINGER_PADS: tuple[tuple[int, ...], ...] = ((0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10))


@dataclass
class BaselineConfig:
    close_speed: float = 1.5  # rad/s of joint target per flexion joint
    force_threshold: float = 0.5  # N on any pad of a finger stops that finger
    squeeze: float = 0.1  # rad added beyond the stopping point


class RuleBasedController:
    """Tactile-triggered constant-speed closing; ``act(obs)`` returns actions like a policy."""

    def __init__(self, env: GraspEnv, cfg: BaselineConfig | None = None) -> None:
        self.env = env
        self.cfg = cfg or BaselineConfig()
        W, dev = env.num_envs, env.torch_device
        self.target = env.lower.expand(W, -1).clone()
        self.stopped = torch.zeros(W, 4, dtype=torch.bool, device=dev)
        mid = 0.5 * (env.lower + env.upper)
        self.rest = env.lower.clone()
        self.rest[[0, 4, 8, 12]] = mid[[0, 4, 8, 12]]  # abduction joints centred
        self.flex = torch.zeros(16, dtype=torch.bool, device=dev)
        self.flex[[1, 2, 3, 5, 6, 7, 9, 10, 11, 13, 14, 15]] = True
        uses = torch.zeros(len(GRASP_NAMES), 4, dtype=torch.bool, device=dev)
        for g, name in enumerate(GRASP_NAMES):
            uses[g, list(GRASP_TYPES[name].baseline_fingers)] = True
        self.grasp_uses = uses

    def reset(self, env_ids: torch.Tensor) -> None:
        self.target[env_ids] = self.rest
        self.stopped[env_ids] = False

    def act(self, obs: object = None) -> torch.Tensor:
        env, cfg = self.env, self.cfg
        t = env.episode_length_buf
        fresh = t == 0
        if fresh.any():
            self.reset(torch.nonzero(fresh).flatten())
        phase = env.phase_of(t)
        closing = phase >= PHASES.index("grasp")
        force = torch.linalg.norm(env.t_pad_force, dim=-1)  # (W, 11), the sensor reading
        touch = torch.stack([(force[:, list(p)] > cfg.force_threshold).any(-1) for p in FINGER_PADS], dim=-1)
        newly = touch & ~self.stopped & closing[:, None]
        uses = self.grasp_uses[env.grasp_id]
        # Freeze a finger where it touched, plus the squeeze.
        if newly.any():
            q = env.t_joint_q[env.i_finger_q]
            squeezed = torch.minimum(q + cfg.squeeze, env.upper)
            for f in range(4):
                rows = newly[:, f]
                if rows.any():
                    cols = torch.arange(4 * f + 1, 4 * f + 4)
                    self.target[rows.nonzero().flatten()[:, None], cols] = squeezed[rows][:, cols]
        self.stopped |= newly
        advance = closing[:, None] & uses & ~self.stopped  # (W, 4)
        step = cfg.close_speed * env.dt
        adv_joint = advance.repeat_interleave(4, dim=1) & self.flex
        self.target = torch.where(adv_joint, torch.minimum(self.target + step, env.upper), self.target)
        return 2.0 * (self.target - env.lower) / (env.upper - env.lower) - 1.0
