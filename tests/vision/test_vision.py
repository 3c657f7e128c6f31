"""Camera perception: intrinsics, plane fit, footprint rectangle and localisation of known objects.

References are independent of the code under test: analytic geometry (a rectangle's corners, a
plane's normal, a box's centre and size) and scenes whose depth is cast here in NumPy or ray-traced
by Newton's SensorCamera from bodies of known size and pose.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from d3grasp.envs.config import CameraConfig
from d3grasp.geometry import matrix_to_quat_xyzw_pivot_sign, wrap_angle
from d3grasp.vision.camera import (
    CameraIntrinsics,
    add_depth_noise,
    look_at_pose,
    perturb_pose,
)
from d3grasp.vision.footprint import footprint_of_pieces, register
from d3grasp.vision.localisation import fit_plane_ransac, localise_object, min_area_rectangle
from d3grasp.vision.perception import localisation_error

# Pixel footprint of the default camera at the table: 0.6 m * 2 tan(25 deg) / 240 px = 2.3 mm. Box
# edges are quantised to half a pixel each side, so without noise the centre is good to ~1.2 mm and
# an extent to ~2.3 mm; the bounds below leave a little room on top of that.
CENTRE_BOUND = 0.0015
EXTENT_BOUND = 0.003
YAW_BOUND = math.radians(2.0)
# With the default noise (1.4 mm depth std at 0.6 m, 2 mm / 0.3 deg calibration error, 2 % dropout)
# the calibration dominates: 2 mm + 0.6 m * 5 mrad = 3 mm per axis, ~4 mm 1-sigma in 3-D.
NOISY_CENTRE_MEAN_BOUND = 0.008


def _quat_to_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _cast_box_depth(
    intr: CameraIntrinsics, pose, centre: np.ndarray, half: np.ndarray, yaw: float
) -> np.ndarray:
    """Planar depth of a table (z = 0) and an upright box, ray-cast analytically (slab method)."""
    pos, r = pose
    v, u = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64)
    dirs_cam = np.stack([(u + 0.5 - intr.cx) / intr.fx, -(v + 0.5 - intr.cy) / intr.fy, -np.ones_like(u)], -1)
    dirs = dirs_cam @ r.T  # world directions whose camera-frame z is -1: t is the planar depth
    t_table = np.where(dirs[..., 2] < 0, -pos[2] / np.minimum(dirs[..., 2], -1e-12), np.inf)
    c, s = math.cos(yaw), math.sin(yaw)
    rb = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    o = (pos - centre) @ rb  # ray origin and directions in the box frame
    d = dirs @ rb
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-half - o) / d
        t2 = (half - o) / d
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (t_near <= t_far) & (t_near > 0)
    depth = np.where(hit, np.minimum(t_near, t_table), t_table)
    return np.where(np.isfinite(depth), depth, 0.0)


def test_intrinsics_backproject_then_project_returns_the_pixel():
    intr = CameraIntrinsics.from_fov(64, 48, math.radians(50.0))
    # Vertical field of view: the top pixel row's upper edge lies fov/2 above the axis.
    assert intr.fy == pytest.approx(24.0 / math.tan(math.radians(25.0)))
    depth = np.full((48, 64), 0.7)
    pts = intr.backproject(depth)
    uv = intr.project(pts)
    v, u = np.mgrid[0:48, 0:64]
    np.testing.assert_allclose(uv[..., 0], u, atol=1e-9)
    np.testing.assert_allclose(uv[..., 1], v, atol=1e-9)
    assert pts[0, 0, 1] > 0 and pts[0, 0, 0] < 0  # top-left pixel: up and to the left
    np.testing.assert_allclose(pts[..., 2], -0.7)


def test_look_at_pose_and_quaternion():
    pos, r = look_at_pose(np.array([0.0, -1.0, 1.0]), np.zeros(3))
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(-r[:, 2], np.array([0.0, 1.0, -1.0]) / math.sqrt(2.0), atol=1e-12)
    assert r[2, 1] > 0  # image up has a positive world z component
    # The quaternion of a 90 deg turn about z.
    q = matrix_to_quat_xyzw_pivot_sign(np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(np.abs(q), [0.0, 0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-12)
    rng = np.random.default_rng(3)
    for _ in range(20):
        _, rr = perturb_pose((pos, r), rng, 0.0, 1.0)
        np.testing.assert_allclose(_quat_to_matrix(matrix_to_quat_xyzw_pivot_sign(rr)), rr, atol=1e-9)


def test_min_area_rectangle_of_a_rotated_rectangle():
    a = math.radians(27.0)
    c, s = math.cos(a), math.sin(a)
    rng = np.random.default_rng(0)
    local = rng.uniform([-0.04, -0.015], [0.04, 0.015], size=(500, 2))
    corners = np.array([[-0.04, -0.015], [0.04, -0.015], [0.04, 0.015], [-0.04, 0.015]])
    pts = np.concatenate([local, corners]) @ np.array([[c, s], [-s, c]]) + [0.1, -0.2]
    centre, angle, size = min_area_rectangle(pts)
    np.testing.assert_allclose(centre, [0.1, -0.2], atol=1e-9)
    # Hull edges run along both axes, equal modulo 90 deg: side 0 is the one at 27 deg, 8 cm long.
    assert angle == pytest.approx(a, abs=1e-9)
    np.testing.assert_allclose(size, [0.08, 0.03], atol=1e-9)


def test_ransac_plane_with_outliers():
    rng = np.random.default_rng(1)
    n = np.array([0.02, -0.01, 1.0])
    n /= np.linalg.norm(n)
    e1 = np.cross(n, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    uv = rng.uniform(-0.3, 0.3, (3000, 2))
    plane = 0.05 * n + uv[:, :1] * e1 + uv[:, 1:] * e2 + rng.normal(0, 0.0005, (3000, 1)) * n
    clutter = rng.uniform([-0.05, -0.05, 0.06], [0.05, 0.05, 0.15], (600, 3))
    normal, d, inliers = fit_plane_ransac(np.concatenate([plane, clutter]), rng, threshold=0.002)
    assert math.degrees(math.acos(min(1.0, float(normal @ n)))) < 0.2
    assert d == pytest.approx(0.05, abs=3e-4)
    assert inliers[:3000].mean() > 0.99 and inliers[3000:].sum() == 0


@pytest.mark.parametrize("yaw", [0.0, 0.4, -1.1])
def test_localise_analytic_box_without_noise(yaw):
    cfg = CameraConfig()
    intr = CameraIntrinsics.from_fov(cfg.width, cfg.height, math.radians(cfg.fov_deg))
    pose = look_at_pose(np.asarray(cfg.position), np.asarray(cfg.target))
    half = np.array([0.03, 0.018, 0.025])
    centre = np.array([0.012, -0.008, half[2]])
    depth = _cast_box_depth(intr, pose, centre, half, yaw)
    est = localise_object(depth, intr, pose, np.random.default_rng(0))
    err = localisation_error(est, centre, yaw, 2.0 * half)
    assert est.ok
    assert err.centre < CENTRE_BOUND
    assert err.extents < EXTENT_BOUND
    assert err.yaw < YAW_BOUND
    assert est.extents[2] == pytest.approx(2.0 * half[2], abs=0.001)  # the top face is seen flat


def test_localise_analytic_box_degrades_gracefully_with_noise():
    cfg = CameraConfig()
    intr = CameraIntrinsics.from_fov(cfg.width, cfg.height, math.radians(cfg.fov_deg))
    pose = look_at_pose(np.asarray(cfg.position), np.asarray(cfg.target))
    half = np.array([0.035, 0.02, 0.03])
    centre = np.array([0.0, 0.01, half[2]])
    clean = _cast_box_depth(intr, pose, centre, half, 0.3)
    rng = np.random.default_rng(7)
    errors, sigmas = [], []
    for _ in range(12):
        depth = add_depth_noise(clean, rng, cfg.depth_noise_base, cfg.depth_noise_quadratic, cfg.dropout)
        believed = perturb_pose(pose, rng, cfg.calib_pos_std, cfg.calib_rot_std)
        est = localise_object(
            depth,
            intr,
            believed,
            rng,
            depth_std=0.0014,
            calib_pos_std=cfg.calib_pos_std,
            calib_rot_std=cfg.calib_rot_std,
        )
        assert est.ok
        errors.append(localisation_error(est, centre, 0.3, 2.0 * half).centre)
        sigmas.append(float(np.linalg.norm(est.centre_std)))
    errors = np.asarray(errors)
    assert errors.mean() < NOISY_CENTRE_MEAN_BOUND
    # The reported uncertainty is of the size of the actual errors (within a factor of 3 on average).
    assert np.mean(sigmas) / 3.0 < errors.mean() < 3.0 * np.mean(sigmas)
    # Dropout and depth noise alone (perfect calibration) stay close to the clean bound.
    depth = add_depth_noise(clean, rng, cfg.depth_noise_base, cfg.depth_noise_quadratic, cfg.dropout)
    est = localise_object(depth, intr, pose, rng)
    assert localisation_error(est, centre, 0.3, 2.0 * half).centre < 2.5 * CENTRE_BOUND


def test_localise_reports_failure_on_an_empty_table():
    cfg = CameraConfig()
    intr = CameraIntrinsics.from_fov(cfg.width, cfg.height, math.radians(cfg.fov_deg))
    pose = look_at_pose(np.asarray(cfg.position), np.asarray(cfg.target))
    depth = _cast_box_depth(intr, pose, np.array([5.0, 5.0, 0.01]), np.array([0.01, 0.01, 0.01]), 0.0)
    est = localise_object(depth, intr, pose, np.random.default_rng(0), fallback_extents=np.full(3, 0.05))
    assert not est.ok
    np.testing.assert_allclose(est.extents, 0.05)


def test_newton_rendered_box_is_localised():
    """Newton's ray-traced depth of a box of known size and pose (table = ground plane)."""
    import newton
    import warp as wp

    from d3grasp.vision.camera import RGBDCamera

    half = np.array([0.032, 0.021, 0.027])
    centre = np.array([0.01, 0.015, half[2]])
    yaw = 0.6
    builder = newton.ModelBuilder()
    builder.add_ground_plane()
    builder.begin_world()
    q = wp.quat_from_axis_angle(wp.vec3(0.0, 0.0, 1.0), yaw)
    body = builder.add_body(xform=wp.transform(wp.vec3(*centre), q))
    builder.add_shape_box(body, hx=float(half[0]), hy=float(half[1]), hz=float(half[2]))
    builder.end_world()
    model = builder.finalize(device="cpu")
    state = model.state()
    cfg = CameraConfig()
    intr = CameraIntrinsics.from_fov(cfg.width, cfg.height, math.radians(cfg.fov_deg))
    pose = look_at_pose(np.asarray(cfg.position), np.asarray(cfg.target))
    cam = RGBDCamera(model, intr)
    depth = cam.render(state, [pose], [0])["depth"][0]
    # The renderer agrees with the analytic ray cast (same pixel convention) to a fraction of a mm.
    ref = _cast_box_depth(intr, pose, centre, half, yaw)
    agree = np.abs(depth - ref) < 1e-4
    assert agree.mean() > 0.995  # silhouette pixels may round either way
    est = localise_object(depth, intr, pose, np.random.default_rng(0))
    err = localisation_error(est, centre, yaw, 2.0 * half)
    assert err.centre < CENTRE_BOUND and err.extents < EXTENT_BOUND and err.yaw < YAW_BOUND


