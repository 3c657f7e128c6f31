"""End-to-end training throughput: ``python -m d3grasp.bench train``.

For each total world count W and process count P, runs ``d3grasp-train`` (P = 1) or
``torchrun --standalone --nproc_per_node=P -m d3grasp.train.train`` (W / P worlds per rank) for a few
iterations in a fresh process and reads rank 0's ``timings.json``. A rank layout (worlds per rank,
``--rank_worlds``) with ``--set`` / ``--rank_set`` overrides runs a recipe like the shipped policy's
(rigid and soft worlds on ranks of their own) instead, one row per layout. Reported per configuration,
after dropping the first (warm-up) iteration: env-steps/s over all ranks *including* the PPO update
(median iteration), and the share of iteration time inside ``env.step`` (simulation), in the rest
of the rollout (policy inference, storage) and in the update (returns, PPO epochs, gradient
all-reduce). The speed-up column compares P processes with one process at the same total W.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = ["TrainBenchResult", "bench_one", "run_train_benchmark"]


@dataclass(frozen=True)
class TrainBenchResult:
    worlds: int  # total over ranks
    procs: int
    steps_per_s: float
    sim_share: float
    rollout_other_share: float
    update_share: float
    iteration_s: float


def bench_one(
    task: str,
    worlds: int,
    procs: int,
    iterations: int,
    steps_per_env: int,
    env_factory: str | None = None,
    device: str = "cpu",
    timeout_s: float = 3600.0,
    torch_threads: int = 1,
    rank_worlds: Sequence[int] | None = None,
    overrides: Sequence[str] = (),
    rank_overrides: Sequence[str] = (),
) -> TrainBenchResult:
    """One training run's figures. ``rank_worlds`` (one count per rank) replaces the even split of
    ``worlds`` over ``procs``; ``overrides`` (``KEY=VALUE``) and ``rank_overrides``
    (``RANK:KEY=VALUE``) pass on as the training command's ``--set`` and ``--rank_set``."""
    if rank_worlds:
        worlds, procs = sum(rank_worlds), len(rank_worlds)
        layout = ["--rank_num_envs", *map(str, rank_worlds)]
    elif worlds % procs:
        raise ValueError(f"{worlds} worlds do not split evenly over {procs} processes")
    else:
        layout = ["--num_envs", str(worlds // procs)]
    with tempfile.TemporaryDirectory(prefix="d3grasp-bench-train-") as tmp:
        args = [
            "--task", task, *layout, "--max_iterations", str(iterations),
            "--num_steps_per_env", str(steps_per_env), "--log_root", tmp, "--device", device,
            "--save_interval", str(10**9), "--torch_threads", str(torch_threads),
        ]  # fmt: skip
        if env_factory:
            args += ["--env_factory", env_factory]
        for o in overrides:
            args += ["--set", o]
        for o in rank_overrides:
            args += ["--rank_set", o]
        if procs == 1:
            cmd = [sys.executable, "-m", "d3grasp.train.train", *args]
        else:
            cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={procs}",
                   "-m", "d3grasp.train.train", *args]  # fmt: skip
        env = dict(os.environ, GIT_PYTHON_REFRESH="quiet")
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=env)
        if res.returncode != 0:
            raise RuntimeError(f"training run failed ({' '.join(cmd)}):\n{(res.stdout + res.stderr)[-3000:]}")
        timing_files = list(Path(tmp).rglob("timings.json"))
        if len(timing_files) != 1:
            raise RuntimeError(f"expected one timings.json under {tmp}, found {len(timing_files)}")
        rows = json.loads(timing_files[0].read_text())
    rows = rows[1:] if len(rows) > 1 else rows  # first iteration: allocator / graph warm-up
    totals = [r["rollout_s"] + r["update_s"] for r in rows]
    sum_total = sum(totals)
    sim = sum(r["sim_s"] for r in rows)
    rollout = sum(r["rollout_s"] for r in rows)
    update = sum(r["update_s"] for r in rows)
    median_total = statistics.median(totals)
    return TrainBenchResult(
        worlds=worlds,
        procs=procs,
        steps_per_s=rows[0]["env_steps"] / median_total,
        sim_share=sim / sum_total,
        rollout_other_share=(rollout - sim) / sum_total,
        update_share=update / sum_total,
        iteration_s=median_total,
    )


def run_train_benchmark(
    task: str,
    worlds: list[int],
    procs: list[int],
    iterations: int = 4,
    steps_per_env: int = 24,
    env_factory: str | None = None,
    device: str = "cpu",
    torch_threads: int = 1,
    rank_layouts: Sequence[Sequence[int]] = (),
    overrides: Sequence[str] = (),
    rank_overrides: Sequence[str] = (),
) -> list[TrainBenchResult]:
    """Print (and return) one row per world count and process count, or per rank layout when
    ``rank_layouts`` is given (each a list of worlds per rank)."""
    print(
        f"d3grasp training benchmark: {task}, {steps_per_env} steps/world/iteration, {iterations} iterations "
        f"(first dropped), {torch_threads} torch thread(s) per process; env-steps/s over all processes "
        "including the PPO update"
        + (f"; --set {' '.join(overrides)}" if overrides else "")
        + (f"; --rank_set {' '.join(rank_overrides)}" if rank_overrides else "")
    )
    cols = (("worlds", 12), ("procs", 6), ("steps/s", 9), ("iter s", 8), ("sim", 6), ("policy", 7))
    print(" ".join(f"{c:>{w}}" for c, w in cols) + f" {'update':>7} {'speed-up':>9}")
    runs: list[tuple[int, int, Sequence[int] | None]] = [(sum(r), len(r), r) for r in rank_layouts] or [
        (w, p, None) for w in worlds for p in procs
    ]
    results: list[TrainBenchResult] = []
    base: dict[int, float] = {}
    for w, p, layout in runs:
        r = bench_one(
            task, w, p, iterations, steps_per_env, env_factory, device, torch_threads=torch_threads,
            rank_worlds=layout, overrides=overrides, rank_overrides=rank_overrides,
        )  # fmt: skip
        results.append(r)
        if p == 1:
            base[w] = r.steps_per_s
        speed = f"{r.steps_per_s / base[w]:.2f}x" if w in base else "n/a"
        label = " + ".join(map(str, layout)) if layout else str(w)
        print(
            f"{label:>12} {p:>6} {r.steps_per_s:>9.0f} {r.iteration_s:>8.2f} {100 * r.sim_share:>5.0f}% "
            f"{100 * r.rollout_other_share:>6.0f}% {100 * r.update_share:>6.0f}% {speed:>9}",
            flush=True,
        )
    return results
