"""The brittleness benchmark (``python -m d3grasp.bench shift``): the whole-scene shift moves object and
hand together by exactly the shift, and the report counts the outcomes that differ from the unshifted
ones, by object and by episode."""

from __future__ import annotations

import numpy as np
import pytest

from d3grasp.envs import make_env
from d3grasp.eval.shift import ShiftReport, outcomes

BOX = "box_01"  # a stored grasp in the shipped grasp file


def _starts(shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """(object start, planned palm position) of 2 worlds, evaluation mode, seed 3."""
    env = make_env(
        "D3Grasp-DexHand13-Mixed-v0",
        num_envs=2,
        seed=3,
        eval_mode=True,
        objects={"ids": (BOX, BOX)},
        scene_shift=shift,
    )
    try:
        return env.draw.object_start.double().numpy().copy(), env.grasp.palm_pos.double().numpy().copy()
    finally:
        env.close()


def test_scene_shift_moves_object_and_hand_together():
    obj0, palm0 = _starts((0.0, 0.0))
    obj1, palm1 = _starts((0.001, -0.002))
    expected = np.array([0.001, -0.002, 0.0])
    # float32 positions of a few decimetres: the shift survives to ~1e-7 m
    np.testing.assert_allclose(obj1 - obj0, np.tile(expected, (2, 1)), atol=2e-7)
    np.testing.assert_allclose(palm1 - palm0, np.tile(expected, (2, 1)), atol=2e-7)


def _records(rows: list[tuple[str, bool, bool]]) -> list[dict]:
    return [{"object": o, "s_lift": lift, "s_disturb": hold} for o, lift, hold in rows]


def test_report_counts_changed_outcomes_by_object_and_episode():
    ref = outcomes(_records([("a", True, True), ("b", True, False), ("c", False, False)]), seed=0)
    ref |= outcomes(_records([("a", True, True), ("b", True, True), ("c", False, False)]), seed=1)
    report = ShiftReport(0.001, ref)
    # +x: b's hold at seed 0 flips (False -> True); -x: nothing; +y: a is dropped at seed 1 and c lifts
    # at seed 0 (a lift alone is a change of outcome).
    report.shifted["+x"] = {**ref, ("b", 0): (True, True)}
    report.shifted["-x"] = dict(ref)
    report.shifted["+y"] = {**ref, ("a", 1): (True, False), ("c", 0): (True, False)}
    assert report.changed("+x") == {("b", 0)}
    assert report.changed("-x") == set()
    assert report.changed() == {("b", 0), ("a", 1), ("c", 0)}
    assert report.changed_objects() == {"a", "b", "c"}
    assert report.changed_objects("+y") == {"a", "c"}
    assert report.rates(report.shifted["+y"]) == pytest.approx((100.0 * 5 / 6, 100.0 * 2 / 6))
    text = report.summary()
    assert "3 of 3 objects (100.0%)" in text and "3 of 6 episodes (50.0%)" in text


def test_two_episodes_of_an_object_at_one_seed_are_refused():
    with pytest.raises(ValueError, match="two episodes"):
        outcomes(_records([("a", True, True), ("a", False, False)]), seed=0)
