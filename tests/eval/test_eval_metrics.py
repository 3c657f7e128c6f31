"""Success aggregation against hand-made episode records and textbook Wilson intervals."""

from __future__ import annotations

import math

import pytest

from d3grasp.eval.metrics import (
    ablation_markdown,
    aggregate,
    comparison_markdown,
    table_markdown,
    wilson_interval,
)


def test_wilson_interval_reference_values():
    # Wilson score interval, 95% (z = 1.96): 8/10 -> [0.4902, 0.9433]; 0/10 -> [0, 0.2775].
    lo, hi = wilson_interval(8, 10)
    assert lo == pytest.approx(0.4902, abs=1e-4) and hi == pytest.approx(0.9433, abs=1e-4)
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson_interval(10, 10)
    assert hi == pytest.approx(1.0) and lo == pytest.approx(0.7225, abs=1e-4)
    # Large n approaches the normal interval p ± 1.96 sqrt(p(1-p)/n).
    lo, hi = wilson_interval(5000, 10000)
    assert hi - lo == pytest.approx(2 * 1.96 * math.sqrt(0.25 / 10000), rel=1e-3)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))
    with pytest.raises(ValueError):
        wilson_interval(3, 2)


def test_wilson_interval_contains_the_rate_and_reaches_the_bounds_exactly():
    # Analytically the interval always contains p = k/n, starts at 0 for k = 0 and ends at 1 for k = n.
    for n in range(1, 200):
        assert wilson_interval(0, n)[0] == 0.0 and wilson_interval(n, n)[1] == 1.0
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert lo <= k / n <= hi


def _rec(kind, size_bin, g, lift, dist):
    return {"kind": kind, "size_bin": size_bin, "s_grasp": g, "s_lift": lift, "s_disturb": dist}


def test_aggregate_by_bin_and_kind():
    records = [
        _rec("rigid", "small", True, True, False),
        _rec("rigid", "small", True, False, False),
        _rec("rigid", "medium", True, True, True),
        _rec("rigid", "large", False, False, False),
        _rec("deformable", "small", True, True, True),
        _rec("deformable", "large", True, True, False),
    ]
    s = aggregate(records)
    assert (s["Small"]["s_grasp"].successes, s["Small"]["s_grasp"].trials) == (2, 2)
    assert s["Small"]["s_lift"].value == 0.5
    assert s["Medium"]["s_disturb"].value == 1.0
    assert s["Large"]["s_lift"].value == 0.0
    # Soft objects of every size go to the Deformable column, not to a size bin.
    assert s["Deformable"]["s_lift"].trials == 2 and s["Deformable"]["s_disturb"].successes == 1
    assert s["Average"]["s_lift"].successes == 4 and s["Average"]["s_lift"].trials == 6
    # Diverse pools the four rigid episodes of every size bin (the comparison table's column).
    assert (s["Diverse"]["s_grasp"].successes, s["Diverse"]["s_grasp"].trials) == (3, 4)
    assert (s["Diverse"]["s_lift"].successes, s["Diverse"]["s_disturb"].successes) == (2, 1)
    md = table_markdown(s, "test")
    assert "| s_lift | 50.0 [" in md and "| episodes | 2 | 1 | 1 | 2 | 6 |" in md


def test_unknown_size_bin_is_an_error():
    with pytest.raises(ValueError, match="size bin"):
        aggregate([_rec("rigid", "huge", True, True, True)])


def _many(kind, size_bin, n, g, lift, dist):
    """``n`` episodes of which the first ``g`` grasp, ``lift`` lift and ``dist`` resist the pushes."""
    return [_rec(kind, size_bin, i < g, i < lift, i < dist) for i in range(n)]


# Textbook 95% Wilson intervals (percent, one decimal): 8/10, 0/10, 10/10, and 5/10 -> [23.7, 76.3].
W8, W0, W10, W5 = "80.0 [49.0, 94.3]", "0.0 [0.0, 27.8]", "100.0 [72.2, 100.0]", "50.0 [23.7, 76.3]"


