"""``d3grasp-train``: train a D3Grasp policy with rsl-rl PPO, on one process or many.

    d3grasp-train --task D3Grasp-DexHand13-Mixed-v0 --num_envs 32 --max_iterations 1000
    torchrun --nproc_per_node=2 -m d3grasp.train.train --task ... --num_envs 16   # 2 CPU ranks (gloo)
    torchrun --nnodes=2 --nproc_per_node=1 --rdzv_endpoint=HOST:29500 -m d3grasp.train.train ...
    d3grasp-train --task ... --resume [--load_run RUN] [--checkpoint model_500.pt]

Each rank builds its own worlds (seed + rank) and the ranks average gradients (D3GraspRunner).
Rank 0 writes ``<log_root>/<experiment>/<YYYY-mm-dd_HH-MM-SS>[_<run_name>]/``: TensorBoard events,
``params/env.json`` and ``params/agent.json`` (the resolved configs), ``model_<N>.pt`` checkpoints
(N = completed iterations) and ``timings.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import importlib
import importlib.util
import json
import math
import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

import torch  # noqa: E402
from d3grasp.train.cli_args import make_train_parser  # noqa: E402
from d3grasp.train.configs import fit_mini_batches, make_train_cfg, set_cfg_value  # noqa: E402
from d3grasp.train.runner import CheckpointError, D3GraspRunner, latest_checkpoint  # noqa: E402

from d3grasp.cli.args import resolve_torch_threads, run_command  # noqa: E402
from d3grasp.envs import close_env  # noqa: E402
from d3grasp.envs.config import POLICY_INTERFACE  # noqa: E402
from d3grasp.envs.registry import get_task  # noqa: E402
from d3grasp.policies.checkpoint import refuse_code  # noqa: E402
from d3grasp.seeding import seed_everything

__all__ = [
    "DistInfo",
    "load_env_factory",
    "main",
    "rank_env_settings",
    "resolve_device",
    "resume_checkpoint",
    "run_training",
]


@dataclasses.dataclass(frozen=True)
class DistInfo:
    rank: int = 0
    local_rank: int = 0
    world_size: int = 1

    @classmethod
    def from_env(cls) -> DistInfo:
        return cls(
            rank=int(os.getenv("RANK", "0")),
            local_rank=int(os.getenv("LOCAL_RANK", "0")),
            world_size=int(os.getenv("WORLD_SIZE", "1")),
        )


def resolve_device(device: str, dist: DistInfo) -> str:
    """Validate ``--device``; with several CUDA ranks each uses ``cuda:<local_rank>``."""
    try:
        dev = torch.device(device)
    except RuntimeError:
        raise ValueError(f"invalid --device '{device}' (use cpu or cuda[:i])") from None
    if dev.type == "cpu":
        return "cpu"
    if dev.type != "cuda":
        raise ValueError(f"unsupported --device '{device}' (use cpu or cuda[:i])")
    if not torch.cuda.is_available():
        raise ValueError(f"--device {device}: this torch build has no CUDA (torch {torch.__version__})")
    if dist.world_size > 1:
        return f"cuda:{dist.local_rank}"
    return f"cuda:{dev.index or 0}"


def load_env_factory(spec: str) -> Callable[..., Any]:
    """``'module:function'`` -> the callable that builds the VecEnv."""
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"--env_factory must look like 'module:function', got '{spec}'")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        raise ValueError(f"--env_factory: cannot import '{module_name}' ({exc})") from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise ValueError(f"--env_factory: '{module_name}' has no callable '{attr}'")
    return fn


def resume_checkpoint(experiment_dir: Path, load_run: str | None, checkpoint: str | None) -> Path:
    """Isaac Lab's resume rule: the latest (or ``load_run``-matching) run, its highest (or
    ``checkpoint``-matching) ``model_<N>.pt``. A ``checkpoint`` that is a path wins; a ``load_run``
    that is a path names the run folder itself."""
    if checkpoint and os.sep in checkpoint:
        path = Path(checkpoint)
        if not path.is_file():
            raise CheckpointError(f"checkpoint not found: {path}")
        return path
    if load_run and os.sep in load_run:  # a run folder's path, as a user copies it from the log line
        if not Path(load_run).is_dir():
            raise CheckpointError(f"run folder not found: {load_run}")
        runs = [Path(load_run)]
    elif not experiment_dir.is_dir():
        raise CheckpointError(f"nothing to resume: no runs in {experiment_dir}")
    else:
        runs = sorted(p for p in experiment_dir.iterdir() if p.is_dir())
    if load_run and os.sep not in load_run:
        rx = re.compile(load_run)
        # A search, not a full match: run folders start with a timestamp, users remember the run name.
        runs = [p for p in runs if p.name == load_run or rx.search(p.name)]
        if not runs:
            raise CheckpointError(f"no run named or matching '{load_run}' in {experiment_dir}")
    # Newest first: the first run that holds a checkpoint (a run killed before its first save has none).
    errors = []
    for run in reversed(runs):
        if checkpoint and (run / checkpoint).is_file():
            return run / checkpoint
        try:
            return latest_checkpoint(run, checkpoint)
        except CheckpointError as exc:
            errors.append(str(exc))
    raise CheckpointError(errors[0] if len(errors) == 1 else f"no checkpoint in any run of {experiment_dir}")


def _json_default(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return dataclasses.asdict(obj)
    if isinstance(obj, tuple | set):
        return list(obj)
    return str(obj)


def _dump_params(log_dir: Path, env_cfg: Any, train_cfg: dict[str, Any], argv: Sequence[str]) -> None:
    params = log_dir / "params"
    params.mkdir(parents=True, exist_ok=True)
    env_dict = dataclasses.asdict(env_cfg) if dataclasses.is_dataclass(env_cfg) else env_cfg
    (params / "env.json").write_text(json.dumps(env_dict, indent=1, default=_json_default), encoding="utf-8")
    (params / "agent.json").write_text(
        json.dumps(train_cfg, indent=1, default=_json_default), encoding="utf-8"
    )
    (params / "command.txt").write_text(" ".join(argv) + "\n", encoding="utf-8")


def rank_env_settings(
    args: argparse.Namespace, dist: DistInfo
) -> tuple[int | None, int | None, dict[str, Any]]:
    """``(worlds of this rank, worlds every rank divides by, env overrides of this rank)`` from
    ``--num_envs``/``--rank_num_envs`` and ``--set``/``--rank_set``.

    The common divisor sizes PPO's mini-batches: every rank must run the same number of them, since
    each mini-batch ends in a gradient all-reduce that all ranks join.
    """
    per_rank = getattr(args, "rank_num_envs", None)
    rank_overrides = list(getattr(args, "rank_overrides", None) or ())
    bad = sorted({r for r, _ in rank_overrides if r >= dist.world_size})
    if bad:
        raise ValueError(f"--rank_set names rank(s) {bad}, but this run has {dist.world_size} rank(s)")
    # All ranks train one policy: what its actions mean (the checkpoint's contract) must be the same.
    meaning = sorted({key for _, (key, _) in rank_overrides if key in POLICY_INTERFACE})
    if meaning:
        raise ValueError(f"--rank_set cannot change {meaning} (what actions mean) per rank: use --set")
    overrides = dict(getattr(args, "overrides", None) or ())
    overrides.update(kv for r, kv in rank_overrides if r == dist.rank)
    if per_rank is None:
        return args.num_envs, args.num_envs, overrides
    if args.num_envs is not None:
        raise ValueError("give either --num_envs or --rank_num_envs, not both")
    if len(per_rank) != dist.world_size:
        raise ValueError(
            f"--rank_num_envs gives {len(per_rank)} count(s) for {dist.world_size} rank(s): give one per rank"
        )
    return per_rank[dist.rank], math.gcd(*per_rank), overrides


def _agent_cfg(args: argparse.Namespace) -> dict[str, Any]:
    """The task's agent (rsl-rl) config with the flags' changes: iterations, logger, ``--agent``
    values and a distillation teacher."""
    overrides: dict[str, Any] = {"logger": args.logger, "run_name": args.run_name}
    for key in (
        "max_iterations",
        "num_steps_per_env",
        "save_interval",
        "experiment_name",
        "resample_objects_every",
    ):
        if getattr(args, key, None) is not None:
            overrides[key] = getattr(args, key)
    if args.logger == "wandb":
        if importlib.util.find_spec("wandb") is None:
            raise ValueError("--logger wandb needs the wandb package (pip install wandb)")
        project = (
            args.log_project_name
            or overrides.get("experiment_name")
            or make_train_cfg(args.task)["experiment_name"]
        )
        overrides["logger"] = {"class_name": "WandbLogWriter", "project_name": project}
    train_cfg = make_train_cfg(args.task, **overrides)
    for dotted, value in getattr(args, "agent_overrides", None) or ():
        set_cfg_value(train_cfg, dotted, value)
    if getattr(args, "distill", None):
        train_cfg["distillation"]["teacher"] = args.distill
    return train_cfg


def _new_log_dir(experiment_dir: Path, run_name: str | None) -> Path:
    """Create this run's folder, ``<experiment_dir>/<YYYY-mm-dd_HH-MM-SS>[_<run_name>]``."""
    stamp = datetime.datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    name = stamp + (f"_{run_name}" if run_name else "")
    log_dir = experiment_dir / name
    suffix = 1
    while log_dir.exists():  # two runs in the same second
        log_dir = experiment_dir / f"{name}-{suffix}"
        suffix += 1
    log_dir.mkdir(parents=True)
    return log_dir