@pytest.mark.slow
def test_env_camera_perception_records_localisation_error():
    """GraspEnv with camera perception: the planner's estimate of shipped objects and the records."""
    import torch

    import d3grasp

    env = d3grasp.make_env(
        num_envs=2,
        eval_mode=True,
        perception="camera",
        camera={"noise": False},
        objects={"ids": ("box_00", "sponge_cube_s")},
        phases={"approach": 0.05, "grasp": 0.05, "lift": 0.05, "hold": 0.05, "disturb_per_direction": 0.02},
    )
    for w, rec in enumerate(env.record.localisation):
        assert rec["perception"] == "camera" and rec["loc_ok"]
        assert rec["loc_error"] < 2.0 * CENTRE_BOUND, env.world_entries[w].id
    episodes = []
    for _ in range(env.max_episode_length):
        _, _, _, extras = env.step(torch.zeros(2, env.num_actions))
        episodes += extras.get("episodes", [])
        if len(episodes) >= 2:
            break
    assert {ep["object"] for ep in episodes} == {"box_00", "sponge_cube_s"}
    assert all(0.0 <= ep["loc_error"] < 2.0 * CENTRE_BOUND for ep in episodes)


# --- Registration to the object's own footprint (vision/footprint.py) ---------------------------
# Objects made of upright boxes (centre (x, y) in the body frame, half sizes): an L-shape, whose two
# ends a box fit cannot tell apart, and a plus, whose box fit lies at 45 degrees to its arms. The
# body origin is the centre of the axis-aligned bounding box, as the asset authoring makes it.
L_SHAPE = [((0.0, -0.02), (0.05, 0.01, 0.02)), ((-0.04, 0.01), (0.01, 0.02, 0.02))]
PLUS = [((0.0, 0.0), (0.045, 0.01, 0.02)), ((0.0, 0.0), (0.01, 0.045, 0.02))]
# A step: an 8 x 3 cm rectangle from above, whose half turn is the same footprint, 4 cm tall at one
# end and 2 cm at the other; only the heights tell its ends apart.
STEP = [((-0.02, 0.0), (0.02, 0.015, 0.02)), ((0.02, 0.0), (0.02, 0.015, 0.01))]


