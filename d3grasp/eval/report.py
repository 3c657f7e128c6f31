"""What an evaluation writes: ``results.json`` (every episode and its summaries), ``summary.csv``,
``table.md`` (the paper's tables, the paired comparisons, the localisation error) and ``plot.png``.

``results.json`` holds only what the settings determine (no timings, no paths), so two runs of one
seed write the same file (d3grasp.eval.evaluate).
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from d3grasp.envs.registry import apply_overrides, get_task
from d3grasp.eval.evaluate import EvalResult
from d3grasp.eval.metrics import (
    COLUMNS,
    ablation_markdown,
    aggregate,
    comparison_markdown,
    grasp_type_markdown,
    outcomes_markdown,
    summary_rows,
    table_markdown,
)
from d3grasp.eval.paired import compare_pairs, format_table, pair_episodes
from d3grasp.eval.specs import PAPER_REFERENCE, EvalSettings, RunSpec
from d3grasp.files import atomic_write_text
from d3grasp.policies import BASELINE
from d3grasp.policies.teacher import TEACHER
from d3grasp.vision.perception import localisation_markdown

__all__ = ["write_outputs"]


def _conditions(s: EvalSettings) -> str:
    """What every run of one evaluation shares: objects, split, repeats, grasp types and seed."""
    return (
        f"objects {s.objects or 'task default'}, split {s.split}, {s.episodes_per_object} episode(s) per "
        f"object, grasp types {s.grasp_types}, seed {s.seed}"
    )


def _spec_of(result: EvalResult, label: str) -> RunSpec:
    # A result built by hand (not by evaluate()) may carry no specs: fall back to its settings.
    s = result.settings
    checkpoint = BASELINE if label == BASELINE else str(s.checkpoint)
    return result.specs.get(label) or RunSpec(label, s.task, checkpoint)


def _baseline_name(task: str, overrides: Mapping[str, Any]) -> str:
    """What ``--checkpoint baseline`` ran on ``task``: the paper's touch rule, or the stall rule of the
    Base task (``rule.stop_on="stall"``: the Base ablation's prior, which reads no pad)."""
    cfg = apply_overrides(get_task(task).make_cfg(), dict(overrides))
    return "rule-based baseline" if cfg.rule.stop_on == "touch" else f"{cfg.rule.stop_on} rule (no touch)"


def _title(spec: RunSpec, s: EvalSettings) -> str:
    if spec.checkpoint == BASELINE:
        who = _baseline_name(spec.task, s.env_overrides)
    else:
        ckpt = Path(spec.checkpoint)
        who = f"{'policy' if spec.label == 'policy' else spec.label} {ckpt.name}"
        if s.ablation:  # several checkpoints are often all model_<N>.pt: name the run folder too
            who = f"{spec.label} {ckpt.parent.name}/{ckpt.name}"
    if spec.label.endswith("/camera"):  # a controller under camera perception (camera, both, paper)
        who += ", camera perception"
    elif spec.label == PAPER_REFERENCE:
        who += ", oracle pose (the reference for perfect localisation)"
    return f"{who} on {spec.task}: {_conditions(s)}"


def _ablation_header(spec: RunSpec, label: str, overrides: Mapping[str, Any]) -> str:
    """The ablation table's column head of run ``label``: which senses the actor reads and whether the
    critic is asymmetric (reads the privileged group), as in the paper's ablation table; the baseline's
    with its perception where the label names one (``baseline/camera`` beside ``baseline/oracle``)."""
    if spec.checkpoint == BASELINE:
        _, _, perception = label.partition("/")
        name = _baseline_name(spec.task, overrides)
        return f"{name}, {perception}" if perception else name
    task = get_task(spec.task)
    actor = "proprioception + tactile" if task.make_cfg().tactile_obs else "proprioception"
    if "privileged" in task.critic_groups:
        return f"{spec.label} (asymmetric; actor: {actor}; critic: + privileged)"
    return f"{spec.label} (symmetric; actor: {actor})"


def _finite_or_null(value: Any) -> Any:
    """A copy of a JSON-able value with NaN and infinities replaced by ``None``."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(v) for v in value]
    return value


def write_outputs(
    result: EvalResult, out_dir: str | os.PathLike[str], log: Callable[[str], None] = print
) -> dict[str, Path]:
    """Write results.json, summary.csv, table.md and plot.png; returns their paths.

    table.md holds, in this order: the ablation table (ablation mode), the comparison table (two or
    more runs) and the evaluation table of every run.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"results": out / "results.json", "summary": out / "summary.csv", "table": out / "table.md"}
    # Strict JSON: a non-finite number (the max strain of an episode whose state blew up) is null.
    doc = json.dumps(_finite_or_null(result.to_json()), indent=1, sort_keys=True, allow_nan=False)
    atomic_write_text(paths["results"], doc + "\n")

    with paths["summary"].open("w", newline="") as f:
        fields = ["run", "column", "metric", "successes", "trials", "rate", "ci_low", "ci_high"]
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for label, eps in result.runs.items():
            for row in summary_rows(eps):
                writer.writerow(
                    {
                        "run": label,
                        **{
                            k: ("" if v is None else (f"{v:.6f}" if isinstance(v, float) else v))
                            for k, v in row.items()
                        },
                    }
                )

    summaries = {label: aggregate(eps) for label, eps in result.runs.items()}
    specs = {label: _spec_of(result, label) for label in result.runs}
    tables = []
    if result.settings.ablation:
        overrides = result.settings.env_overrides
        headers = {label: _ablation_header(spec, label, overrides) for label, spec in specs.items()}
        title = f"Ablation, every episode: {_conditions(result.settings)}"
        tables.append(ablation_markdown(summaries, headers, title))
    if len(summaries) > 1:
        tables.append(comparison_markdown(summaries, f"Comparison: {_conditions(result.settings)}"))
    for label_a, label_b in _paired_runs(result.runs):
        results = compare_pairs(pair_episodes(result.runs[label_a], result.runs[label_b]))
        title = f"**Paired by object and seed: {label_a} against {label_b}** (exact sign test)"
        tables.append(f"{title}\n\n{format_table(results, label_a, label_b)}\n")
    tables += [table_markdown(summaries[label], _title(specs[label], result.settings)) for label in summaries]
    tables.append(grasp_type_markdown(result.runs, "By grasp type"))
    tables.append(outcomes_markdown(result.runs, "How the episodes ended (first cause)"))
    loc_table = localisation_markdown(result.runs)
    if loc_table:
        tables.append(loc_table)
    paths["table"].write_text("\n".join(tables))

    paths["plot"] = out / "plot.png"
    _plot(result, paths["plot"])
    return paths


