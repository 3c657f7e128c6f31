"""The privileged teacher (issue 43): the correction from the grasp planned at the camera's estimate to
the same grasp at the true pose, and the teacher's wrist actions that apply it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from d3grasp.envs import make_env
from d3grasp.policies.teacher import PoseTeacher
from d3grasp.vocabulary import GRASP_TYPES

BOX = "box_01"  # 9.5 x 3.4 x 6.6 cm: a stored grasp in the shipped grasp file
LIMIT, YAW_LIMIT = 0.03, 0.5


def _env(perception: str | None, **kw):
    extra = {"perception": perception, "camera": {"noise": False}} if perception else {}
    return make_env(
        "D3Grasp-DexHand13-Mixed-v0",
        num_envs=2,
        seed=2,
        eval_mode=True,
        objects={"ids": (BOX, BOX)},
        palm_offset_limit=LIMIT,
        palm_yaw_limit=YAW_LIMIT,
        **extra,
        **kw,
    )


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(q).as_matrix()  # scipy's xyzw: the reference, not d3grasp's own


@pytest.fixture(scope="module")
def camera_env():
    env = _env("camera")
    yield env
    env.close()


def test_the_correction_is_zero_with_the_true_pose():
    env = _env(None)
    try:
        assert torch.count_nonzero(env.grasp.pose_correction) == 0
    finally:
        env.close()


def test_the_correction_moves_the_planned_grasp_onto_the_grasp_at_the_true_pose(camera_env):
    """Palm + correction, read in the true object's frame (or its half-turn twin: a box fit cannot
    tell the two ends apart), is the stored grasp's palm in the object frame; the planned orientation
    turned by the correction's yaw is the stored orientation at the true yaw."""
    env = camera_env
    plan = env.planning.plan[BOX]
    for w in range(env.num_envs):
        corr = env.grasp.pose_correction[w].double().numpy()
        assert env.record.localisation[w]["loc_correction"] == pytest.approx(
            np.linalg.norm(corr[:3]), rel=1e-5
        )
        obj_pos = env.draw.object_start[w].double().numpy()
        body_q = env.view.body_q[env.index.obj_body][w].double().numpy()
        r_obj = _quat_to_matrix(body_q[3:])
        true_yaw = math.atan2(r_obj[1, 0], r_obj[0, 0])
        planned_pos = env.grasp.palm_pos[w].double().numpy()
        planned_rot = _quat_to_matrix(env.grasp.palm_quat[w].double().numpy())
        g = plan.grasps[GRASP_TYPES[int(env.grasp.type_id[w])]]
        matches = []
        for twin in (0.0, math.pi):
            yaw = true_yaw + twin
            in_object = _rot_z(yaw).T @ (planned_pos + corr[:3] - obj_pos)
            turned = _rot_z(corr[3]) @ planned_rot
            pos_err = np.abs(in_object - g.palm_pos).max()
            rot_err = np.abs(turned - _rot_z(yaw) @ _quat_to_matrix(g.palm_quat)).max()
            matches.append(max(pos_err, rot_err))
        assert min(matches) < 2e-4, (w, corr)
        # The camera's error is a few mm and a few degrees: so is the correction (no half turn).
        assert np.linalg.norm(corr[:3]) < 0.03 and abs(corr[3]) < 0.5
        # The centre's correction: the true origin less the camera's pose estimate, the box fit
        # registered to the box's footprint: across, that registration's recorded error; up, the box
        # fit's height error (its 3-D error less its horizontal one).
        centre = env.grasp.centre_correction[w].double().numpy()
        rec = env.record.localisation[w]
        assert np.linalg.norm(centre[:2]) == pytest.approx(rec["loc_registered_xy"], rel=1e-4, abs=1e-6)
        up = math.sqrt(max(rec["loc_error"] ** 2 - rec["loc_error_xy"] ** 2, 0.0))
        assert abs(centre[2]) == pytest.approx(up, rel=1e-3, abs=1e-6)


def test_the_teacher_commands_the_correction_over_the_limits(camera_env):
    """Within the wrist's limits the full correction (offset and turn), scaled to actions; beyond them
    the centre's correction with no turn, clipped to the limit."""
    env = camera_env
    saved = env.grasp.pose_correction.clone(), env.grasp.centre_correction.clone()
    try:
        env.grasp.pose_correction[:] = torch.tensor([[0.006, -0.015, 0.0, 0.1], [0.0, 0.09, -0.003, -0.2]])
        env.grasp.centre_correction[:] = torch.tensor([[0.001, 0.002, 0.003], [0.006, -0.045, 0.0]])
        a = PoseTeacher(env).actions()
        assert a.shape == (2, env.num_actions)
        assert torch.count_nonzero(a[:, :-4]) == 0  # the rule's fingers
        want = torch.tensor([[0.2, -0.5, 0.0, 0.2], [0.2, -1.0, 0.0, 0.0]])
        torch.testing.assert_close(a[:, -4:], want, atol=1e-6, rtol=0)
    finally:
        env.grasp.pose_correction[:], env.grasp.centre_correction[:] = saved


def test_the_teacher_needs_a_wrist():
    env = make_env("D3Grasp-DexHand13-Mixed-v0", num_envs=1, objects={"ids": (BOX,)})
    try:
        with pytest.raises(ValueError, match="wrist"):
            PoseTeacher(env)
    finally:
        env.close()


def test_the_footprint_registered_to_is_the_boxs_own(camera_env):
    """The footprint drawn from the box's collision shape (for registering the camera's fit) spans
    the manifest's extents round the body origin."""
    env = camera_env
    ex = np.asarray(env.world_entries[0].extents[:2])
    fp = env.planning.estimator.footprints[0]
    np.testing.assert_allclose(np.ptp(fp.outline, axis=0), ex, atol=2.0 * fp.cell)
    np.testing.assert_allclose(fp.centroid, 0.0, atol=fp.cell)
    assert fp.outside.min() == 0.0 and fp.outside.max() >= 2.0 * fp.cell


def test_plan_yaw_offset_turns_the_planned_grasp_about_the_object():
    """``plan_yaw_offset`` = pi (the study of symmetric turns): at the true pose, the planned palm read
    in the object's frame turned by a half turn is the stored grasp's palm."""
    env = _env(None, plan_yaw_offset=math.pi)
    try:
        plan = env.planning.plan[BOX]
        for w in range(env.num_envs):
            obj_pos = env.draw.object_start[w].double().numpy()
            r_obj = _quat_to_matrix(env.view.body_q[env.index.obj_body][w].double().numpy()[3:])
            yaw = math.atan2(r_obj[1, 0], r_obj[0, 0]) + math.pi
            g = plan.grasps[GRASP_TYPES[int(env.grasp.type_id[w])]]
            in_object = _rot_z(yaw).T @ (env.grasp.palm_pos[w].double().numpy() - obj_pos)
            np.testing.assert_allclose(in_object, g.palm_pos, atol=2e-4)
            planned_rot = _quat_to_matrix(env.grasp.palm_quat[w].double().numpy())
            np.testing.assert_allclose(planned_rot, _rot_z(yaw) @ _quat_to_matrix(g.palm_quat), atol=2e-4)
    finally:
        env.close()