def _box_corners(centre_xy, half) -> np.ndarray:
    """An upright box standing on z = 0, as the cast puts it."""
    c = np.array([centre_xy[0], centre_xy[1], half[2]])
    return np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) * np.asarray(half) + c


def _cast_boxes(intr, pose, boxes, origin_xy, yaw) -> np.ndarray:
    """Depth of a table and a union of upright boxes at body pose (origin, yaw): the nearest hit."""
    r = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    depths = []
    for c, half in boxes:
        xy = np.asarray(origin_xy) + r @ np.asarray(c)
        depths.append(_cast_box_depth(intr, pose, np.array([xy[0], xy[1], half[2]]), np.asarray(half), yaw))
    return np.min(np.stack(depths), axis=0)


def _camera():
    cfg = CameraConfig()
    intr = CameraIntrinsics.from_fov(cfg.width, cfg.height, math.radians(cfg.fov_deg))
    return intr, look_at_pose(np.asarray(cfg.position), np.asarray(cfg.target))


def _seen_and_model(boxes, origin, yaw):
    """The camera's estimate of the union of ``boxes`` at body pose (origin, yaw), noise-free, and
    the footprint of the same boxes in their body frame."""
    intr, pose = _camera()
    depth = _cast_boxes(intr, pose, boxes, origin, yaw)
    est = localise_object(depth, intr, pose, np.random.default_rng(0))
    return est, footprint_of_pieces([_box_corners(c, h) for c, h in boxes])


