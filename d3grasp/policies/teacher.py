"""The privileged teacher of issue 43: the grasp at the object's true pose, with the rule's fingers.

Under camera perception the planner places the grasp at the camera's estimate of the object's pose.
The teacher knows the truth (computed where the episode is placed, ``mdp.events``) and moves the
wrist by one of two corrections, its fingers the rule's touch-stopped closing (zero action):

- ``env.grasp.pose_correction``: onto the same grasp at the true pose (offset and turn), where the wrist's
  limits allow it;
- ``env.grasp.centre_correction``: else by the camera's centre error only, the planned yaw kept. The grasp
  sits ~0.17 m from the object's centre, so a yaw error of 0.3-0.8 rad moves it by 4-16 cm: larger
  than any wrist, and for the objects that give such errors (cylinders, bottles, bowls, balls, crosses:
  a box fit's yaw is arbitrary when the footprint is round or square) the turned grasp is the same
  grasp (measured, docs/studies/privileged_teacher.md).

It is what a student that reads only touch, proprioception and the camera's estimate is distilled
from (``d3grasp.train.distill``), and its evaluation under the camera bounds what the wrist can
recover of the camera's error.
"""

from __future__ import annotations

from typing import Any

import torch

from d3grasp.envs.mdp.actions import WRIST_ACTIONS, has_wrist

__all__ = ["TEACHER", "TEACHER_WRIST", "PoseTeacher"]

TEACHER = "teacher"
"""The ``--checkpoint`` value that runs the privileged teacher."""

TEACHER_WRIST: dict[str, float] = {
    "palm_offset_limit": 0.02,
    "palm_yaw_limit": 0.3,
    "palm_offset_rate": 0.04,
    "palm_yaw_rate": 0.6,
}
"""The wrist the teacher's evaluation runs with when the environment has none (m, rad, m/s, rad/s):
the limit twice the camera's 95th-percentile centre error (10.5 mm), the rate such that the 0.5 s
approach covers it before the fingers touch."""


class PoseTeacher:
    """Actions (W, 4 + 4): zero finger residual, wrist targets ``correction / limit`` (module
    docstring for which correction)."""

    def __init__(self, env: Any) -> None:
        if env.residual_base is None or not has_wrist(env.cfg):
            raise ValueError("the teacher needs a residual action mode and a wrist (palm_offset_limit > 0)")
        self.env = env

    def corrections(self) -> torch.Tensor:
        """(W, 4) the correction each world's wrist moves by: the full one where it is within the
        wrist's limits, else the centre's with no turn."""
        env, cfg = self.env, self.env.cfg
        full = env.grasp.pose_correction
        fits = (full[:, :3].abs() <= cfg.palm_offset_limit).all(dim=1) & (
            full[:, 3].abs() <= cfg.palm_yaw_limit
        )
        centre = torch.cat([env.grasp.centre_correction, torch.zeros_like(full[:, :1])], dim=1)
        return torch.where(fits[:, None], full, centre)

    def actions(self) -> torch.Tensor:
        env, cfg = self.env, self.env.cfg
        a = torch.zeros(env.num_envs, env.num_actions, device=env.torch_device)
        limits = torch.tensor([cfg.palm_offset_limit] * 3 + [cfg.palm_yaw_limit], device=env.torch_device)
        corr = self.corrections()
        target = torch.where(limits > 0, corr / limits.clamp(min=1e-9), torch.zeros_like(corr))
        a[:, -WRIST_ACTIONS:] = target.clamp(-1.0, 1.0)
        return a

    def act(self, obs: object = None) -> torch.Tensor:
        return self.actions()
