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
from dataclasses import dataclass

import numpy as np
import torch

from d3grasp.envs.config import PhaseConfig
from d3grasp.vocabulary import PHASES

DISTURB_DIRECTIONS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float32
)
"""The six push directions (+x, -x, +y, -y, +z, -z, world frame)."""
DISTURB_NAMES: tuple[str, ...] = ("+x", "-x", "+y", "-y", "+z", "-z")


@dataclass(frozen=True)
class ScheduleTables:
    """The script's per-step quantities, one row per control step ``t`` in ``[0, max_episode_length
    + 1]`` (a later step reads the last row): a step looks them up with one index each instead of
    computing them from ``t`` with a chain of small tensor operations (each ~2-3 us on the CPU,
    which at a few worlds costs more than the arithmetic)."""

    phase: torch.Tensor  # long: index into PHASES (the fixed schedule, lift at its latest start)
    approach_back: torch.Tensor  # m the palm is still short of its grasp pose (cosine approach)
    push_slot: torch.Tensor  # long: the push under way (0-5), 6 outside the disturb phase
    push_started: torch.Tensor  # bool: the step after a push's first step (s_disturb's reference)
    in_push_score: torch.Tensor  # bool: a step whose result s_disturb scores (after the push began)
    scored_push: torch.Tensor  # int32: the push (0-5) whose result a step's state shows (step t - 1's)
    in_hold_score: torch.Tensor  # bool: a step whose result s_lift's hold check scores
    clock: torch.Tensor  # (steps, 3): t / T, sin(2 pi t / T), cos(2 pi t / T), T the clock's period
    lift_rise: torch.Tensor  # m the palm has risen d steps into its lift (d clamped to [0, lift])
    push_dirs: torch.Tensor  # (7, 3): the six push directions by slot, and a zero row for slot 6


class EpisodeScript:
    """Phase timing in control steps, the palm command and the disturbance for every world."""

    def __init__(
        self, phases: PhaseConfig, control_hz: float, eval_mode: bool, clock_period: float = 4.5
    ) -> None:
        self.cfg = phases
        dt = 1.0 / control_hz
        # The clock's period in steps: fixed in seconds (ObservationConfig.clock_period), not the
        # episode's length, so that a training and an evaluation episode show the same clock.
        self.clock_steps = max(1.0, clock_period / dt)
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
        self._tables: dict[torch.device, ScheduleTables] = {}

    def tables(self, device: torch.device) -> ScheduleTables:
        """The :class:`ScheduleTables` on ``device``, made once (the formulas of the schedule live
        here; the per-step methods below only look them up)."""
        if device not in self._tables:
            ph, n = self.cfg, self.max_episode_length + 2
            t = torch.arange(n, device=device)
            starts = torch.as_tensor([self.phase_start[p] for p in PHASES[1:]], device=device)
            ta = t.float() / self.phase_steps["approach"]
            s_app = 0.5 - 0.5 * torch.cos(math.pi * ta.clamp(0.0, 1.0))
            d0, d_end = self.phase_start["disturb"], self.phase_start["release"]
            k = ((t - d0).clamp(min=0) // self.steps_per_push).clamp(max=5)
            in_disturb = (t >= d0) & (t < d_end)
            # A step's result is scored after the step: step t + 1's state belongs to step t's push.
            k_in = (t - d0 - 1).clamp(min=0) % self.steps_per_push
            in_push_score = (t > d0) & (t <= d_end)
            hold0 = self.phase_start["hold"]
            T = float(self.clock_steps)
            dl = torch.arange(self.phase_steps["lift"] + 1, device=device)
            tl = dl.float() / self.phase_steps["lift"]
            s_lift = 0.5 - 0.5 * torch.cos(math.pi * tl.clamp(0.0, 1.0))
            dirs = torch.as_tensor(DISTURB_DIRECTIONS, device=device)
            self._tables[device] = ScheduleTables(
                phase=torch.bucketize(t, starts, right=True),
                approach_back=(1.0 - s_app) * ph.pregrasp_clearance,
                push_slot=torch.where(in_disturb, k, 6),
                push_started=in_push_score & (k_in == 0),
                in_push_score=in_push_score,
                scored_push=((t - d0 - 1).clamp(min=0) // self.steps_per_push).clamp(max=5).to(torch.int32),
                in_hold_score=(t > hold0) & (t <= d0),
                clock=torch.stack(
                    [t / T, torch.sin(2.0 * math.pi * t / T), torch.cos(2.0 * math.pi * t / T)], dim=-1
                ),
                lift_rise=ph.lift_height * s_lift,
                push_dirs=torch.cat([dirs, torch.zeros(1, 3, device=device)]),
            )
        return self._tables[device]

    def row(self, t: torch.Tensor) -> torch.Tensor:
        """Table rows of steps ``t`` (a step past the schedule reads its last row)."""
        return t.clamp(0, self.max_episode_length + 1)

    def phase_of(self, t: torch.Tensor, lift_start: torch.Tensor | None = None) -> torch.Tensor:
        """Phase index (into :data:`PHASES`) of every world at step ``t``; a world whose lift started
        early (``lift_start`` (W,) steps) is in the lift phase from then on."""
        phase = self.tables(t.device).phase[self.row(t)]
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
        tab = self.tables(t.device)
        pos = grasp_palm_pos - tab.approach_back[self.row(t)][:, None] * approach_dir
        start = self.phase_start["lift"] if lift_start is None else lift_start
        pos[:, 2] += tab.lift_rise[(t - start).clamp(0, self.phase_steps["lift"])]
        return pos

    def disturbance(self, t: torch.Tensor, disturb_order: torch.Tensor) -> torch.Tensor:
        """The push on every world's object (W, 3) at step ``t``: the episode's k-th direction
        (``disturb_order`` (W, 6)) during the k-th push of the disturb phase, zero outside it."""
        tab = self.tables(t.device)
        slot = tab.push_slot[self.row(t)]
        # Slot 6 (no push) reads the zero row appended to the directions.
        order = torch.cat([disturb_order, torch.full_like(disturb_order[:, :1], 6)], dim=1)
        return tab.push_dirs[order.gather(1, slot[:, None])[:, 0]] * self.cfg.disturb_force
