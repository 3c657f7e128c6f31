"""Aggregate per-episode outcomes into the paper's success table with 95% Wilson intervals.

An episode record is the dict the environment returns in ``extras["episodes"]`` (keys used here:
``kind``, ``size_bin``, ``s_grasp``, ``s_lift``, ``s_disturb``). Columns follow the paper's
evaluation table: rigid objects by size bin (Small, Medium, Large), all deformable objects
(Deformable), and every episode (Average); the paper's comparison table pools the rigid objects
(Diverse). Success rates from a few hundred episodes carry
several points of sampling error, so every rate comes with its Wilson score interval, which
stays inside [0, 1] and behaves at 0% and 100% where the normal approximation does not.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from d3grasp.vocabulary import METRICS  # noqa: F401  (re-exported: eval's own name for them)

COLUMNS: tuple[str, ...] = ("Small", "Medium", "Large", "Deformable", "Average")
# Every group aggregate() reports: the evaluation table's columns and all rigid objects pooled, the
# "Diverse" columns of the paper's comparison table.
GROUPS: tuple[str, ...] = (*COLUMNS, "Diverse")
_BIN_COLUMN = {"small": "Small", "medium": "Medium", "large": "Large"}


def wilson_interval(successes: int, trials: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (default 95%). (0, 0) ... for no trials: NaNs."""
    if trials < 0 or successes < 0 or successes > trials:
        raise ValueError(f"need 0 <= successes <= trials, got {successes}/{trials}")
    if trials == 0:
        return (math.nan, math.nan)
    p = successes / trials
    z2 = z * z
    denom = 1.0 + z2 / trials
    centre = (p + z2 / (2.0 * trials)) / denom
    half = z * math.sqrt(p * (1.0 - p) / trials + z2 / (4.0 * trials * trials)) / denom
    # The interval contains p, and is exactly [0, .] at p = 0 and [., 1] at p = 1; in floating point
    # centre -/+ half misses both by ~1e-17, which made error bars negative. Clamp to the exact form.
    return (min(max(0.0, centre - half), p), max(min(1.0, centre + half), p))


@dataclass(frozen=True)
class Rate:
    successes: int
    trials: int

    @property
    def value(self) -> float:
        return self.successes / self.trials if self.trials else math.nan

    @property
    def interval(self) -> tuple[float, float]:
        return wilson_interval(self.successes, self.trials)

    def percent(self) -> str:
        """``"84.2 [78.1, 89.0]"`` (percent with the 95% interval), ``"–"`` without episodes."""
        if not self.trials:
            return "–"
        lo, hi = self.interval
        return f"{100 * self.value:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"


def column_of(record: Mapping) -> str:
    if record["kind"] == "deformable":
        return "Deformable"
    try:
        return _BIN_COLUMN[record["size_bin"]]
    except KeyError:
        raise ValueError(f"episode record has unknown size bin {record['size_bin']!r}") from None


def aggregate(records: Iterable[Mapping]) -> dict[str, dict[str, Rate]]:
    """``{group: {metric: Rate}}`` over the records, for every group of ``GROUPS``; Average pools
    every episode, Diverse every rigid one."""
    counts = {c: {m: [0, 0] for m in METRICS} for c in GROUPS}
    for r in records:
        col = column_of(r)
        for group in (col, "Average") if col == "Deformable" else (col, "Diverse", "Average"):
            for m in METRICS:
                counts[group][m][0] += bool(r[m])
                counts[group][m][1] += 1
    return {c: {m: Rate(*counts[c][m]) for m in METRICS} for c in GROUPS}


