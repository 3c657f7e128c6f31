"""Paired comparison of two controllers from ``d3grasp-eval --compare baseline`` results.

    python -m d3grasp.eval.paired eval_seed0/results.json eval_seed1/results.json
    python -m d3grasp.eval.paired new/results.json --against old/results.json --a baseline --b baseline

Both controllers met the same objects with the same seeds, so each episode of one has a twin of the
other (same object, seed and repeat). Success rates from a few dozen objects move by several points
with the seed alone; the paired view counts the objects only one controller succeeded on and tests
them with the exact sign (McNemar) test, which a difference of two independent rates cannot do.
``--against`` pairs the runs of two evaluations instead (the same objects and seeds under two grasp
libraries, say): run ``--a`` of the first files with run ``--b`` of the others.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from d3grasp.vocabulary import METRICS

__all__ = ["PairedResult", "compare_pairs", "load_pairs", "main", "pair_episodes", "sign_test_p"]

Z95 = 1.959963984540054


@dataclass(frozen=True)
class PairedResult:
    kind: str
    metric: str
    n: int  # episode pairs
    rate_a: float
    rate_b: float
    only_a: int  # pairs where only controller a succeeded
    only_b: int
    p_value: float  # exact two-sided sign test on the discordant pairs
    diff_ci: tuple[float, float]  # 95% interval of rate_a - rate_b (normal approximation, paired)


def sign_test_p(only_a: int, only_b: int) -> float:
    """Exact two-sided p-value of ``only_a`` against ``only_b`` discordant pairs under p = 1/2."""
    m = only_a + only_b
    if m == 0:
        return 1.0
    tail = sum(math.comb(m, i) for i in range(min(only_a, only_b) + 1)) / 2.0**m
    return min(1.0, 2.0 * tail)


def _read_runs(path: Path) -> dict[str, Any]:
    """The runs of a results file (ValueError for a file that is not one)."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))["runs"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a d3grasp-eval results.json ({exc})") from None


def _runs(path: Path, wanted: Sequence[str]) -> dict[str, Any]:
    """The runs of a results file, checked to hold ``wanted`` (ValueError otherwise)."""
    runs = _read_runs(path)
    missing = [r for r in wanted if r not in runs]
    if missing:
        raise ValueError(f"{path}: no run {missing} (has {sorted(runs)}); evaluate with --compare baseline")
    return runs


DEFAULT_RUNS: tuple[tuple[str, str], ...] = (("policy/camera", "baseline/camera"), ("policy", "baseline"))
"""The pairs of runs compared by default, the first a results file holds: the main command's (every
controller under the camera, ``--perception paper``), then a single-perception evaluation's."""


def default_runs(path: Path) -> tuple[str, str]:
    """The runs of ``DEFAULT_RUNS`` that the results file holds (its last pair when it holds none,
    which ``load_pairs`` then reports missing)."""
    try:
        runs = _read_runs(path)
    except ValueError:
        runs = {}
    return next((pair for pair in DEFAULT_RUNS if all(r in runs for r in pair)), DEFAULT_RUNS[-1])


def load_pairs(
    paths: Sequence[Path], run_a: str = "policy", run_b: str = "baseline", against: Sequence[Path] = ()
) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """``(episode of a, its twin of b)`` over the result files (ValueError on a file without the runs);
    with ``against``, run a of ``paths`` against run b of the ``against`` files."""
    if against:
        episodes_a = [ep for path in paths for ep in _runs(path, [run_a])[run_a]["episodes"]]
        episodes_b = [ep for path in against for ep in _runs(path, [run_b])[run_b]["episodes"]]
        return pair_episodes(episodes_a, episodes_b)
    pairs = []
    for path in paths:
        runs = _runs(path, [run_a, run_b])
        pairs += pair_episodes(runs[run_a]["episodes"], runs[run_b]["episodes"])
    return pairs


def pair_episodes(
    episodes_a: Sequence[dict[str, Any]], episodes_b: Sequence[dict[str, Any]]
) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """``(episode of a, its twin of b)``: the same object, seed and repeat."""

    def key(ep: dict[str, Any]) -> tuple[str, int, int]:
        return ep["object"], int(ep["seed"]), int(ep.get("repeat", 0))

    twins = {key(ep): ep for ep in episodes_b}
    return [(ep, twins[key(ep)]) for ep in episodes_a if key(ep) in twins]


def compare_pairs(pairs: Sequence[tuple[dict[str, Any], dict[str, Any]]]) -> list[PairedResult]:
    """One result per object kind present and metric."""
    results = []
    for kind in ("rigid", "deformable"):
        mine = [(a, b) for a, b in pairs if a["kind"] == kind]
        if not mine:
            continue
        n = len(mine)
        for metric in METRICS:
            d = [int(bool(a[metric])) - int(bool(b[metric])) for a, b in mine]
            only_a, only_b = d.count(1), d.count(-1)
            mean = sum(d) / n
            var = sum((x - mean) ** 2 for x in d) / (n - 1) if n > 1 else 0.0
            half = Z95 * math.sqrt(var / n)
            results.append(
                PairedResult(
                    kind=kind,
                    metric=metric,
                    n=n,
                    rate_a=sum(bool(a[metric]) for a, _ in mine) / n,
                    rate_b=sum(bool(b[metric]) for _, b in mine) / n,
                    only_a=only_a,
                    only_b=only_b,
                    p_value=sign_test_p(only_a, only_b),
                    diff_ci=(max(-1.0, mean - half), min(1.0, mean + half)),
                )
            )
    return results


def format_table(results: Sequence[PairedResult], run_a: str, run_b: str) -> str:
    rows = [
        f"| objects, metric | pairs | {run_a} % | {run_b} % | difference (95% CI) | only {run_a} | "
        f"only {run_b} | sign test p |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        kind = "Diverse" if r.kind == "rigid" else "Deformable"
        lo, hi = r.diff_ci
        rows.append(
            f"| {kind} {r.metric} | {r.n} | {100 * r.rate_a:.1f} | {100 * r.rate_b:.1f} | "
            f"{100 * (r.rate_a - r.rate_b):+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}] | {r.only_a} | "
            f"{r.only_b} | {r.p_value:.3g} |"
        )
    return "\n".join(rows)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m d3grasp.eval.paired",
        description="Paired comparison of two controllers over d3grasp-eval results (one file per seed).",
    )
    p.add_argument(
        "results", nargs="+", type=Path, help="results.json files of d3grasp-eval --compare baseline"
    )
    p.add_argument(
        "--a",
        default=None,
        help="first run (default: policy/camera and baseline/camera if the files have them, as the main "
        "command writes, else policy and baseline)",
    )
    p.add_argument("--b", default=None, help="second run (default: see --a)")
    p.add_argument(
        "--against",
        nargs="+",
        type=Path,
        default=(),
        help="results.json files of another evaluation: --a of RESULTS against --b of these",
    )
    args = p.parse_args(argv)
    try:
        if args.a is None or args.b is None:
            a, b = default_runs(args.results[0])
            args.a, args.b = args.a or a, args.b or b
        pairs = load_pairs(args.results, args.a, args.b, args.against)
    except ValueError as exc:
        print(f"d3grasp.eval.paired: error: {exc}", file=sys.stderr)
        return 2
    # Two evaluations compared: name the columns by file group as well as by run.
    a, b = (f"{args.a} (results)", f"{args.b} (against)") if args.against else (args.a, args.b)
    print(format_table(compare_pairs(pairs), a, b))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
