"""The episode script's schedule against closed forms in NumPy: phases, the palm's path, the pushes
and the episode clock, step by step past both ends of an episode (the script reads them from tables
made once; the references below compute each step from the phase durations)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from d3grasp.envs.config import PhaseConfig
from d3grasp.envs.script import DISTURB_DIRECTIONS, EpisodeScript
from d3grasp.vocabulary import PHASES

HZ = 60.0


def _starts(ph: PhaseConfig, pushes: int) -> dict[str, int]:
    """Phase start steps from the durations (seconds x control rate, rounded, at least one step)."""
    steps = [
        max(1, round(ph.approach * HZ)),
        max(1, round(ph.grasp * HZ)),
        max(1, round(ph.lift * HZ)),
        max(1, round(ph.hold * HZ)),
        pushes * max(1, round(ph.disturb_per_direction * HZ)),
        round(ph.release * HZ),
    ]
    return dict(zip(PHASES, np.concatenate([[0], np.cumsum(steps)[:-1]]).tolist(), strict=True)) | {
        "end": int(np.sum(steps))
    }


def _cosine(x: np.ndarray) -> np.ndarray:
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(x, 0.0, 1.0))


@pytest.mark.parametrize("eval_mode", [True, False])
def test_schedule_matches_closed_forms(eval_mode: bool) -> None:
    ph = PhaseConfig(train_disturb_directions=2, release=0.25)
    pushes = 6 if eval_mode else 2
    script = EpisodeScript(ph, HZ, eval_mode=eval_mode)
    s = _starts(ph, pushes)
    assert script.max_episode_length == s["end"]
    rng = np.random.default_rng(0)
    W = 5
    grasp_pos = rng.normal(size=(W, 3)).astype(np.float32)
    approach = rng.normal(size=(W, 3)).astype(np.float32)
    order = np.stack([rng.permutation(6) for _ in range(W)])
    # Worlds 1 and 3 start their lift early (touch-timed); the others at the lift phase's start.
    lift_start = np.full(W, s["lift"])
    lift_start[1], lift_start[3] = s["grasp"] + 7, s["grasp"] + 30
    per_push = max(1, round(ph.disturb_per_direction * HZ))
    lift_steps = max(1, round(ph.lift * HZ))
    for step in [-2, *range(s["end"] + 4)]:
        t = np.full(W, step)
        tt = torch.as_tensor(t)
        # Phases: the fixed schedule, and the lift from a world's own start once it has started.
        bounds = [s[p] for p in PHASES[1:]]
        phase = np.searchsorted(bounds, t, side="right")
        early = (phase == PHASES.index("grasp")) & (t >= lift_start)
        phase = np.where(early, PHASES.index("lift"), phase)
        got = script.phase_of(tt, torch.as_tensor(lift_start)).numpy()
        np.testing.assert_array_equal(got, phase, err_msg=f"phase at step {step}")
        # The palm: back along the approach direction by the clearance, cosine approach, then
        # up by lift_height on a cosine profile from the world's lift start.
        back = (1.0 - _cosine(t / max(1, round(ph.approach * HZ)))) * ph.pregrasp_clearance
        pos = grasp_pos - back[:, None] * approach
        pos[:, 2] += ph.lift_height * _cosine((t - lift_start) / lift_steps)
        got = script.palm_command(
            tt, torch.as_tensor(grasp_pos), torch.as_tensor(approach), torch.as_tensor(lift_start)
        )
        np.testing.assert_allclose(got.numpy(), pos, atol=2e-6, err_msg=f"palm at step {step}")
        # The pushes: the episode's k-th direction through the k-th push, nothing outside them.
        force = np.zeros((W, 3))
        if s["disturb"] <= step < s["release"]:
            k = (step - s["disturb"]) // per_push
            force = DISTURB_DIRECTIONS[order[:, k]] * ph.disturb_force
        got = script.disturbance(tt, torch.as_tensor(order))
        np.testing.assert_allclose(got.numpy(), force, atol=0.0, err_msg=f"push at step {step}")
        # The clock of the paper's t_i, its period fixed in seconds (4.5 s, ObservationConfig's
        # default), the same in training and evaluation whatever the episode's length.
        T = 4.5 * HZ
        clock = np.array([step / T, np.sin(2 * np.pi * step / T), np.cos(2 * np.pi * step / T)])
        if 0 <= step <= s["end"] + 1:
            row = script.tables(tt.device).clock[script.row(tt)].numpy()
            # float32 tables: sin of an angle up to ~6 pi carries ~1e-6 of round-off.
            np.testing.assert_allclose(row, np.broadcast_to(clock, (W, 3)), atol=1e-5)


def test_scoring_windows_follow_the_schedule() -> None:
    """The steps whose results s_lift's hold check and s_disturb score: a step's result (the state
    after step t - 1 -> t) belongs to the phase step t - 1 ran in."""
    ph = PhaseConfig()
    script = EpisodeScript(ph, HZ, eval_mode=True)
    s = _starts(ph, 6)
    per_push = max(1, round(ph.disturb_per_direction * HZ))
    tab = script.tables(torch.device("cpu"))
    t = np.arange(s["end"] + 2)
    np.testing.assert_array_equal(tab.in_hold_score.numpy(), (t > s["hold"]) & (t <= s["disturb"]))
    in_push = (t > s["disturb"]) & (t <= s["release"])
    np.testing.assert_array_equal(tab.in_push_score.numpy(), in_push)
    # A push's reference is the first state under it: one step after each push began.
    first = in_push & ((t - s["disturb"] - 1) % per_push == 0)
    np.testing.assert_array_equal(tab.push_started.numpy(), first)
    assert int(tab.push_started.sum()) == 6
    # The push a scored step's state shows: the one step t - 1 ran under.
    scored = tab.scored_push.numpy()[in_push]
    np.testing.assert_array_equal(scored, np.repeat(np.arange(6), per_push))
