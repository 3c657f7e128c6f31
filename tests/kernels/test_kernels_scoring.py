"""The scoring kernel against its NumPy twin, step by step over random episodes that reach every rule:
touch-timed lifts, s_grasp, the four s_lift failures, losses under each push, pushes off the table,
blow-ups and non-finite states. (The rules themselves are checked on hand-made episodes in
``tests/envs/test_terminations.py``.)

Positions lie on a grid of 1/128 m and force components on one of 1/8 N, so no norm falls within
round-off of a threshold: the kernel and the twin may sum in another order without a flip."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import warp as wp
from d3grasp.kernels import scoring as sk

from d3grasp.dexhand13 import NUM_PADS
from d3grasp.envs.config import PhaseConfig
from d3grasp.envs.mdp.terminations import pad_roles, score_params
from d3grasp.envs.script import EpisodeScript

wp.config.log_level = wp.LOG_WARNING
W, BODIES = 48, 60
GRID = 1.0 / 128.0


def _params(
    script: EpisodeScript, eval_mode: bool, lift_on_touch: bool, lift_on_pads: bool = True
) -> sk.ScoreParams:
    phases = PhaseConfig(lift_on_touch=lift_on_touch, lift_height=0.1)
    prm = score_params(script, phases, 1.0 / 60.0, eval_mode, lift_on_pads=lift_on_pads)
    prm.settle_steps = 3
    return prm


def _schedule(script: EpisodeScript) -> dict[str, np.ndarray]:
    """The scoring's read-only tables of ``script`` as host arrays (the NumPy twin's ``sched``)."""
    tab = script.tables(torch.device("cpu"))
    return {
        "in_hold_score": tab.in_hold_score.numpy(),
        "in_push_score": tab.in_push_score.numpy(),
        "push_started": tab.push_started.numpy(),
        "scored_push": tab.scored_push.numpy(),
        "pad_role": pad_roles(),
    }


class _Episodes:
    """Random worlds, each at its own step: a palm that rises through the lift, an object that follows
    it until a random step and then drifts, pads that touch in random sets."""

    def __init__(self, rng: np.random.Generator, script: EpisodeScript) -> None:
        self.rng, self.script = rng, script
        self.t0 = rng.integers(0, 40, W)  # the worlds are out of step
        ps, end = script.phase_start, script.max_episode_length
        # When the object stops following the palm: before the lift, in it, in the hold, under the
        # pushes or never; then it drifts by a grid step every 8 steps along each axis.
        windows = [
            (0, ps["lift"]),
            (ps["lift"] + 4, ps["hold"]),
            (ps["hold"] + 2, ps["disturb"]),
            (ps["disturb"], ps["release"]),
            (end + 10, end + 11),
        ]
        self.slip = np.array([rng.integers(*windows[k]) for k in rng.integers(0, len(windows), W)])
        self.drift = rng.integers(-1, 2, (W, 3)) * GRID
        self.palm_body = rng.permutation(BODIES)[:W].astype(np.int32)
        self.start = np.zeros((W, 3), dtype=np.float32)
        self.start[:, :2] = rng.integers(-8, 9, (W, 2)) * GRID
        self.order = np.stack([rng.permutation(6) for _ in range(W)]).astype(np.int64)
        self.grip = rng.random(W) < 0.7  # worlds whose pads grasp most of the time

    def step(self, i: int) -> dict[str, np.ndarray]:
        rng, lift0 = self.rng, self.script.phase_start["lift"]
        t = self.t0 + i
        up = np.clip(t - lift0, 0, 12) * GRID  # the palm rises 12/128 m through the lift
        body_q = np.zeros((BODIES, 7), dtype=np.float32)
        body_q[:, 6] = 1.0
        body_q[:, :3] = rng.integers(-20, 21, (BODIES, 3)) * GRID
        palm = np.zeros((W, 3), dtype=np.float32)
        palm[:, 2] = 0.25 + up
        body_q[self.palm_body, :3] = palm
        drifted = ((t - self.slip) // 8)[:, None] * self.drift
        obj = self.start + np.where((t < self.slip)[:, None], 0.0, drifted)
        obj[:, 2] += np.where(t < self.slip, up, 0.0)
        obj += rng.integers(-1, 2, (W, 3)) * GRID * (rng.random((W, 1)) < 0.2)  # jolts
        forces = rng.integers(-8, 9, (W, NUM_PADS, 3)) / 8.0
        forces *= ((rng.random((W, NUM_PADS)) < 0.1) | self.grip[:, None])[..., None]
        true = forces + rng.integers(0, 40, (W, NUM_PADS, 3)) / 8.0
        # Worlds 0-1 blow up at their 100th step, 2-3 turn non-finite at it, and world 4's pads read
        # NaN then beside a blow-up (a NaN makes the largest force NaN: no blow-up read).
        late = i == 100
        true[:2, 3] = [0.0, 0.0, 1000.0] if late else 0.0
        finite = np.ones(W, dtype=bool)
        finite[2:4] = not late
        obj[~finite] = np.nan
        if late:
            true[4, 3], true[4, 5] = [0.0, 0.0, 1000.0], np.nan
        return {
            "t": t.astype(np.int64),
            "obj_pos": obj.astype(np.float32),
            "finite": finite,
            "rule_settled": rng.random(W) < 0.05,
            "pad_force_object": forces.astype(np.float32),
            "pad_force_true": true.astype(np.float32),
            "body_q": body_q,
            "palm_body": self.palm_body,
            "object_start": self.start,
            "disturb_order": self.order,
        }


def _upload(inp: dict[str, np.ndarray]) -> sk.ScoreInputs:
    vec3 = {"obj_pos", "pad_force_object", "pad_force_true", "object_start"}
    dtypes = {"t": wp.int64, "finite": wp.bool, "rule_settled": wp.bool, "palm_body": wp.int32}
    arrays = {}
    for name, a in inp.items():
        if name == "body_q":
            arrays[name] = wp.array(a, dtype=wp.transform)
        elif name in vec3:
            arrays[name] = wp.array(a, dtype=wp.vec3)
        else:
            arrays[name] = wp.array(a, dtype=dtypes.get(name, wp.int64))
    return sk.ScoreInputs(**arrays)


@pytest.mark.parametrize(
    ("eval_mode", "lift_on_touch", "lift_on_pads"),
    [(True, True, True), (False, True, True), (True, False, True), (True, True, False)],
)
def test_kernel_matches_numpy_twin(eval_mode: bool, lift_on_touch: bool, lift_on_pads: bool) -> None:
    phases = PhaseConfig()
    phases.disturb_per_direction = 0.1  # 6 steps a push: every push within a short episode
    script = EpisodeScript(phases, 60.0, eval_mode=True)
    prm = _params(script, eval_mode, lift_on_touch, lift_on_pads)
    sched_np = _schedule(script)
    dtypes = {"pad_role": wp.int32, "scored_push": wp.int32}
    sched = sk.ScoreSchedule(**{k: wp.array(v, dtype=dtypes.get(k, wp.bool)) for k, v in sched_np.items()})
    state = sk.ScoreState.allocate(W, NUM_PADS, script.phase_start["lift"])
    twin = state.numpy()
    episodes = _Episodes(np.random.default_rng(7), script)
    seen: dict[int, int] = {}
    for i in range(script.max_episode_length + 4):
        inp = episodes.step(i)
        sk.score_step(prm, sched, _upload(inp), state)
        sk.score_step_numpy(prm, sched_np, inp, twin)
        got = state.numpy()
        for name, want in twin.items():
            if got[name].dtype.kind == "f":
                np.testing.assert_allclose(
                    got[name], want, rtol=1e-6, atol=1e-7, equal_nan=True, err_msg=f"{name} at {i}"
                )
            else:
                np.testing.assert_array_equal(got[name], want, err_msg=f"{name} at {i}")
        for c in got["failure"]:
            seen[int(c)] = seen.get(int(c), 0) + 1
    # The episodes reach the rules the comparison is meant to cover.
    expected = {sk.NO_GRASP, sk.SLIPPED, sk.DROPPED, sk.PUSHED_OFF, sk.BLOWUP, sk.NON_FINITE}
    expected |= {sk.LOST_UNDER_PUSH + k for k in range(3)}
    assert expected <= set(seen), (sorted(expected - set(seen)), sorted(seen))
    assert twin["s_grasp"].any() and not twin["s_grasp"].all()
    if lift_on_touch and lift_on_pads:
        assert (twin["lift_start"] < script.phase_start["lift"]).any()  # touch started some lifts early


def test_without_the_pads_only_the_rule_settling_times_the_lift() -> None:
    """``lift_on_pads`` off (the Base ablation's prior): pads that show a grasp through the whole
    grasp phase start no lift early, a rule that has settled for ``settle_steps`` does."""
    script = EpisodeScript(PhaseConfig(), 60.0, eval_mode=True)
    sched = _schedule(script)
    g0, lift0 = script.phase_start["grasp"], script.phase_start["lift"]
    roles = pad_roles()
    forces = np.zeros((2, NUM_PADS, 3), dtype=np.float32)
    forces[:, np.flatnonzero(roles == sk.PAD_THUMB)[0], 2] = 2.0  # a thumb pad and an opposing pad
    forces[:, np.flatnonzero(roles == sk.PAD_OPPOSING)[0], 2] = 2.0
    starts = {}
    for pads in (True, False):
        prm = _params(script, True, True, lift_on_pads=pads)
        state = sk.ScoreState.allocate(2, NUM_PADS, lift0).numpy()
        for t in range(g0, lift0):
            body_q = np.zeros((2, 7), dtype=np.float32)
            body_q[:, 6] = 1.0
            inp = {
                "t": np.full(2, t, dtype=np.int64),
                "body_q": body_q,
                "palm_body": np.array([0, 1], dtype=np.int32),
                "obj_pos": np.zeros((2, 3), dtype=np.float32),
                "object_start": np.zeros((2, 3), dtype=np.float32),
                "pad_force_object": forces,
                "pad_force_true": forces,
                "finite": np.ones(2, dtype=bool),
                # World 1's rule settles 10 steps into the grasp phase.
                "rule_settled": np.array([False, t >= g0 + 10]),
                "disturb_order": np.tile(np.arange(6), (2, 1)),
            }
            sk.score_step_numpy(prm, sched, inp, state)
        starts[pads] = state["lift_start"].tolist()
    settle = prm.settle_steps
    assert starts[True] == [g0 + settle, g0 + settle]  # the pads grasp from the phase's first step
    assert starts[False] == [lift0, g0 + 10 + settle]  # only the settled rule starts a lift
