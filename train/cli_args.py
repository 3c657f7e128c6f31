"""Command-line flags of ``d3grasp-train`` and ``d3grasp-play``, named as Isaac Lab's rsl-rl scripts
name them (``--task``, ``--num_envs``, ``--max_iterations``, ``--resume --load_run --checkpoint``, ...).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from typing import Any

from d3grasp.envs.config import PERCEPTION_MODES
from d3grasp.envs.registry import DEFAULT_TASK

__all__ = [
    "add_common_args",
    "add_env_override_arg",
    "make_play_parser",
    "make_train_parser",
    "non_negative_int",
    "parse_override",
    "positive_float",
    "positive_int",
    "resolve_torch_threads",
    "run_command",
]


def positive_int(value: str) -> int:
    """argparse type: an integer >= 1."""
    n = int(value)
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {value}")
    return n


def non_negative_int(value: str) -> int:
    """argparse type: an integer >= 0."""
    n = int(value)
    if n < 0:
        raise argparse.ArgumentTypeError(f"must be a non-negative integer, got {value}")
    return n


def positive_float(value: str) -> float:
    """argparse type: a number > 0."""
    x = float(value)
    if not x > 0.0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {value}")
    return x


def _size(value: str) -> tuple[int, int]:
    w, sep, h = value.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 8 or int(h) < 8:
        raise argparse.ArgumentTypeError(f"expected WxH in pixels (at least 8x8), got '{value}'")
    return int(w), int(h)


def parse_override(text: str) -> tuple[str, Any]:
    """``"phases.disturb_per_direction=0.1"`` -> ``("phases__disturb_per_direction", 0.1)``.

    The value is read as JSON when it parses (numbers, true/false, lists), else kept as a string.
    """
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"--set expects KEY=VALUE, got '{text}'")
    try:
        value: Any = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    if isinstance(value, list):
        value = tuple(value)  # config sequences are tuples
    return key.strip().replace(".", "__"), value


def add_env_override_arg(parser: argparse.ArgumentParser, help_text: str) -> None:
    """``--set KEY=VALUE`` (repeatable): environment config overrides, collected in ``args.overrides``."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        type=parse_override,
        default=[],
        metavar="KEY=VALUE",
        help=help_text,
    )


def add_common_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", default=DEFAULT_TASK, help=f"registered task name (default {DEFAULT_TASK})")
    parser.add_argument(
        "--num_envs", type=positive_int, default=None, help="worlds per process (default: the task's)"
    )
    parser.add_argument("--seed", type=int, default=0, help="random seed (rank r uses seed + r)")
    parser.add_argument(
        "--device", default="cpu", help="cpu or cuda[:i] (multi-process CUDA: one GPU per rank)"
    )
    parser.add_argument(
        "--torch_threads",
        type=positive_int,
        default=None,
        help="torch CPU threads per process (default 1: scale with processes, one per core)",
    )
    parser.add_argument(
        "--env_factory",
        default="d3grasp.envs:make_env",
        help="advanced: 'module:function(task, num_envs, device, seed)' returning an rsl-rl VecEnv",
    )


def make_train_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="d3grasp-train",
        description="Train a D3Grasp policy with rsl-rl PPO (multi-process: torchrun --nproc_per_node=P "
        "-m d3grasp.train.train ...).",
    )
    add_common_args(p)
    p.add_argument("--max_iterations", type=positive_int, default=None, help="PPO iterations to run")
    p.add_argument(
        "--num_steps_per_env", type=positive_int, default=None, help="rollout length per iteration"
    )
    p.add_argument("--save_interval", type=positive_int, default=None, help="checkpoint every N iterations")
    p.add_argument(
        "--resample_objects_every",
        type=non_negative_int,
        default=None,
        help="rebuild the worlds with other objects every N iterations (0: never; default: the task's)",
    )
    p.add_argument(
        "--experiment_name", default=None, help="log folder under the log root (default: from task)"
    )
    p.add_argument("--run_name", default="", help="suffix of the run folder <timestamp>_<run_name>")
    p.add_argument("--log_root", default=os.path.join("logs", "rsl_rl"), help="default logs/rsl_rl")
    p.add_argument("--logger", choices=("tensorboard", "wandb"), default="tensorboard")
    p.add_argument("--log_project_name", default=None, help="wandb project (default: experiment name)")
    add_env_override_arg(
        p,
        "override a training env config field, e.g. phases.disturb_per_direction=1.0 (recorded in "
        "params/env.json; evaluation uses the task's own config)",
    )
    p.add_argument(
        "--resume", action="store_true", help="continue from a checkpoint (weights, optimizer, count)"
    )
    p.add_argument(
        "--load_run", default=None, help="run folder name or regex to resume from (default: latest)"
    )
    p.add_argument(
        "--checkpoint",
        default=None,
        help="checkpoint file name or regex in that run (default: highest model_<N>.pt), or a path",
    )
    return p


