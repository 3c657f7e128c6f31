"""The pose estimators' registry: the configuration selects one by name, and a new estimator is a
class registered in ``ESTIMATORS``, nothing else (shown by registering one here)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from d3grasp.envs import make_env
from d3grasp.vision import estimators
from d3grasp.vision.estimators import ESTIMATORS, PlacedObject, PlanningPose, estimator_name


def test_the_configuration_selects_the_estimator() -> None:
    assert estimator_name("oracle", register_footprint=True) == "oracle"
    assert estimator_name("camera", register_footprint=True) == "footprint"
    assert estimator_name("camera", register_footprint=False) == "box_fit"
    assert estimator_name("oracle", True, pose_estimator="box_fit") == "box_fit"
    with pytest.raises(ValueError, match="unknown pose_estimator 'nope'.*oracle"):
        estimator_name("oracle", True, pose_estimator="nope")
    assert set(ESTIMATORS) == {"oracle", "box_fit", "footprint"}


class _ShiftedTruth:
    """The true pose moved 1 cm along +x: an estimator with a known error."""

    def __init__(self) -> None:
        self.seen: list[PlacedObject] = []

    def estimate(self, state: Any, placed: PlacedObject) -> PlanningPose:
        self.seen.append(placed)
        pos = np.asarray(placed.pos) + np.array([0.01, 0.0, 0.0])
        return PlanningPose(pos, placed.yaw, placed.extents, True, True, {"perception": "shifted"})


def test_a_new_estimator_is_a_registration(monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[_ShiftedTruth] = []
    monkeypatch.setitem(
        estimators.ESTIMATORS, "shifted", lambda scene: made.append(_ShiftedTruth()) or made[-1]
    )
    env = make_env(
        "D3Grasp-DexHand13-Mixed-v0", num_envs=2, objects={"ids": ("box_01",)}, pose_estimator="shifted"
    )
    try:
        (estimator,) = made
        assert env.planning.estimator is estimator
        placed = estimator.seen[-2:]
        assert [p.world for p in placed] == [0, 1]
        for p in placed:
            np.testing.assert_allclose(p.pos, env.draw.object_start[p.world].numpy(), atol=1e-6)
            rec = env.record.localisation[p.world]
            # The environment scores the estimate against the truth: the centre was told 1 cm off.
            assert rec["perception"] == "shifted"
            assert rec["loc_correction_centre"] == pytest.approx(0.01, abs=1e-6)
    finally:
        env.close()
