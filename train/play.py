"""``d3grasp-play``: run a trained policy, report grasp outcomes, export it, time it.

    d3grasp-play --task D3Grasp-DexHand13-Mixed-v0 --checkpoint logs/rsl_rl/<exp>/<run>/model_1000.pt \
        [--num_envs 8] [--episodes 20]

Prints one line per finished episode (object, kind, size bin, grasp type, s_grasp / s_lift /
s_disturb, failure reason, peak strain) and the success rates overall and per kind / size bin /
grasp type; writes ``exported/policy.pt`` (TorchScript) and ``exported/policy.onnx`` next to the
checkpoint (``--export_dir`` elsewhere; the shipped policy's into ``./exported/`` of the current
folder, since its own exports live in the installed package); reports the latency of 200 sequential
single-robot policy steps.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

import torch  # noqa: E402
from d3grasp.train.cli_args import make_play_parser  # noqa: E402
from d3grasp.train.export import ExportPaths, LatencyReport, export_policy, measure_latency  # noqa: E402
from d3grasp.train.run_log import EpisodeStats  # noqa: E402
from d3grasp.train.runner import read_checkpoint  # noqa: E402
from d3grasp.train.train import DistInfo, load_env_factory, resolve_device  # noqa: E402

from d3grasp.cli.args import resolve_torch_threads, run_command  # noqa: E402
from d3grasp.console import set_verbosity  # noqa: E402
from d3grasp.controllers import Controller, make_controller  # noqa: E402
from d3grasp.envs import close_env  # noqa: E402
from d3grasp.envs.registry import get_task  # noqa: E402
from d3grasp.policies import BASELINE, SHIPPED, resolve_checkpoint  # noqa: E402
from d3grasp.policies.checkpoint import interface_overrides, observation_sizes  # noqa: E402
from d3grasp.seeding import seed_everything  # noqa: E402
from d3grasp.viz.rollout import PictureSettings, RolloutPictures  # noqa: E402

__all__ = ["Controller", "PlayResult", "format_episode", "main", "make_controller", "play"]


@dataclass
class PlayResult:
    episodes: list[dict[str, Any]] = field(default_factory=list)
    rates: dict[str, float] = field(default_factory=dict)
    steps: int = 0
    export: ExportPaths | None = None
    latency: LatencyReport | None = None


def _mark(flag: Any) -> str:
    return "yes" if flag else "no"


def format_episode(n: int, ep: dict[str, Any]) -> str:
    strain = ep.get("max_strain")
    return (
        f"{n:>4} env {ep.get('env', '?'):>3}  {str(ep.get('object', '?')):<20} "
        f"{str(ep.get('kind', '?')):<10} "
        f"{str(ep.get('size_bin', '?')):<6} {str(ep.get('grasp_type', '?')):<5}  "
        f"grasp {_mark(ep.get('s_grasp')):<3} lift {_mark(ep.get('s_lift')):<3} "
        f"disturb {_mark(ep.get('s_disturb')):<3}  "
        f"max_strain {float(strain) if strain is not None else float('nan'):.4f}  "
        f"failure: {ep.get('failure') or '-'}"
    )


def play(
    task: str,
    checkpoint: str | os.PathLike[str],
    num_envs: int | None = None,
    episodes: int = 10,
    device: str = "cpu",
    seed: int = 0,
    export: bool = True,
    latency_steps: int = 200,
    env_factory: str | Callable[..., Any] = "d3grasp.envs:make_env",
    max_steps: int | None = None,
    log: Callable[[str], None] = print,
    perception: str | None = None,
    pictures: PictureSettings | None = None,
    export_dir: str | os.PathLike[str] | None = None,
    trust_checkpoint: bool = False,
    env_overrides: dict[str, Any] | None = None,
) -> PlayResult:
    """Evaluate the checkpoint's deterministic policy until ``episodes`` episodes finished.

    The checkpoint is checked against the task's observation sizes before any weights load
    (``CheckpointError`` on mismatch or a missing file). The LSTM state of a world is zeroed when
    its episode ends, as in training. ``checkpoint="baseline"`` runs the rule-based controller
    (nothing to export or time). ``perception`` ("oracle" | "camera") overrides the task's; ``pictures``
    records a video, a USD animation and / or a tactile plot of the rollout. ``export_dir``: where
    the exports go (default ``exported/`` next to the checkpoint; for ``"shipped"``, ``exported/`` in
    the current folder: the package's files stay as installed). ``trust_checkpoint``: read a file
    that names code (``--trust-checkpoint``; refused otherwise). ``env_overrides``: ``make_env``
    overrides (``--set``).
    """
    get_task(task)
    is_baseline = str(checkpoint) == BASELINE
    ckpt = None if is_baseline else Path(resolve_checkpoint(str(checkpoint), task))  # "shipped" too
    # A bad or code-carrying file fails here, before the env is built.
    data = {} if ckpt is None else read_checkpoint(ckpt, trust=trust_checkpoint)
    device = resolve_device(device, DistInfo())
    make = load_env_factory(env_factory) if isinstance(env_factory, str) else env_factory
    seed_everything(seed)
    overrides = {} if perception is None else {"perception": perception}  # custom factories need not know it
    overrides |= interface_overrides(data)  # the checkpoint's action interface (none: nothing to pass)
    overrides |= env_overrides or {}  # --set goes over it (a checkpoint that then does not fit is refused)
    env = make(task, num_envs=num_envs, device=device, seed=seed, **overrides)
    result = PlayResult()
    try:
        controller = make_controller(env, task, BASELINE if ckpt is None else ckpt, device, data=data)
        who = "the rule-based baseline" if ckpt is None else f"{ckpt} (iteration {data.get('iter')})"
        log(f"[d3grasp] playing {who} on {task}, {env.num_envs} worlds")
        _rollout(env, controller, episodes, max_steps, pictures, result, log)
        actor = controller.actor
        if export and actor is not None:  # the baseline has nothing to export or time
            meta = {
                "task": task,
                "checkpoint": ckpt.name,
                "iteration": data.get("iter"),
                "obs_groups": ",".join(actor.obs_groups),
                "obs_dim": int(actor.obs_dim),
                "num_actions": int(env.num_actions),
                "obs_sizes": observation_sizes(env.get_observations()),
            }
            out = default_export_dir(str(checkpoint), ckpt) if export_dir is None else Path(export_dir)
            result.export = export_policy(actor, out, metadata=meta)
            log(f"[d3grasp] exported {result.export.jit} and {result.export.onnx}")
            result.latency = measure_latency(actor, result.export, int(actor.obs_dim), steps=latency_steps)
            for line in result.latency.lines():
                log(line)
    finally:
        close_env(env)
    return result


def default_export_dir(checkpoint: str, resolved: Path) -> Path:
    """``exported/`` next to the checkpoint; for the shipped policy ``exported/`` in the current
    folder, because its own exports are files of the installed package (which may not be writable)."""
    return Path("exported") if checkpoint == SHIPPED else resolved.parent / "exported"


def _rollout(
    env: Any,
    controller: Controller,
    episodes: int,
    max_steps: int | None,
    pictures: PictureSettings | None,
    result: PlayResult,
    log: Callable[[str], None],
) -> None:
    """Step ``env`` with ``controller`` until ``episodes`` episodes finished; fill ``result``, log."""
    pics = RolloutPictures(env, pictures) if pictures is not None and pictures.any else None
    stats = EpisodeStats()
    limit = max_steps or int(2 * (math.ceil(episodes / env.num_envs) + 1) * int(env.max_episode_length))
    obs = env.get_observations()
    with torch.inference_mode():
        while len(result.episodes) < episodes and result.steps < limit:
            obs, _, dones, extras = env.step(controller.act(obs).to(env.device))
            controller.on_dones(dones)
            result.steps += 1
            if pics is not None:
                pics.after_step(extras)
            for ep in extras.get("episodes", ()):
                if len(result.episodes) >= episodes:
                    break
                result.episodes.append(ep)
                stats.add([ep])
                log(format_episode(len(result.episodes), ep))
    if len(result.episodes) < episodes:
        log(f"[d3grasp] warning: only {len(result.episodes)} episodes finished in {result.steps} steps")
    result.rates = stats.rates()
    for line in _summary_lines(stats):
        log(line)
    if pics is not None:
        pics.finish(log)


def _summary_lines(stats: EpisodeStats) -> list[str]:
    counts = stats.counts
    lines = [f"{'group':<18}{'episodes':>9}{'s_grasp':>9}{'s_lift':>9}{'s_disturb':>10}"]
    for i, group in enumerate(stats.groups):
        n = float(counts[i, 0])
        if n == 0:
            continue
        rates = [100.0 * float(counts[i, 1 + j]) / n for j in range(3)]
        lines.append(f"{group:<18}{int(n):>9}{rates[0]:>8.1f}%{rates[1]:>8.1f}%{rates[2]:>9.1f}%")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    args: argparse.Namespace = make_play_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    torch.set_num_threads(resolve_torch_threads(args.torch_threads))
    set_verbosity(args.verbose)

    def body() -> None:
        if args.video:
            from d3grasp.viz.video import check_video_path

            check_video_path(args.video)  # before the checkpoint is read and the env is built
        play(
            args.task,
            args.checkpoint,
            num_envs=args.num_envs,
            episodes=args.episodes,
            device=args.device,
            seed=args.seed,
            export=not args.no_export,
            latency_steps=args.latency_steps,
            env_factory=args.env_factory,
            max_steps=args.max_steps,
            perception=args.perception,
            export_dir=args.export_dir,
            trust_checkpoint=args.trust_checkpoint,
            env_overrides=dict(args.overrides),
            pictures=PictureSettings(
                video=args.video,
                video_fps=args.video_fps,
                video_size=args.video_size,
                video_worlds=args.video_worlds,
                video_frames=args.video_frames,
                usd=args.usd,
                usd_worlds=args.video_worlds,
                tactile_plot=args.tactile_plot,
            ),
        )

    return run_command("d3grasp-play", body)


if __name__ == "__main__":
    raise SystemExit(main())
