"""Training curves of a run as one PNG: mean return, success rates and reward terms over iterations.

    python -m d3grasp.train.curves logs/rsl_rl/<experiment>/<run> [<resumed run> ...] --out curves.png

Reads the TensorBoard event files of the run folders given (a run and the runs resumed from it, in
order: their iteration counts continue, so they are drawn as one curve) and plots against the
learning iteration: the mean episode return, the success rates logged per finished batch of
episodes (``Success/s_*/all``, smoothed over a window because a batch holds only a few episodes),
and each reward term's mean per step.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from d3grasp.vocabulary import METRICS

__all__ = ["load_scalars", "plot_run", "main"]


def load_scalars(*run_dirs: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{tag: (steps, values)}`` over every event file of the runs, later files winning on a step."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    files = []
    for run_dir in run_dirs:
        found = sorted(Path(run_dir).glob("events.out.tfevents.*"))
        if not found:
            raise FileNotFoundError(
                f"{run_dir}: no TensorBoard event files (not a d3grasp-train run folder?)"
            )
        files += found
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


def _smooth(x: np.ndarray, window: int, weights: np.ndarray | None = None) -> np.ndarray:
    """Trailing (weighted) moving average over ``window`` points; the first points average what exists.

    Success rates are weighted by the episodes behind each point: a batch of 1 episode must not
    count as much as a batch of 24.
    """
    if len(x) == 0 or window <= 1:
        return x
    w = np.ones_like(x) if weights is None else np.asarray(weights, dtype=np.float64)
    cx = np.cumsum(np.insert(x * w, 0, 0.0))
    cw = np.cumsum(np.insert(w, 0, 0.0))
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(idx - window, 0)
    return (cx[idx] - cx[lo]) / np.maximum(cw[idx] - cw[lo], 1e-12)


def plot_run(
    run_dirs: str | Path | Sequence[str | Path],
    out: str | Path,
    steps_per_iteration: int | None = None,
    window: int = 10,
) -> Path:
    """Write the curves PNG of a run (or a run and its resumptions); ``steps_per_iteration`` labels
    the x axis with the env-steps an iteration consumed."""
    if isinstance(run_dirs, (str, Path)):
        run_dirs = [run_dirs]
    from d3grasp.viz.figure import pyplot, save_figure

    plt = pyplot()
    s = load_scalars(*run_dirs)
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
    # Episodes finished in each iteration (the weights of that iteration's success rates).
    episodes = dict(zip(*s["Success/episodes"], strict=True)) if "Success/episodes" in s else {}
    for name, color in zip(METRICS, ("tab:green", "tab:orange", "tab:red"), strict=True):
        tag = f"Success/{name}/all"
        if tag in s:
            it, v = s[tag]
            counts = np.array([episodes.get(int(i), 1.0) for i in it])
            ax.plot(it, _smooth(v, window, counts), color=color, label=name)
    ax.set_ylim(-0.02, 1.02)
    ax.set_title(f"success rate (episode-weighted, last {window} logged batches)")
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

    fig.suptitle(" + ".join(Path(d).name for d in run_dirs))
    return save_figure(fig, out, dpi=90)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m d3grasp.train.curves", description=__doc__.split("\n")[0])
    p.add_argument("run_dir", nargs="+", help="d3grasp-train run folder(s): a run, then its resumptions")
    p.add_argument("--out", default=None, help="PNG path (default <last run_dir>/curves.png)")
    p.add_argument("--steps_per_iteration", type=int, default=None, help="num_envs x steps per env x ranks")
    p.add_argument("--window", type=int, default=10, help="moving-average window in logged points")
    args = p.parse_args(argv)
    try:
        out = args.out or Path(args.run_dir[-1]) / "curves.png"
        path = plot_run(args.run_dir, out, args.steps_per_iteration, args.window)
    except FileNotFoundError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
