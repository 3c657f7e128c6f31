"""The localisation error's definition, against hand-worked boxes: a box is the same box turned by
half a turn or written a quarter turn on with its sides swapped, and nothing else; and the summary
the evaluation prints (means and 95th percentiles in millimetres) against NumPy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from d3grasp.vision.localisation import ObjectEstimate
from d3grasp.vision.perception import localisation_error, localisation_summary

TRUE_CENTRE = np.array([0.01, -0.02, 0.03])
TRUE_SIDES = np.array([0.10, 0.04, 0.06])  # a 10 x 4 cm box, 6 cm high


def _estimate(yaw: float, extents, centre=TRUE_CENTRE) -> ObjectEstimate:
    return ObjectEstimate(
        centre=np.asarray(centre, dtype=np.float64),
        yaw=yaw,
        extents=np.asarray(extents, dtype=np.float64),
        centre_std=np.zeros(3),
        extents_std=np.zeros(3),
        num_points=100,
    )


@pytest.mark.parametrize(
    ("yaw", "extents"),
    [
        (0.3, TRUE_SIDES),  # the truth itself
        (0.3 + math.pi, TRUE_SIDES),  # turned by half a turn: the same box
        (0.3 + 0.5 * math.pi, [0.04, 0.10, 0.06]),  # a quarter turn on, sides swapped: the same box
        (0.3 - 0.5 * math.pi, [0.04, 0.10, 0.06]),
    ],
)
def test_the_same_box_written_another_way_has_no_error(yaw: float, extents) -> None:
    err = localisation_error(_estimate(yaw, extents), TRUE_CENTRE, 0.3, TRUE_SIDES)
    assert err.yaw == pytest.approx(0.0, abs=1e-12) and err.extents == pytest.approx(0.0, abs=1e-12)
    assert err.centre == 0.0 and err.horizontal == 0.0


def test_a_box_turned_a_quarter_with_its_sides_unswapped_is_another_box() -> None:
    # Turned by 90 degrees, sides as the truth's: the long side lies across the true long side.
    err = localisation_error(_estimate(0.3 + 0.5 * math.pi, TRUE_SIDES), TRUE_CENTRE, 0.3, TRUE_SIDES)
    assert err.yaw == pytest.approx(0.0, abs=1e-12)  # written the other way, its yaw agrees...
    assert err.extents == pytest.approx(0.06)  # ...and its sides are 4 and 10 against 10 and 4 cm


def test_yaw_and_extent_errors_of_a_slightly_wrong_box() -> None:
    est = _estimate(0.3 + 0.1, [0.095, 0.043, 0.058], centre=TRUE_CENTRE + [0.003, -0.004, 0.012])
    err = localisation_error(est, TRUE_CENTRE, 0.3, TRUE_SIDES)
    assert err.yaw == pytest.approx(0.1)
    assert err.extents == pytest.approx(0.005)  # 9.5 against 10 cm
    assert err.horizontal == pytest.approx(0.005)  # 3-4-5
    assert err.centre == pytest.approx(0.013)  # 5-12-13
    # 50 degrees off a box is 40 degrees off its quarter-turn writing: read as 40 degrees.
    far = localisation_error(_estimate(0.3 + math.radians(50), TRUE_SIDES), TRUE_CENTRE, 0.3, TRUE_SIDES)
    assert far.yaw == pytest.approx(math.radians(40))
    assert far.extents == pytest.approx(0.06)  # in that writing its sides are swapped against the truth's


def test_summary_means_and_percentiles_in_millimetres() -> None:
    rng = np.random.default_rng(3)
    errors = rng.uniform(0.0, 0.02, size=(20, 3))
    episodes = [
        {"loc_error": float(a), "loc_error_xy": float(b), "loc_extent_error": float(c), "loc_ok": k != 4}
        for k, (a, b, c) in enumerate(errors)
    ]
    for ep in episodes[:5]:
        ep["loc_registered_xy"] = 0.002 * (1 + episodes.index(ep))
    episodes.append({"loc_error": None})  # an oracle episode: not counted
    s = localisation_summary(episodes)
    assert s is not None and s["episodes"] == 20 and s["failed"] == 1
    for key, column in (("loc_error", 0), ("loc_error_xy", 1), ("loc_extent_error", 2)):
        assert s[f"{key}_mean_mm"] == pytest.approx(1000.0 * errors[:, column].mean())
        assert s[f"{key}_p95_mm"] == pytest.approx(1000.0 * np.percentile(errors[:, column], 95))
    assert s["loc_registered_xy_mean_mm"] == pytest.approx(6.0)  # 2, 4, 6, 8, 10 mm
    assert localisation_summary([{"loc_error": None}, {}]) is None
