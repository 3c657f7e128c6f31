"""The scripted part of an episode: its phases, the palm's path through them and the pushes.

Phases (seconds in ``PhaseConfig``): approach (the palm moves from the pre-grasp to the grasp
pose), grasp (root still, the fingers close), lift (the root rises ``lift_height`` on a cosine
profile), hold,
disturb (``disturb_force`` on the object along each of the episode's directions; all six in
evaluation), release. The grasp pose itself comes from the planner (``d3grasp.envs.grasps``) at
reset; the policy drives the fingers.

The lift of each world starts when its pads show a grasp (``lift_on_touch``: the environment sets
``lift_start`` per world, the paper's use of touch to time the lift) and at the latest when the
grasp phase's time is up; the lift then runs its full duration and the hold, the pushes and the
episode's length keep their fixed schedule.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from d3grasp.envs.config import PhaseConfig
from d3grasp.vocabulary import PHASES

DISTURB_DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float32
)
"""The six push directions (+x, -x, +y, -y, +z, -z, world frame)."""
DISTURB_NAMES: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")


class EpisodeScript:
    """Phase timing in control steps, the palm command and the disturbance for every world."""

    def __init__(self, phases: PhaseConfig, control_hz: float, eval_mode: bool) -> None:
        self.cfg = phases
        dt = 1.0 / control_hz
        self.phase_steps = {
            "approach": max(1, round(phases.approach / dt)),
            "grasp": max(1, round(phases.grasp / dt)),
            "lift": max(1, round(phases.lift / dt)),
            "hold": max(1, round(phases.hold / dt)),
        }
        self.disturb_dirs = 6 if eval_mode else max(0, int(phases.train_disturb_directions))
        self.steps_per_push = max(1, round(phases.disturb_per_direction / dt))
        self.phase_steps["disturb"] = self.disturb_dirs * self.steps_per_push
        self.phase_steps["release"] = round(phases.release / dt)
        bounds = np.cumsum([0] + [self.phase_steps[p] for p in PHASES])
        self.phase_start = {p: int(bounds[i]) for i, p in enumerate(PHASES)}
        self.max_episode_length = int(bounds[-1])
        self._constants: dict[torch.device, tuple[torch.Tensor, torch.Tensor]] = {}

    def _on(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
        """(phase starts after the first, push directions) on ``device``, made once: a tensor built
        from Python values costs more than the step's use of it."""
        if device not in self._constants:
            starts = torch.as_tensor([self.phase_start[p] for p in PHASES[1:]], device=device)
            self._constants[device] = (starts, torch.as_tensor(DISTURB_DIRECTIONS, device=device))
        return self._constants[device]

    def phase_of(self, t: torch.Tensor, lift_start: torch.Tensor | None = None) -> torch.Tensor:
        """Phase index (into :data:`PHASES`) of every world at step ``t``; a world whose lift started
        early (``lift_start`` (W,) steps) is in the lift phase from then on."""
        phase = torch.bucketize(t, self._on(t.device)[0], right=True)
        if lift_start is not None:
            early = (phase == PHASES.index("grasp")) & (t >= lift_start)
            phase = torch.where(early, PHASES.index("lift"), phase)
        return phase

    def palm_command(
        self,
        t: torch.Tensor,
        grasp_palm_pos: torch.Tensor,
        approach_dir: torch.Tensor,
        lift_start: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Palm position command (W, 3) at step ``t`` (the orientation stays the grasp orientation);
        the lift of each world starts at its ``lift_start`` (default: the lift phase's start)."""
        ph = self.cfg
        ta = t.float() / self.phase_steps["approach"]
        s_app = 0.5 - 0.5 * torch.cos(math.pi * ta.clamp(0.0, 1.0))
        pos = grasp_palm_pos - (1.0 - s_app)[:, None] * ph.pregrasp_clearance * approach_dir
        start = self.phase_start["lift"] if lift_start is None else lift_start
        tl = (t - start).float() / self.phase_steps["lift"]
        s_lift = 0.5 - 0.5 * torch.cos(math.pi * tl.clamp(0.0, 1.0))
        pos = pos.clone()
        pos[:, 2] += ph.lift_height * s_lift
        return pos

    def disturbance(self, t: torch.Tensor, phase: torch.Tensor, disturb_order: torch.Tensor) -> torch.Tensor:
        """The push on every world's object (W, 3) at step ``t``: the episode's k-th direction
        during the k-th push of the disturb phase, zero outside it."""
        in_push = phase == PHASES.index("disturb")
        k = ((t - self.phase_start["disturb"]).clamp(min=0) // self.steps_per_push).clamp(max=5)
        dir_idx = disturb_order[torch.arange(len(t)), k]
        dirs = self._on(t.device)[1][dir_idx]
        return dirs * self.cfg.disturb_force * in_push[:, None].float()