def test_comparison_table_layout():
    # Method A: 10 rigid (8 lift, 5 resist) in two bins, 10 soft (10 lift, 0 resist); B: rigid only.
    a = _many("rigid", "small", 4, 4, 4, 2) + _many("rigid", "large", 6, 6, 4, 3)
    a += _many("deformable", "medium", 10, 10, 10, 0)
    b = _many("rigid", "medium", 10, 10, 0, 0)
    md = comparison_markdown({"A": aggregate(a), "B": aggregate(b)}, "cmp")
    lines = md.splitlines()
    assert lines[0] == "**cmp**"
    assert lines[2] == (
        "| method (%, 95% CI) | Diverse s_lift | Diverse s_disturb | Deformable s_lift "
        "| Deformable s_disturb | episodes (diverse / deformable) |"
    )
    assert lines[4] == f"| A | {W8} | {W5} | {W10} | {W0} | 10 / 10 |"
    assert lines[5] == f"| B | {W0} | {W0} | – | – | 10 / 0 |"


def test_ablation_table_layout():
    # Every episode counts (the Average group): Base 10 rigid + 10 soft, Tactile 10 rigid.
    base = _many("rigid", "small", 10, 10, 8, 5) + _many("deformable", "large", 10, 10, 8, 5)
    tactile = _many("rigid", "medium", 10, 8, 5, 0)
    md = ablation_markdown({"Base": aggregate(base), "Tac": aggregate(tactile)}, {"Tac": "Base+Tactile"})
    lines = md.splitlines()
    assert lines[0] == "| metric (%, 95% CI) | Base | Base+Tactile |"  # no title; header from the mapping
    # 16/20 and 10/20: Wilson [58.4, 91.9] and [29.9, 70.1] (from the score-interval formula by hand).
    assert lines[2] == f"| s_grasp | 100.0 [83.9, 100.0] | {W8} |"
    assert lines[3] == f"| s_lift | 80.0 [58.4, 91.9] | {W5} |"
    assert lines[4] == f"| s_disturb | 50.0 [29.9, 70.1] | {W0} |"
    assert lines[5] == "| episodes | 20 | 10 |"


def test_outcome_and_grasp_type_tables_count_by_hand() -> None:
    from d3grasp.eval.metrics import grasp_type_markdown, outcomes_markdown

    def ep(grasp: str, lift: bool, disturb: bool, failure: str | None) -> dict:
        return {"grasp_type": grasp, "s_lift": lift, "s_disturb": disturb, "failure": failure}

    base = [
        ep("top", True, True, None),
        ep("top", False, False, "no grasp"),
        ep("side", False, False, "no grasp"),
    ]
    policy = [ep("pinch", True, False, "lost under a push (-z)")]
    table = outcomes_markdown({"baseline": base, "policy": policy})
    rows = {line.split(" | ")[0].strip("| "): line for line in table.splitlines()[2:]}
    assert rows["held through the pushes"] == "| held through the pushes | 1 | 0 |"
    assert rows["no grasp"] == "| no grasp | 2 | 0 |"
    assert rows["lost under a push (-z)"] == "| lost under a push (-z) | 0 | 1 |"
    assert list(rows)[0] == "held through the pushes" and len(rows) == 3
    by_type = grasp_type_markdown({"baseline": base}).splitlines()[2]
    assert "| 50.0 [" in by_type and "(n=2)" in by_type and "(n=1)" in by_type and "(n=0)" in by_type


def test_the_ablation_table_tells_the_baselines_perceptions_apart() -> None:
    """Under the paper's protocol the ablation table holds the rule twice (camera and oracle): each
    column head names its perception."""
    from d3grasp.eval.evaluate import RunSpec
    from d3grasp.eval.report import _ablation_header

    rule = RunSpec("baseline", "D3Grasp-DexHand13-Mixed-v0", "baseline")
    assert _ablation_header(rule, "baseline/camera", {}) == "rule-based baseline, camera"
    assert _ablation_header(rule, "baseline/oracle", {}) == "rule-based baseline, oracle"
    assert _ablation_header(rule, "baseline", {}) == "rule-based baseline"
    base = RunSpec("Base/camera", "D3Grasp-DexHand13-Base-v0", "model_25.pt")
    assert _ablation_header(base, "Base/camera", {}) == "Base/camera (symmetric; actor: proprioception)"
    # The Base task's --checkpoint baseline runs its stall prior, which is not the paper's touch rule.
    stall = RunSpec("baseline", "D3Grasp-DexHand13-Base-v0", "baseline")
    assert _ablation_header(stall, "baseline/camera", {}) == "stall rule (no touch), camera"
    assert _ablation_header(rule, "baseline", {"rule": {"stop_on": "stall"}}) == "stall rule (no touch)"
    assert _ablation_header(stall, "baseline", {"rule__stop_on": "touch"}) == "rule-based baseline"
