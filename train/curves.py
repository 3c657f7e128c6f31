"""Training curves of a run as one PNG: mean return, success rates and reward terms over iterations.

    python -m d3grasp.train.curves logs/rsl_rl/<experiment>/<run> --out curves.png

Reads the run's TensorBoard event files (every file in the folder, so a resumed run that wrote a
second file is drawn as one curve) and plots, against the learning iteration and the env-steps
consumed: the mean episode return, the success rates logged per finished batch of episodes
(``Success/s_*/all``, smoothed over a window because a batch holds only a few episodes), and each
reward term's mean per step.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["load_scalars", "plot_run", "main"]

_SUCCESS = ("s_grasp", "s_lift", "s_disturb")


def load_scalars(run_dir: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{tag: (steps, values)}`` over every event file of a run, later files winning on a step."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = sorted(Path(run_dir).glob("events.out.tfevents.*"))
    if not files:
        raise FileNotFoundError(
            f"{run_dir}: no TensorBoard event files (is this a d3grasp-train run folder?)"
        )
    merged: dict[str, dict[int, float]] = {}
    for f in files:
        acc = EventAccumulator(str(f), size_guidance={"scalars": 0})  # 0: keep every point
        acc.Reload()
        for tag in acc.Tags()["scalars"]:
            merged.setdefault(tag, {}).update({e.step: e.value for e in acc.Scalars(tag)})
    out = {}
    for tag, points in merged.items():
        steps = np.array(sorted(points), dtype=np.int64)
        out[tag] = (steps, np.array([points[s] for s in steps], dtype=np.float64))
    return out


def _smooth(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average (the first points average what exists so far)."""
    if len(x) == 0 or window <= 1:
        return x
    c = np.cumsum(np.insert(x, 0, 0.0))
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def plot_run(
    run_dir: str | Path, out: str | Path, steps_per_iteration: int | None = None, window: int = 10
) -> Path:
    """Write the curves PNG of a run; ``steps_per_iteration`` adds an env-steps axis label."""
    from d3grasp.viz.figure import pyplot, save_figure

    plt = pyplot()
    s = load_scalars(run_dir)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    xlabel = "learning iteration"
    if steps_per_iteration:
        xlabel += f" (x {steps_per_iteration} env-steps)"

    ax = axes[0]
    if "Train/mean_reward" in s:
        it, v = s["Train/mean_reward"]
        ax.plot(it, v, color="tab:blue")
    ax.set_title("mean episode return")
    ax.set_xlabel(xlabel)
    ax.grid(alpha=0.3)

    ax = axes[1]
    for name, color in zip(_SUCCESS, ("tab:green", "tab:orange", "tab:red"), strict=True):
        tag = f"Success/{name}/all"
        if tag in s:
            it, v = s[tag]
            ax.plot(it, v, color=color, alpha=0.2)
            ax.plot(it, _smooth(v, window), color=color, label=name)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"success per finished batch (moving average of {window})")
    ax.set_xlabel(xlabel)
    ax.legend(loc="upper left")
    ax.grid(alpha=0.3)

    ax = axes[2]
    for tag in sorted(t for t in s if t.startswith("Reward/")):
        it, v = s[tag]
        ax.plot(it, _smooth(v, window), label=tag.split("/", 1)[1])
    ax.set_title("reward terms per step (moving average)")
    ax.set_xlabel(xlabel)
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)

    fig.suptitle(Path(run_dir).name)
    return save_figure(fig, out, dpi=90)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m d3grasp.train.curves", description=__doc__.split("\n")[0])
    p.add_argument("run_dir", help="a d3grasp-train run folder (holds events.out.tfevents.*)")
    p.add_argument("--out", default=None, help="PNG path (default <run_dir>/curves.png)")
    p.add_argument("--steps_per_iteration", type=int, default=None, help="num_envs x steps per env x ranks")
    p.add_argument("--window", type=int, default=10, help="moving-average window in logged points")
    args = p.parse_args(argv)
    try:
        path = plot_run(
            args.run_dir, args.out or Path(args.run_dir) / "curves.png", args.steps_per_iteration, args.window
        )
    except FileNotFoundError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
