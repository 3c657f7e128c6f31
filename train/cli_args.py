"""Command-line flags of ``d3grasp-train`` and ``d3grasp-play``, named as Isaac Lab's rsl-rl scripts
name them (``--task``, ``--num_envs``, ``--max_iterations``, ``--resume --load_run --checkpoint``, ...).
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from d3grasp.cli.args import (
    add_env_override_arg,
    add_trust_arg,
    non_negative_int,
    parse_override,
    positive_int,
)
from d3grasp.envs.config import PERCEPTION_MODES
from d3grasp.envs.registry import DEFAULT_TASK

__all__ = ["add_common_args", "make_play_parser", "make_train_parser"]


def _size(value: str) -> tuple[int, int]:
    w, sep, h = value.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 8 or int(h) < 8:
        raise argparse.ArgumentTypeError(f"expected WxH in pixels (at least 8x8), got '{value}'")
    return int(w), int(h)


def _rank_override(text: str) -> tuple[int, tuple[str, Any]]:
    """``"1:objects.kinds=[\"deformable\"]"`` -> ``(1, ("objects__kinds", ("deformable",)))``."""
    rank, sep, rest = text.partition(":")
    if not sep or not rank.strip().isdigit():
        raise argparse.ArgumentTypeError(f"--rank_set expects RANK:KEY=VALUE, got '{text}'")
    return int(rank), parse_override(rest)


def _agent_override(text: str) -> tuple[str, Any]:
    """``"algorithm.learning_rate=1e-4"`` -> ``("algorithm.learning_rate", 0.0001)``."""
    key, value = parse_override(text)
    return key.replace("__", "."), value


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
    add_trust_arg(parser)


def make_train_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="d3grasp-train",
        description="Train a D3Grasp policy with rsl-rl PPO (multi-process: torchrun --nproc_per_node=P "
        "-m d3grasp.train.train ...).",
    )
    add_common_args(p)
    p.add_argument("--max_iterations", type=positive_int, default=None, help="PPO iterations to run")
    p.add_argument(
        "--num_steps_per_env",
        type=positive_int,
        default=None,
        help="rollout length per iteration (default: one episode)",
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
        "--agent",
        dest="agent_overrides",
        action="append",
        type=_agent_override,
        default=[],
        metavar="KEY=VALUE",
        help="override a runner/PPO config value, e.g. algorithm.learning_rate=1e-4 or "
        "actor.distribution_cfg.init_std=0.15 (recorded in params/agent.json)",
    )
    p.add_argument(
        "--rank_set",
        dest="rank_overrides",
        action="append",
        type=_rank_override,
        default=[],
        metavar="RANK:KEY=VALUE",
        help="an env override for one rank only (after --set), e.g. 1:objects.kinds='[\"deformable\"]': "
        "rigid and soft worlds on separate ranks, so the rigid ones keep the cheaper solver settings",
    )
    p.add_argument(
        "--rank_num_envs",
        type=positive_int,
        nargs="+",
        default=None,
        metavar="N",
        help="worlds of each rank, one count per rank (instead of --num_envs), e.g. 48 8 to give the "
        "rigid rank as many worlds as it steps in the soft rank's time",
    )
    p.add_argument(
        "--distill",
        choices=("teacher",),
        default=None,
        help="train by DAgger from the privileged teacher instead of PPO (needs a wrist and camera "
        "perception, e.g. --set palm_offset_limit=0.02 --set palm_yaw_limit=0.3 --set perception=camera, "
        "the teacher's evaluation wrist)",
    )
    p.add_argument(
        "--resume", action="store_true", help="continue from a checkpoint (weights, optimizer, count)"
    )
    p.add_argument(
        "--load_run",
        default=None,
        help="run to resume: its folder's name, a regex, or its path (default: latest)",
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
    add_env_override_arg(p, "env config override, e.g. phases.disturb_per_direction=0.5 (repeatable)")
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
    p.add_argument(
        "--export_dir",
        default=None,
        help="folder for policy.pt and policy.onnx (default: exported/ next to the checkpoint; "
        "for --checkpoint shipped, exported/ in the current folder)",
    )
    p.add_argument("--latency_steps", type=positive_int, default=200, help="policy steps timed (default 200)")
    p.add_argument("--max_steps", type=positive_int, default=None, help="stop after this many env steps")
    p.add_argument(
        "--verbose", action="store_true", help="also what Warp and rsl-rl report (module loads, models)"
    )
    return p
