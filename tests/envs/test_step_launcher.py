"""``GraspEnv.step_launcher``: the public hook through which the env benchmark launches (and times) the
control step inside ``step``, instead of swapping a private method."""

from __future__ import annotations

import torch

from d3grasp.envs import close_env, make_env
from d3grasp.envs.benchmark import TASK_BY_KIND, _timed_physics_launch, bench_one


def test_the_benchmark_launch_runs_the_episode_the_env_would() -> None:
    """Physics and sensors as two timed graphs (the benchmark's hook) give the state the env's own
    captured step gives, step for step."""
    own = make_env(TASK_BY_KIND["rigid"], num_envs=1, seed=0)
    hooked = make_env(TASK_BY_KIND["rigid"], num_envs=1, seed=0)
    physics_s: list[float] = []
    sensors_s: list[float] = []
    hooked.step_launcher = _timed_physics_launch(hooked, physics_s, sensors_s)
    actions = torch.zeros(1, own.num_actions)
    for _ in range(3):
        own.step(actions)
        hooked.step(actions)
    assert len(physics_s) == len(sensors_s) == 3
    assert torch.equal(own.view.body_q, hooked.view.body_q)
    assert torch.equal(own.view.pad_force, hooked.view.pad_force)
    close_env(hooked)
    assert hooked.step_launcher is None  # closing lets the hook's graphs go with the env's
    close_env(own)


def test_env_benchmark_row() -> None:
    row = bench_one("rigid", 1, episodes=0.01, device="cpu")
    assert row["steps"] >= 1 and row["physics_steps_per_s"] > 0
    assert 0.0 < row["physics_share"] < 1.0 and 0.0 < row["sensors_share"] < 1.0
