"""The training benchmark's command lines and figures, with the training run replaced by a stand-in
that records its command and writes a ``timings.json`` of known iterations."""

from __future__ import annotations

import json
import statistics
import subprocess
from pathlib import Path

import pytest
from d3grasp.train import benchmark

# Three iterations of rank 0's timings: the first is dropped as warm-up.
ROWS = [
    {"env_steps": 2400, "sim_s": 9.0, "rollout_s": 9.5, "update_s": 1.0},
    {"env_steps": 2400, "sim_s": 3.0, "rollout_s": 3.2, "update_s": 0.3},
    {"env_steps": 2400, "sim_s": 4.0, "rollout_s": 4.1, "update_s": 0.4},
]


@pytest.fixture
def fake_training(monkeypatch: pytest.MonkeyPatch) -> list[list[str]]:
    commands: list[list[str]] = []

    def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
        commands.append(cmd)
        log_root = Path(cmd[cmd.index("--log_root") + 1])
        run_dir = log_root / "exp" / "run"
        run_dir.mkdir(parents=True)
        (run_dir / "timings.json").write_text(json.dumps(ROWS))
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(benchmark.subprocess, "run", run)
    return commands


def _value(cmd: list[str], flag: str) -> list[str]:
    """The values after each occurrence of ``flag`` up to the next flag."""
    out: list[str] = []
    for i, a in enumerate(cmd):
        if a == flag:
            for b in cmd[i + 1 :]:
                if b.startswith("--"):
                    break
                out.append(b)
    return out


def test_rank_layout_replaces_the_even_split(fake_training: list[list[str]]) -> None:
    r = benchmark.bench_one(
        "D3Grasp-DexHand13-Mixed-v0",
        worlds=8,
        procs=1,
        iterations=3,
        steps_per_env=24,
        rank_worlds=[48, 48, 4],
        overrides=["phases.disturb_per_direction=1.0"],
        rank_overrides=['0:objects.kinds=["rigid"]', '2:objects.kinds=["deformable"]'],
    )
    (cmd,) = fake_training
    assert "--nproc_per_node=3" in cmd  # one process per rank, through torchrun
    assert _value(cmd, "--rank_num_envs") == ["48", "48", "4"]
    assert "--num_envs" not in cmd  # training refuses both
    assert _value(cmd, "--set") == ["phases.disturb_per_direction=1.0"]
    assert _value(cmd, "--rank_set") == ['0:objects.kinds=["rigid"]', '2:objects.kinds=["deformable"]']
    assert (r.worlds, r.procs) == (100, 3)
    # env-steps over the median of the iterations after the first, update included.
    kept = [row["rollout_s"] + row["update_s"] for row in ROWS[1:]]
    assert r.steps_per_s == pytest.approx(2400 / statistics.median(kept))
    assert r.sim_share == pytest.approx((3.0 + 4.0) / sum(kept))
    assert r.update_share == pytest.approx((0.3 + 0.4) / sum(kept))


def test_even_split_without_a_layout(fake_training: list[list[str]]) -> None:
    r = benchmark.bench_one("D3Grasp-DexHand13-Mixed-v0", worlds=32, procs=2, iterations=3, steps_per_env=24)
    (cmd,) = fake_training
    assert _value(cmd, "--num_envs") == ["16"]
    assert "--rank_num_envs" not in cmd and "--set" not in cmd
    assert (r.worlds, r.procs) == (32, 2)
    with pytest.raises(ValueError, match="split evenly"):
        benchmark.bench_one("D3Grasp-DexHand13-Mixed-v0", worlds=33, procs=2, iterations=3, steps_per_env=24)