def table_markdown(summary: Mapping[str, Mapping[str, Rate]], title: str = "") -> str:
    """The paper's evaluation table layout: rows s_grasp, s_lift, s_disturb; columns by bin."""
    lines = [f"**{title}**", ""] if title else []
    lines.append("| metric (%, 95% CI) | " + " | ".join(COLUMNS) + " |")
    lines.append("|---|" + "---|" * len(COLUMNS))
    for m in METRICS:
        lines.append(f"| {m} | " + " | ".join(summary[c][m].percent() for c in COLUMNS) + " |")
    lines.append("| episodes | " + " | ".join(str(summary[c]["s_lift"].trials) for c in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


def comparison_markdown(summaries: Mapping[str, Mapping[str, Mapping[str, Rate]]], title: str = "") -> str:
    """The paper's comparison table layout: one row per method (``{method: aggregate(...)}``), columns
    s_lift and s_disturb on the diverse (all rigid) and the deformable objects."""
    groups, metrics = ("Diverse", "Deformable"), ("s_lift", "s_disturb")
    lines = [f"**{title}**", ""] if title else []
    lines.append(
        "| method (%, 95% CI) | "
        + " | ".join(f"{g} {m}" for g in groups for m in metrics)
        + " | episodes (diverse / deformable) |"
    )
    lines.append("|---|" + "---|" * (len(groups) * len(metrics) + 1))
    for method, summary in summaries.items():
        cells = [summary[g][m].percent() for g in groups for m in metrics]
        counts = " / ".join(str(summary[g]["s_lift"].trials) for g in groups)
        lines.append(f"| {method} | " + " | ".join(cells) + f" | {counts} |")
    return "\n".join(lines) + "\n"


def ablation_markdown(
    summaries: Mapping[str, Mapping[str, Mapping[str, Rate]]],
    headers: Mapping[str, str] | None = None,
    title: str = "",
) -> str:
    """The paper's ablation table layout: rows s_grasp, s_lift, s_disturb over every episode (the
    Average group); one column per variant (``{variant: aggregate(...)}``), headed ``headers[variant]``
    where given."""
    names = list(summaries)
    heads = [(headers or {}).get(n, n) for n in names]
    lines = [f"**{title}**", ""] if title else []
    lines.append("| metric (%, 95% CI) | " + " | ".join(heads) + " |")
    lines.append("|---|" + "---|" * len(names))
    for m in METRICS:
        lines.append(f"| {m} | " + " | ".join(summaries[n]["Average"][m].percent() for n in names) + " |")
    episodes = (str(summaries[n]["Average"]["s_lift"].trials) for n in names)
    lines.append("| episodes | " + " | ".join(episodes) + " |")
    return "\n".join(lines) + "\n"


def outcomes_markdown(runs: Mapping[str, Iterable[Mapping]], title: str = "") -> str:
    """How the episodes ended, one column per run: each failure reason by count (the first cause of
    an episode, ``d3grasp.envs.mdp.terminations.FAILURES``), and the episodes that held."""
    from collections import Counter

    from d3grasp.envs.mdp.terminations import FAILURES, HELD, episode_ending

    counted = {label: Counter(episode_ending(r) for r in eps) for label, eps in runs.items()}
    seen = {k for c in counted.values() for k in c}
    order = [HELD, *FAILURES, *sorted(seen - {HELD, *FAILURES})]
    lines = [f"**{title}**", ""] if title else []
    lines.append("| ending | " + " | ".join(counted) + " |")
    lines.append("|---|" + "---|" * len(counted))
    for ending in order:
        if ending in seen:
            lines.append(
                f"| {ending} | " + " | ".join(str(c.get(ending, 0)) for c in counted.values()) + " |"
            )
    return "\n".join(lines) + "\n"


def grasp_type_markdown(runs: Mapping[str, Iterable[Mapping]], title: str = "") -> str:
    """s_lift and s_disturb by grasp type (the type each episode's grasp was), one row per run."""
    from d3grasp.vocabulary import GRASP_TYPES

    lines = [f"**{title}**", ""] if title else []
    lines.append(
        "| run (%, 95% CI) | " + " | ".join(f"{g} s_lift | {g} s_disturb" for g in GRASP_TYPES) + " |"
    )
    lines.append("|---|" + "---|" * (2 * len(GRASP_TYPES)))
    for label, eps in runs.items():
        eps = list(eps)
        cells = []
        for g in GRASP_TYPES:
            mine = [e for e in eps if e.get("grasp_type") == g]
            for m in ("s_lift", "s_disturb"):
                cells.append(Rate(sum(bool(e[m]) for e in mine), len(mine)).percent() + f" (n={len(mine)})")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def summary_rows(episodes: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (group, metric): successes, trials, rate and 95% Wilson interval (None if no trials).

    The groups are the evaluation table's columns and Diverse (every rigid object, the comparison table's).
    """
    summary = aggregate(episodes)
    rows = []
    for col in GROUPS:
        for m in METRICS:
            rate = summary[col][m]
            lo, hi = rate.interval
            rows.append(
                {
                    "column": col,
                    "metric": m,
                    "successes": rate.successes,
                    "trials": rate.trials,
                    "rate": None if math.isnan(rate.value) else rate.value,
                    "ci_low": None if math.isnan(lo) else lo,
                    "ci_high": None if math.isnan(hi) else hi,
                }
            )
    return rows