def run_training(
    args: argparse.Namespace,
    argv: Sequence[str] = (),
    work: Callable[[D3GraspRunner], None] | None = None,
) -> D3GraspRunner:
    """Train as ``args`` (``make_train_parser()``'s flags) say; returns the runner (its ``log_dir``
    is the run folder on rank 0 and None on other ranks; its environment is closed).

    ``work``: instead of training, call ``work(runner)`` on the runner built and loaded as training
    would build it, with no run folder (measurements at a checkpoint: d3grasp.train.gradient_noise)."""
    dist = DistInfo.from_env()
    get_task(args.task)  # unknown task -> UnknownTaskError before anything is built
    device = resolve_device(args.device, dist)
    torch.set_num_threads(resolve_torch_threads(args.torch_threads))

    train_cfg = _agent_cfg(args)

    experiment_dir = Path(args.log_root) / train_cfg["experiment_name"]
    resume_path = resume_checkpoint(experiment_dir, args.load_run, args.checkpoint) if args.resume else None
    trust = bool(getattr(args, "trust_checkpoint", False))
    if resume_path is not None and not trust:
        refuse_code(resume_path)  # a code-carrying file fails now, before the environment is built

    seed = int(args.seed) + dist.rank
    seed_everything(seed)
    make = load_env_factory(args.env_factory)
    num_envs, common_envs, env_overrides = rank_env_settings(args, dist)

    def build_env(draw: int) -> Any:
        # Draw k (= completed iterations // resample_objects_every) of the objects: the same worlds
        # seeded apart, so each draw picks other objects; the first segment uses the base seed.
        return make(args.task, num_envs=num_envs, device=device, seed=seed + 1000 * draw, **env_overrides)

    env = build_env(0)
    runner: D3GraspRunner | None = None
    try:
        alg = train_cfg["algorithm"]
        alg["num_mini_batches"] = fit_mini_batches(alg["num_mini_batches"], common_envs or env.num_envs)

        log_dir: Path | None = None
        if dist.rank == 0 and work is None:
            log_dir = _new_log_dir(experiment_dir, args.run_name)
            print(f"[d3grasp] logging to {log_dir}")

        runner_class = D3GraspRunner
        if train_cfg["distillation"]["teacher"]:
            from d3grasp.train.distill import DaggerRunner

            runner_class = DaggerRunner
        runner = runner_class(
            env, train_cfg, log_dir=log_dir, device=device, task_name=args.task, env_builder=build_env
        )
        if resume_path is not None:
            runner.load(str(resume_path), trust=trust)
            print(f"[d3grasp] resumed from {resume_path} at iteration {runner.current_learning_iteration}")
        if log_dir is not None:
            train_cfg["resumed_from"] = None if resume_path is None else str(resume_path)
            train_cfg["world_size"] = dist.world_size
            _dump_params(log_dir, getattr(env, "cfg", {}), train_cfg, argv)
        if work is not None:
            work(runner)
            return runner
        runner.learn(
            int(train_cfg["max_iterations"]), init_at_random_ep_len=bool(train_cfg["init_at_random_ep_len"])
        )
        return runner
    finally:
        # The runner may have replaced the env by a new draw of objects (resample_objects_every).
        close_env(runner.env if runner is not None else env)
        if torch.distributed.is_available() and torch.distributed.is_initialized():
            torch.distributed.destroy_process_group()


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = make_train_parser()
    args = parser.parse_args(argv)

    def body() -> None:
        run_training(args, ["d3grasp-train", *argv])

    return run_command("d3grasp-train", body)


if __name__ == "__main__":
    raise SystemExit(main())