def _paired_runs(runs: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The runs compared pair by pair in table.md: the policy (or the teacher) against the baseline
    under the same perception, and under the paper's protocol the baseline under the camera against
    its reference."""
    pairs = [(f"{who}{s}", f"{BASELINE}{s}") for who in ("policy", TEACHER) for s in ("", "/camera")]
    pairs.append((f"{BASELINE}/camera", PAPER_REFERENCE))
    return [(a, b) for a, b in pairs if a in runs and b in runs]


def _plot(result: EvalResult, path: Path) -> None:
    """Bars of s_lift and s_disturb per column, one colour per controller, with Wilson error bars."""
    from d3grasp.viz.figure import pyplot, save_figure

    plt = pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
    labels = list(result.runs)
    width = 0.8 / len(labels)
    for ax, metric in zip(axes, ("s_lift", "s_disturb"), strict=True):
        for k, label in enumerate(labels):
            summary = aggregate(result.runs[label])
            vals, err_lo, err_hi = [], [], []
            for col in COLUMNS:
                rate = summary[col][metric]
                v = 0.0 if math.isnan(rate.value) else rate.value
                lo, hi = rate.interval
                # No bar (NaN) for a column without episodes: a 0 bar would read as "all failed".
                vals.append(100 * v if rate.trials else math.nan)
                # max(0, .): at 0/n or n/n the Wilson bound equals the rate up to round-off (-1e-17).
                err_lo.append(0.0 if math.isnan(lo) else max(0.0, 100 * (v - lo)))
                err_hi.append(0.0 if math.isnan(hi) else max(0.0, 100 * (hi - v)))
            xs = [i + (k - (len(labels) - 1) / 2) * width for i in range(len(COLUMNS))]
            ax.bar(xs, vals, width, yerr=[err_lo, err_hi], capsize=3, label=label)
        # Every controller ran the same objects, so the first run's episode counts label the columns.
        counts = aggregate(result.runs[labels[0]]) if labels else {}
        ticks = [f"{col}\n(n={counts[col][metric].trials})" if counts else col for col in COLUMNS]
        ax.set_xticks(range(len(COLUMNS)), ticks)
        ax.set_title(metric)
        ax.set_ylim(0, 100)
    axes[0].set_ylabel("success (%, 95% CI)")
    axes[-1].legend()
    save_figure(fig, path, dpi=120)