def test_footprint_of_an_l_shape_matches_its_geometry():
    ref = footprint_of_pieces([_box_corners(c, h) for c, h in L_SHAPE])
    # Area-weighted centroid of the two rectangles: 10 x 2 cm at (0, -2) cm and 2 x 4 cm at (-4, 1) cm.
    a1, a2 = 0.1 * 0.02, 0.02 * 0.04
    expected = (a1 * np.array([0.0, -0.02]) + a2 * np.array([-0.04, 0.01])) / (a1 + a2)
    np.testing.assert_allclose(ref.centroid, expected, atol=2e-4)

    def outside(p):
        ij = np.floor((np.asarray(p) - ref.origin) / ref.cell).astype(int)
        return ref.outside[ij[0], ij[1]]

    assert outside((0.0, -0.02)) == 0.0  # inside the bar
    assert outside((0.0, 0.0)) == pytest.approx(0.01, abs=1.5 * ref.cell)  # 1 cm off the bar
    assert outside((-0.0295, 0.02)) == pytest.approx(0.0005, abs=1.5 * ref.cell)  # just right of the arm
    # Every outline cell lies on the L's edge (within a cell of it), none deep inside or far out.
    lo = np.array([[-0.05, -0.03], [-0.05, -0.01]])
    hi = np.array([[0.05, -0.01], [-0.03, 0.03]])
    for p in ref.outline:
        d_in = [max(np.max(lo[k] - p), np.max(p - hi[k])) for k in range(2)]  # < 0 inside box k
        assert -1.5 * ref.cell <= min(d_in) <= 1.5 * ref.cell