def make_play_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="d3grasp-play",
        description="Run a trained D3Grasp policy, report grasp outcomes, export TorchScript/ONNX, time it.",
    )
    add_common_args(p)
    p.add_argument(
        "--checkpoint",
        required=True,
        help="path of a model_<N>.pt written by d3grasp-train, 'shipped' (the package's trained policy) "
        "or 'baseline' (the rule-based controller)",
    )
    p.add_argument(
        "--episodes", type=positive_int, default=10, help="finished episodes to evaluate (default 10)"
    )
    p.add_argument("--video", default=None, help="out.gif | out.mp4: ray-traced rollout of the first worlds")
    p.add_argument("--video_fps", type=float, default=30.0, help="video and USD frame rate (default 30)")
    p.add_argument(
        "--video_size",
        type=_size,
        default=(240, 180),
        metavar="WxH",
        help="px per world tile (default 240x180)",
    )
    p.add_argument(
        "--video_worlds", type=positive_int, default=4, help="worlds tiled in the video / USD (default 4)"
    )
    p.add_argument("--video_frames", type=positive_int, default=None, help="stop the video after N frames")
    p.add_argument("--usd", default=None, help="out.usd(a): time-sampled USD animation of the rollout")
    p.add_argument("--tactile_plot", default=None, help="out.png: pad forces over world 0's first episode")
    p.add_argument(
        "--perception",
        choices=PERCEPTION_MODES,
        default=None,
        help="object pose for the grasp planner: simulator truth or the RGB-D camera (default: the task's)",
    )
    p.add_argument("--no_export", action="store_true", help="skip the TorchScript/ONNX export")
    p.add_argument("--latency_steps", type=positive_int, default=200, help="policy steps timed (default 200)")
    p.add_argument("--max_steps", type=positive_int, default=None, help="stop after this many env steps")
    p.add_argument(
        "--verbose", action="store_true", help="also what Warp and rsl-rl report (module loads, models)"
    )
    return p


def resolve_torch_threads(requested: int | None) -> int:
    """Threads for this process: explicit, else 1.

    One thread per process is the default because the simulation of a rank is one CPU thread and
    the PPO update of these small networks gains little from more: measured on the 2-core machine
    with another job running, one process with 2 torch threads took 8.5 s per update at 32 worlds
    (OpenMP threads spinning against the busy core) against 0.5 s with 1 thread per rank.
    """
    return 1 if requested is None else requested


def run_command(prog: str, body: Callable[[], int | None], *, one_line: bool = False) -> int:
    """Run a command's body with the commands' shared error contract.

    A bad task, a checkpoint that does not fit, bad input or a missing file print
    ``<prog>: error: <reason>`` and exit 2 (``one_line`` folds a multi-line reason onto one line);
    Ctrl-C prints ``<prog>: aborted`` and exits 130; ``D3GRASP_DEBUG=1`` re-raises for a traceback.
    """
    from d3grasp.train.runner import CheckpointError

    from d3grasp.envs.registry import UnknownTaskError

    try:
        code = body()
    except (UnknownTaskError, CheckpointError, ValueError, FileNotFoundError) as exc:
        if os.getenv("D3GRASP_DEBUG"):
            raise
        reason = " ".join(str(exc).split()) if one_line else str(exc)
        print(f"{prog}: error: {reason}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: aborted", file=sys.stderr)
        return 130
    return 0 if code is None else code
