"""Success aggregation against hand-made episode records and textbook Wilson intervals."""

from __future__ import annotations

import math

import pytest

from d3grasp.eval.metrics import aggregate, table_markdown, wilson_interval


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
    md = table_markdown(s, "test")
    assert "| s_lift | 50.0 [" in md and "| episodes | 2 | 1 | 1 | 2 | 6 |" in md


def test_unknown_size_bin_is_an_error():
    with pytest.raises(ValueError, match="size bin"):
        aggregate([_rec("rigid", "huge", True, True, True)])
