"""A short PPO run: the asymmetric actor-critic with an LSTM actor, on rigid objects, its
checkpoint read back as data.

    python -m d3grasp.examples.train_short [--iterations 3] [--worlds 8] [--steps 24] [--out DIR]

The pieces ``d3grasp-train`` puts together, in one process: the environment (an rsl-rl VecEnv with
the ``policy`` and ``privileged`` observation groups), the task's runner config, and the runner
(rsl-rl's ``OnPolicyRunner`` with atomic checkpoints that carry their task). The actor starts at
the zero residual, the rule; a run that trains a policy worth shipping takes hours (docs/training.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import d3grasp
from d3grasp.console import quiet_warp
from d3grasp.policies.checkpoint import read_checkpoint
from d3grasp.train.configs import fit_mini_batches, make_train_cfg
from d3grasp.train.runner import D3GraspRunner

TASK = "D3Grasp-DexHand13-Diverse-v0"


def run(
    iterations: int = 3, worlds: int = 8, steps: int = 24, out: str | Path = "logs/example_train"
) -> Path:
    """Train ``iterations`` PPO updates of ``steps`` control steps in ``worlds`` worlds; returns the
    checkpoint the runner wrote (``OUT/model_<iterations>.pt``)."""
    quiet_warp()
    env = d3grasp.make_env(TASK, num_envs=worlds, seed=0)
    cfg = make_train_cfg(TASK, max_iterations=iterations, num_steps_per_env=steps)
    algorithm = cfg["algorithm"]
    algorithm["num_mini_batches"] = fit_mini_batches(algorithm["num_mini_batches"], worlds)
    sizes = {group: int(x.shape[1]) for group, x in env.get_observations().items()}
    groups = cfg["obs_groups"]
    print(f"observation groups {sizes}: the actor reads {groups['actor']}, the critic {groups['critic']}")
    try:
        runner = D3GraspRunner(env, cfg, log_dir=Path(out), task_name=TASK)
        runner.learn(iterations)
    finally:
        env.close()
    return Path(out) / f"model_{iterations}.pt"


def describe(path: Path) -> dict[str, Any]:
    """What a checkpoint says of itself, read as data (weights, no code)."""
    data = read_checkpoint(path)
    infos = data["infos"]
    print(f"{path}: iteration {data['iter']}, task {infos['task']}, observation sizes {infos['obs_sizes']}")
    return data


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=3, help="PPO updates")
    ap.add_argument("--worlds", type=int, default=8, help="worlds stepped side by side")
    ap.add_argument("--steps", type=int, default=24, help="control steps per world and update")
    ap.add_argument("--out", default="logs/example_train", help="where the checkpoint and logs go")
    args = ap.parse_args(argv)
    describe(run(args.iterations, args.worlds, args.steps, args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
