"""The grasp planner's rule and poses, checked against the placement it documents: the object's
face nearest the wrist at the type's palm-frame x, its top the type's distance below the palm, the
palm's x along the object's shorter horizontal side, the palm facing down (top, pinch) or sideways
with the thumb up (side)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from d3grasp.envs.grasps import GRASPS, choose_grasp, grasp_pose
from d3grasp.vocabulary import GRASP_TYPES

ALL = tuple(GRASP_TYPES)


def test_rule_by_size_and_shape() -> None:
    assert choose_grasp(np.array([0.04, 0.03, 0.045]), ALL) == "side"  # small: the wrap cages it
    assert choose_grasp(np.array([0.06, 0.09, 0.10]), ALL) == "top"  # tall, a short side <= 7 cm
    assert choose_grasp(np.array([0.10, 0.12, 0.04]), ALL) == "pinch"  # low
    assert choose_grasp(np.array([0.09, 0.12, 0.10]), ALL) == "pinch"  # both sides too wide to hook
    assert choose_grasp(np.array([0.04, 0.03, 0.045]), ("top", "pinch")) == "top"  # falls back in order
    with pytest.raises(ValueError, match="three positive lengths"):
        choose_grasp(np.array([0.05, 0.0, 0.05]), ALL)


def _palm_frame(pose) -> np.ndarray:
    return Rotation.from_quat(pose.palm_quat).as_matrix()  # columns: palm x, y, z in the world


@pytest.mark.parametrize("grasp", ["top", "pinch"])
def test_palm_down_poses_place_the_object_as_documented(grasp: str) -> None:
    ex = np.array([0.06, 0.08, 0.10])  # x is the shorter horizontal side
    centre = np.array([0.01, -0.02, 0.05])
    pose = grasp_pose(grasp, centre, 0.0, ex)
    r = _palm_frame(pose)
    np.testing.assert_allclose(r[:, 2], [0, 0, -1], atol=1e-9)  # palm faces the table
    np.testing.assert_allclose(r[:, 0], [1, 0, 0], atol=1e-9)  # fingers along the short side
    local = r.T @ (centre - pose.palm_pos)  # object centre in the palm frame
    g = GRASPS[grasp]
    assert local[0] - 0.5 * ex[0] == pytest.approx(g.near_face_x)  # near face at the type's x
    assert local[1] == pytest.approx(g.lateral_y)
    assert local[2] - 0.5 * ex[2] == pytest.approx(g.top_z)  # top face that far from the palm plane
    np.testing.assert_allclose(pose.approach_dir, [0, 0, -1], atol=1e-9)  # approaching from above


def test_yaw_turns_the_pose_with_the_object_and_the_long_side_is_never_gripped() -> None:
    ex = np.array([0.09, 0.06, 0.10])  # here y is the shorter side: the palm turns 90 degrees
    pose = grasp_pose("top", np.zeros(3), 0.3, ex)
    r = _palm_frame(pose)
    yaw_of_palm_x = math.atan2(r[1, 0], r[0, 0])
    assert yaw_of_palm_x == pytest.approx(0.3 + 0.5 * math.pi - math.pi)  # the +x-facing of the two
    assert abs(yaw_of_palm_x) <= 0.5 * math.pi + 1e-9


def test_side_wrap_is_vertical_with_the_thumb_up_and_clears_the_table() -> None:
    ex = np.array([0.05, 0.07, 0.12])
    centre = np.array([0.0, 0.0, 0.06])  # standing on a table at height 0
    pose = grasp_pose("side", centre, 0.0, ex)
    r = _palm_frame(pose)
    np.testing.assert_allclose(r[:, 2], [0, 1, 0], atol=1e-9)  # palm normal horizontal (+y)
    np.testing.assert_allclose(r[:, 1], [0, 0, -1], atol=1e-9)  # palm -y, the thumb's side, points up
    assert pose.feasible
    low = grasp_pose("side", np.array([0.0, 0.0, 0.015]), 0.0, np.array([0.05, 0.07, 0.03]))
    assert not low.feasible  # a 3 cm object would put the hand's lower edge into the table