@pytest.mark.parametrize("yaw", [0.3, 2.5, -2.0])
def test_register_finds_an_l_shapes_end_from_a_cast_depth_image(yaw):
    origin = np.array([0.015, -0.01])
    est, ref = _seen_and_model(L_SHAPE, origin, yaw)
    xy, got, extents = register(est.footprint, ref)
    assert abs(math.atan2(math.sin(got - yaw), math.cos(got - yaw))) < YAW_BOUND  # the full turn, not mod 180
    assert np.linalg.norm(xy - origin) < 2.0 * CENTRE_BOUND
    np.testing.assert_allclose(extents, [0.1, 0.06], atol=EXTENT_BOUND)


def test_register_turns_a_plus_back_onto_its_arms():
    yaw, origin = 0.2, np.array([-0.01, 0.012])
    est, ref = _seen_and_model(PLUS, origin, yaw)
    # The box fit round a plus lies at 45 degrees to its arms: the raw estimate is as wrong as it can be.
    assert localisation_error(est, np.r_[origin, 0.02], yaw, np.array([0.09, 0.09, 0.04])).yaw > 0.6
    xy, got, _ = register(est.footprint, ref)
    quarter = (got - yaw) % (0.5 * math.pi)
    assert min(quarter, 0.5 * math.pi - quarter) < YAW_BOUND  # its quarter turns are the same shape
    assert abs(got) <= 0.25 * math.pi + 1e-9  # of those, the smallest yaw
    assert np.linalg.norm(xy - origin) < 2.0 * CENTRE_BOUND


def test_register_keeps_the_smaller_yaw_of_a_box_and_its_half_turn():
    origin = np.array([0.005, 0.02])
    est, ref = _seen_and_model([((0.0, 0.0), (0.04, 0.015, 0.02))], origin, 0.3 + math.pi)
    xy, got, _ = register(est.footprint, ref, heights=est.footprint_heights)  # level: no help
    assert got == pytest.approx(0.3, abs=YAW_BOUND)
    assert np.linalg.norm(xy - origin) < 2.0 * CENTRE_BOUND


def test_footprint_top_is_each_cells_height_above_the_lowest_point():
    ref = footprint_of_pieces([_box_corners(c, h) for c, h in STEP])

    def top(p):
        ij = np.floor((np.asarray(p) - ref.origin) / ref.cell).astype(int)
        return ref.top[ij[0], ij[1]]

    assert top((-0.03, 0.005)) == pytest.approx(0.04, abs=1e-9)  # the tall end
    assert top((0.03, -0.005)) == pytest.approx(0.02, abs=1e-9)  # the low end
    assert np.isnan(top((0.0, 0.0165)))  # off the footprint (its grid keeps a 2 mm margin)
    # A slanted piece: a wedge rising from 0 at x = 0 to 3 cm at x = 6 cm over a 4 cm wide base.
    wedge = np.array(
        [
            [0, -0.02, 0],
            [0, 0.02, 0],
            [0.06, -0.02, 0],
            [0.06, 0.02, 0],
            [0.06, -0.02, 0.03],
            [0.06, 0.02, 0.03],
        ]
    )
    slope = footprint_of_pieces([wedge])
    ij = np.floor((np.array([0.02, 0.0]) - slope.origin) / slope.cell).astype(int)
    centre_x = slope.origin[0] + (ij[0] + 0.5) * slope.cell  # the cell's centre, where it is sampled
    assert slope.top[ij[0], ij[1]] == pytest.approx(0.5 * centre_x, abs=1e-9)


@pytest.mark.parametrize("yaw", [0.3, 0.3 - math.pi, 1.2 + math.pi])
def test_register_tells_a_steps_ends_apart_by_their_heights(yaw):
    origin = np.array([0.01, -0.005])
    est, ref = _seen_and_model(STEP, origin, yaw)
    # From above alone the half turn is the same shape: the smaller yaw of the two is kept.
    _, flat, _ = register(est.footprint, ref)
    smaller = min(yaw, wrap_angle(yaw + math.pi), key=abs)
    assert abs(wrap_angle(flat - smaller)) < YAW_BOUND
    # With the seen heights, the tall end goes where the camera saw it.
    xy, got, _ = register(est.footprint, ref, heights=est.footprint_heights)
    assert abs(wrap_angle(got - yaw)) < YAW_BOUND
    assert np.linalg.norm(xy - origin) < 2.0 * CENTRE_BOUND
