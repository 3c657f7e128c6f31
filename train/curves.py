"""Training curves of a run as one PNG, and when its success rates reached each milestone.

    python -m d3grasp.train.curves logs/rsl_rl/<experiment>/<run> [<resumed run> ...] --out curves.png \
        [--baseline s_lift=0.75] [--milestones 0.5 0.7 0.85]

Reads the TensorBoard event files of the run folders given (a run and the runs resumed from it, in
order: their iteration counts continue, so they are drawn as one curve). Plots the mean episode
return and each reward term's mean per step against the learning iteration, and the success rates
logged per finished batch of episodes (``Success/s_*/all``, smoothed over a window because a batch
holds only a few episodes) against the env-steps and the wall-clock the run had consumed
(``Progress/*``, cumulative over resumptions). Prints a table of the iteration, env-steps and
wall-clock at which each smoothed rate first reached each milestone (and first exceeded the
baseline's rate, when given), and the training diagnostics (``Diagnostics/*``, d3grasp.train.ppo)
summarised over a window of iterations (``--diagnostics_window``, default 10-50).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from d3grasp.vocabulary import METRICS

__all__ = [
    "DiagnosticSummary",
    "Milestone",
    "diagnostics_markdown",
    "diagnostics_summary",
    "load_scalars",
    "main",
    "milestones",
    "milestones_markdown",
    "plot_run",
    "smoothed_success",
]


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


def _progress_axes(s: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, dict[int, float]]:
    """Iteration -> cumulative env-steps and wall-clock seconds (``Progress/*``, logged since
    2026-12-05; empty for older runs)."""
    out: dict[str, dict[int, float]] = {}
    for name in ("env_steps", "wall_clock_s"):
        tag = f"Progress/{name}"
        if tag in s:
            out[name] = dict(zip(s[tag][0].tolist(), s[tag][1].tolist(), strict=True))
    return out


def smoothed_success(
    s: dict[str, tuple[np.ndarray, np.ndarray]], metric: str, window: int
) -> tuple[np.ndarray, np.ndarray]:
    """Iterations and the episode-weighted moving average of ``Success/<metric>/all`` over the last
    ``window`` logged batches (a batch of 1 episode must not count as much as a batch of 24)."""
    tag = f"Success/{metric}/all"
    if tag not in s:
        return np.zeros(0, dtype=np.int64), np.zeros(0)
    episodes = dict(zip(*s["Success/episodes"], strict=True)) if "Success/episodes" in s else {}
    it, v = s[tag]
    counts = np.array([episodes.get(int(i), 1.0) for i in it])
    return it, _smooth(v, window, counts)


@dataclass(frozen=True)
class Milestone:
    """The first logged iteration at which a smoothed success rate reached ``rate``."""

    metric: str
    rate: float
    label: str
    iteration: int | None  # None: never reached
    env_steps: float | None
    wall_clock_s: float | None


def milestones(
    s: dict[str, tuple[np.ndarray, np.ndarray]],
    rates: Sequence[float] = (0.5, 0.7, 0.85),
    baselines: dict[str, float] | None = None,
    window: int = 10,
) -> list[Milestone]:
    """When each success metric first reached each rate, and first exceeded the baseline's rate of
    that metric (``baselines``: metric -> rate measured under the training conditions)."""
    progress = _progress_axes(s)
    out = []
    for metric in METRICS:
        it, v = smoothed_success(s, metric, window)
        targets = [(r, f"{100 * r:.0f}%", False) for r in rates]
        if baselines and metric in baselines:
            base = baselines[metric]
            targets.insert(0, (base, f"above the baseline's {100 * base:.1f}%", True))
        for rate, label, strict in targets:
            hit = np.nonzero(v > rate if strict else v >= rate)[0]
            i = int(it[hit[0]]) if len(hit) else None
            out.append(
                Milestone(
                    metric,
                    rate,
                    label,
                    i,
                    progress.get("env_steps", {}).get(i) if i is not None else None,
                    progress.get("wall_clock_s", {}).get(i) if i is not None else None,
                )
            )
    return out


def milestones_markdown(rows: Sequence[Milestone]) -> str:
    lines = [
        "| metric | milestone | iteration | env-steps | wall-clock (min) |",
        "|---|---|---|---|---|",
    ]
    for m in rows:
        if m.iteration is None:
            lines.append(f"| {m.metric} | {m.label} | not reached | | |")
            continue
        steps = f"{m.env_steps:,.0f}" if m.env_steps is not None else "not logged"
        wall = f"{m.wall_clock_s / 60:.1f}" if m.wall_clock_s is not None else "not logged"
        lines.append(f"| {m.metric} | {m.label} | {m.iteration} | {steps} | {wall} |")
    return "\n".join(lines)


def plot_run(
    run_dirs: str | Path | Sequence[str | Path],
    out: str | Path,
    window: int = 10,
    baselines: dict[str, float] | None = None,
    scalars: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Path:
    """Write the curves PNG of a run (or a run and its resumptions): the return and the reward
    terms against the learning iteration, the success rates against env-steps and wall-clock (the
    baseline's rates, when given, as dashed lines). ``scalars``: the runs' ``load_scalars``, when
    already read."""
    if isinstance(run_dirs, (str, Path)):
        run_dirs = [run_dirs]
    from d3grasp.viz.figure import pyplot, save_figure

    plt = pyplot()
    s = load_scalars(*run_dirs) if scalars is None else scalars
    progress = _progress_axes(s)
    fig, axes = plt.subplots(2, 2, figsize=(13, 8.4))

    ax = axes[0, 0]
    if "Train/mean_reward" in s:
        it, v = s["Train/mean_reward"]
        ax.plot(it, v, color="tab:blue")
    ax.set_title("mean episode return")
    ax.set_xlabel("learning iteration")
    ax.grid(alpha=0.3)

    x_axes = (("env_steps", "env-steps (all ranks)", 1.0), ("wall_clock_s", "wall-clock (min)", 1 / 60))
    for ax, (name, xlabel, unit) in zip(axes[:, 1], x_axes, strict=True):
        to_x = progress.get(name)
        for metric, color in zip(METRICS, ("tab:green", "tab:orange", "tab:red"), strict=True):
            it, v = smoothed_success(s, metric, window)
            x = [to_x.get(int(i), np.nan) * unit for i in it] if to_x else it
            ax.plot(x, v, color=color, label=metric)
            if baselines and metric in baselines:
                ax.axhline(
                    baselines[metric], color=color, linestyle="--", linewidth=1, label=f"{metric}, baseline"
                )
        ax.set_ylim(-0.02, 1.02)
        ax.set_title(f"success rate (episode-weighted, last {window} logged batches)")
        ax.set_xlabel(xlabel if to_x else "learning iteration (this run logged no progress)")
        ax.legend(loc="upper left")
        ax.grid(alpha=0.3)

    ax = axes[1, 0]
    for tag in sorted(t for t in s if t.startswith("Reward/")):
        it, v = s[tag]
        ax.plot(it, _smooth(v, window), label=tag.split("/", 1)[1])
    ax.set_title("reward terms per step (moving average)")
    ax.set_xlabel("learning iteration")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)

    fig.suptitle(" + ".join(Path(d).name for d in run_dirs))
    fig.tight_layout()
    return save_figure(fig, out, dpi=90)


@dataclass(frozen=True)
class DiagnosticSummary:
    """One ``Diagnostics/*`` tag over a window of iterations: the median, the lowest and highest, the
    count of iterations with a finite value, and the last logged value."""

    tag: str
    median: float
    low: float
    high: float
    count: int
    last: float


def diagnostics_summary(
    scalars: dict[str, tuple[np.ndarray, np.ndarray]], first: int = 10, last: int = 50
) -> list[DiagnosticSummary]:
    """The training diagnostics (``Diagnostics/*``: episodes per update, the critic's explained
    variance overall and per phase, the split-half gradient cosine; d3grasp.train.ppo) over the
    iterations ``first`` to ``last`` inclusive. Tags with no finite value in the window are left out."""
    rows = []
    for tag in sorted(t for t in scalars if t.startswith("Diagnostics/")):
        steps, values = scalars[tag]
        sel = values[(steps >= first) & (steps <= last)]
        sel = sel[np.isfinite(sel)]
        if len(sel) == 0:
            continue
        rows.append(
            DiagnosticSummary(
                tag=tag.removeprefix("Diagnostics/"),
                median=float(np.median(sel)),
                low=float(sel.min()),
                high=float(sel.max()),
                count=len(sel),
                last=float(values[-1]),
            )
        )
    return rows


def diagnostics_markdown(rows: Sequence[DiagnosticSummary], first: int, last: int) -> str:
    if not rows:
        return f"no training diagnostics logged in iterations {first}-{last}"
    lines = [
        f"| diagnostic (iterations {first}-{last}) | median | min | max | iterations | last |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r.tag} | {r.median:.3f} | {r.low:.3f} | {r.high:.3f} | {r.count} | {r.last:.3f} |")
    return "\n".join(lines)


def _baseline_arg(text: str) -> tuple[str, float]:
    metric, sep, value = text.partition("=")
    if not sep or metric not in METRICS:
        raise argparse.ArgumentTypeError(f"expected METRIC=RATE with METRIC one of {', '.join(METRICS)}")
    try:
        rate = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a rate in [0, 1]") from None
    if not 0.0 <= rate <= 1.0:
        raise argparse.ArgumentTypeError(f"{value!r} is not a rate in [0, 1]")
    return metric, rate


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m d3grasp.train.curves", description=__doc__.split("\n")[0])
    p.add_argument("run_dir", nargs="+", help="d3grasp-train run folder(s): a run, then its resumptions")
    p.add_argument("--out", default=None, help="PNG path (default <last run_dir>/curves.png)")
    p.add_argument("--window", type=int, default=10, help="moving-average window in logged points")
    p.add_argument(
        "--milestones", type=float, nargs="*", default=[0.5, 0.7, 0.85], help="success rates to report"
    )
    p.add_argument(
        "--baseline",
        type=_baseline_arg,
        action="append",
        default=[],
        metavar="METRIC=RATE",
        help="the baseline's rate under the training conditions (e.g. s_lift=0.75): when it was beaten",
    )
    p.add_argument(
        "--diagnostics_window",
        type=int,
        nargs=2,
        default=[10, 50],
        metavar=("FIRST", "LAST"),
        help="iterations over which the training diagnostics are summarised (default 10 50)",
    )
    args = p.parse_args(argv)
    try:
        out = args.out or Path(args.run_dir[-1]) / "curves.png"
        scalars = load_scalars(*args.run_dir)  # the event files are read once for both
        path = plot_run(args.run_dir, out, args.window, dict(args.baseline), scalars)
        rows = milestones(scalars, args.milestones, dict(args.baseline), args.window)
    except FileNotFoundError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(milestones_markdown(rows))
    first, last = args.diagnostics_window
    print(diagnostics_markdown(diagnostics_summary(scalars, first, last), first, last))
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
