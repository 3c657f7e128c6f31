"""Grasp energy kernels against the float64 NumPy twin, finite differences and analytic cases."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.grasp_descent import descend
from d3grasp.kernels.grasp_energy import GraspEnergy
from d3grasp.kernels.grasp_energy_inputs import (
    POSE_PARAMS,
    TERM_NAMES,
    EnergyWeights,
    HandLayout,
    ObjectShape,
)
from d3grasp.kernels.grasp_energy_reference import reference_energy, reference_points

from d3grasp.dexhand13 import FINGER_JOINT_NAMES, PAD_NAMES
from d3grasp.planner.synthesis import (
    contact_weights,
    hand_kinematics_from_spec,
    hand_layout,
    initial_params,
    object_shape,
    synthesise,
)

wp.config.log_level = wp.LOG_WARNING

SPEC = Path(__file__).resolve().parents[2] / "tools" / "specs" / "dexhand13_kinematics.json"
IDENTITY_POSE = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]


@pytest.fixture(scope="module")
def layout() -> HandLayout:
    return hand_layout()


def random_grasps(layout: HandLayout, grasp: str, extents: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Starts of the planner, with the joints spread over (and a little past) their limits."""
    rng = np.random.default_rng(seed)
    x = initial_params(layout, grasp, extents, n, rng)
    span = layout.joint_upper - layout.joint_lower
    x[:, POSE_PARAMS:] = rng.uniform(
        layout.joint_lower - 0.05 * span, layout.joint_upper + 0.05 * span, (n, 16)
    )
    x[:, 3:POSE_PARAMS] *= rng.uniform(0.8, 1.2, (n, 1))  # the energy normalises the quaternion
    return x


def free_points_layout(points: list, normals: list) -> HandLayout:
    """A "hand" of contacts fixed to the palm (no joints): the energy of given points and normals."""
    contacts = [
        {"name": f"c{i}", "link": "palm", "xyz": p, "normal": n}
        for i, (p, n) in enumerate(zip(points, normals, strict=True))
    ]
    return HandLayout.from_dict({"root": "palm", "joints": [], "contacts": contacts, "colliders": []})


def warp_terms(layout: HandLayout, params: np.ndarray, obj: ObjectShape, weight, weights=None) -> dict:
    energy = GraspEnergy(layout, obj, len(params), weight, weights)
    energy.evaluate(params)
    return energy.terms()


# --------------------------------------------------------------------------------------------
# The layout: the hand's USD file, the spec, and forward kinematics by hand.
# --------------------------------------------------------------------------------------------


def _rpy(rpy) -> np.ndarray:
    r, p, y = rpy
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


def spec_pad_contacts(joint_q: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """Pad outer-face centres and normals in the palm frame, straight from the spec JSON (URDF FK)."""
    raw = json.loads(SPEC.read_text())
    assert raw["units"] == {"length": "m", "angle": "rad", "mass": "kg"}
    frames = {raw["root"]: np.eye(4)}
    pending = list(raw["joints"])
    while pending:
        j = next(j for j in pending if j["parent"] in frames)
        pending.remove(j)
        origin, turn = np.eye(4), np.eye(4)
        origin[:3, :3], origin[:3, 3] = _rpy(j["rpy"]), j["xyz"]
        turn[:3, :3] = _rpy((0.0, 0.0, joint_q.get(j["name"], 0.0)))
        frames[j["child"]] = frames[j["parent"]] @ origin @ turn
    points, normals = [], []
    for name in PAD_NAMES:
        pad = next(p for p in raw["tactile_pads"] if p["child"] == name)
        frame = np.eye(4)
        frame[:3, :3], frame[:3, 3] = _rpy(pad["rpy"]), pad["xyz"]
        frame = frames[pad["parent"]] @ frame
        lo, hi = np.array(raw["links"][name]["box_min"]), np.array(raw["links"][name]["box_max"])
        face = np.array([0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), hi[2]])  # the +z (outer) face
        points.append(frame[:3, :3] @ face + frame[:3, 3])
        normals.append(frame[:3, 2])
    return np.array(points), np.array(normals)


def test_layout_from_usd_matches_the_spec(layout: HandLayout) -> None:
    assert layout.joint_names == FINGER_JOINT_NAMES
    assert layout.contact_names[: len(PAD_NAMES)] == PAD_NAMES
    spec = HandLayout.from_dict(hand_kinematics_from_spec(SPEC))
    np.testing.assert_allclose(layout.joint_origin_pos, spec.joint_origin_pos, atol=1e-7)
    np.testing.assert_allclose(layout.joint_origin_rot, spec.joint_origin_rot, atol=1e-6)
    np.testing.assert_allclose(layout.joint_lower, spec.joint_lower, atol=1e-6)
    np.testing.assert_allclose(layout.joint_upper, spec.joint_upper, atol=1e-6)
    np.testing.assert_array_equal(layout.point_link, spec.point_link)
    np.testing.assert_allclose(layout.point_pos, spec.point_pos, atol=1e-7)
    np.testing.assert_allclose(layout.point_normal, spec.point_normal, atol=1e-6)
    raw = json.loads(SPEC.read_text())
    np.testing.assert_allclose(spec.joint_upper, [j["upper"] for j in raw["joints"]])  # rad, as "units" says
    assert layout.num_points - layout.num_contacts > 200  # penetration samples on every collider


def test_forward_kinematics_puts_the_pads_where_the_spec_says(layout: HandLayout) -> None:
    # By hand, the middle finger's proximal pad at rest: joint_0 (rpy pi, 0, pi) and joint_1
    # (rpy -pi/2, 0, pi) turn link_1's axes to palm (x, z, -y) at (0.13528, 0, 0.00175); the pad's rpy
    # (r, -pi/2, y) with r + y = -pi/2 turns pad (x, y, z) to link_1 (-z, x, y), i.e. palm (y, x, z),
    # at link_1 (0.007263, 0.0025, 0); the pad box's outer face centre is pad (0, 0.014195, 0.0032),
    # so the contact is palm (0.13528 + 0.007263 + 0.014195, 0, 0.00175 + 0.0025 + 0.0032), normal +z
    # (to ~1e-5: the spec writes pi as 3.1416 and pi/2 as 1.5708).
    k = layout.contact_index("right_middle_tactile_link_0")
    rest = np.array([IDENTITY_POSE + [0.0] * 16])
    for points, normals in (reference_points(layout, rest), _warp_points(layout, rest)):
        np.testing.assert_allclose(points[0, k], [0.156738, 0.0, 0.00745], atol=2e-6)
        np.testing.assert_allclose(normals[0, k], [0.0, 0.0, 1.0], atol=2e-5)

    rng = np.random.default_rng(3)
    for q in (np.zeros(16), rng.uniform(layout.joint_lower, layout.joint_upper)):
        want_p, want_n = spec_pad_contacts(dict(zip(FINGER_JOINT_NAMES, q, strict=True)))
        row = np.array([IDENTITY_POSE + list(q)])
        for points, normals in (reference_points(layout, row), _warp_points(layout, row)):
            np.testing.assert_allclose(points[0, : len(PAD_NAMES)], want_p, atol=2e-6)
            np.testing.assert_allclose(normals[0, : len(PAD_NAMES)], want_n, atol=2e-6)


def _warp_points(layout: HandLayout, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    terms = warp_terms(layout, params, ObjectShape.sphere(0.02), np.zeros(layout.num_contacts))
    return terms["points"], terms["normals"]


# --------------------------------------------------------------------------------------------
# Warp against the NumPy twin, and gradients against finite differences.
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", ["sphere", "box"])
def test_energy_matches_numpy_twin(layout: HandLayout, kind: str) -> None:
    obj, extents = object_shape(kind, 0.05 if kind == "sphere" else (0.04, 0.06, 0.08))
    rng = np.random.default_rng(0)
    for grasp in ("top", "side", "pinch"):
        x = random_grasps(layout, grasp, extents, 24, seed=1)
        weight = rng.uniform(0.0, 2.0, (24, layout.num_contacts)) * (
            rng.random((24, layout.num_contacts)) < 0.5
        )
        got = warp_terms(layout, x, obj, weight)
        want = reference_energy(layout, x, obj, weight)
        points, _ = reference_points(layout, x)
        np.testing.assert_allclose(got["points"], points, atol=2e-6)
        for name in (*TERM_NAMES, "energy"):
            scale = np.abs(want[name]).max()
            np.testing.assert_allclose(
                got[name], want[name], rtol=1e-4, atol=1e-6 * max(scale, 1.0), err_msg=name
            )
        assert np.any(got["sd"] < 0.0) and np.any(got["sd"] > 0.0)  # points inside and outside
        assert np.any(want["joint"] > 0.0)  # some joints were drawn past their limits


@pytest.mark.parametrize("kind", ["sphere", "box"])
def test_tape_gradients_match_finite_differences(layout: HandLayout, kind: str) -> None:
    obj, extents = object_shape(kind, 0.05 if kind == "sphere" else (0.04, 0.06, 0.08))
    x = random_grasps(layout, "pinch", extents, 6, seed=2)
    weight = contact_weights(layout, "top") + contact_weights(layout, "pinch")
    energy = GraspEnergy(layout, obj, len(x), weight)
    _, grad = energy.evaluate(x, grad=True)
    h = 1e-6
    fd = np.zeros_like(x)
    for i in range(x.shape[1]):
        step = np.zeros_like(x)
        step[:, i] = h
        up = reference_energy(layout, x + step, obj, weight)["energy"]
        down = reference_energy(layout, x - step, obj, weight)["energy"]
        fd[:, i] = (up - down) / (2 * h)
    for g in range(len(x)):
        scale = np.abs(fd[g]).max()
        np.testing.assert_allclose(grad[g], fd[g], rtol=2e-3, atol=2e-4 * scale, err_msg=f"grasp {g}")
    # every group of parameters gets a gradient (position, quaternion, each finger's joints)
    assert np.all(np.abs(fd[:, :3]).max(axis=0) > 0.0)
    assert np.all(np.abs(fd[:, 3:POSE_PARAMS]).max(axis=0) > 0.0)
    assert np.all(np.abs(fd[:, POSE_PARAMS:]).reshape(len(x), 4, 4).max(axis=(0, 2)) > 0.0)


# --------------------------------------------------------------------------------------------
# Analytic cases.
# --------------------------------------------------------------------------------------------


def _both(layout: HandLayout, obj: ObjectShape, weights: EnergyWeights | None = None) -> list[dict]:
    x = np.array([IDENTITY_POSE])
    w = np.ones(layout.num_contacts)
    return [warp_terms(layout, x, obj, w, weights), reference_energy(layout, x, obj, w, weights)]


def test_force_closure_of_antipodal_contacts_on_a_sphere() -> None:
    r = 0.03
    sphere = ObjectShape.sphere(r)
    antipodal = free_points_layout([[r, 0, 0], [-r, 0, 0]], [[-1, 0, 0], [1, 0, 0]])
    for t in _both(antipodal, sphere):
        assert t["fc"][0] == pytest.approx(0.0, abs=1e-10)
        assert t["cone"][0] == pytest.approx(0.0, abs=1e-10)
        assert t["dist"][0] == pytest.approx(0.0, abs=1e-7)
        assert t["pen"][0] == pytest.approx(0.0, abs=1e-7)
    # Same side, 60 degrees apart: the unit forces sum to sqrt(3) (through the centre: no torque).
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    same_side = free_points_layout([[r * c, r * s, 0], [r * c, -r * s, 0]], [[-c, -s, 0], [-c, s, 0]])
    for t in _both(same_side, sphere):
        assert t["fc"][0] == pytest.approx(3.0, rel=1e-5)
    # Friction cone (mu 0.5: half-angle 26.6 deg): a pad normal tilted 20 deg is inside, 40 deg is not.
    for tilt, inside in ((20.0, True), (40.0, False)):
        a = math.radians(tilt)
        tilted = free_points_layout([[r, 0, 0]], [[-math.cos(a), math.sin(a), 0]])
        want = 0.0 if inside else (1 / math.sqrt(1.25) - math.cos(a)) ** 2
        for t in _both(tilted, sphere):
            assert t["cone"][0] == pytest.approx(want, abs=1e-6)


def test_force_closure_of_opposite_box_faces() -> None:
    half = (0.03, 0.02, 0.05)
    box = ObjectShape.box(half)
    faces = free_points_layout([[0.03, 0, 0], [-0.03, 0, 0]], [[-1, 0, 0], [1, 0, 0]])
    for t in _both(faces, box):
        assert t["fc"][0] == pytest.approx(0.0, abs=1e-10)
        assert t["cone"][0] == pytest.approx(0.0, abs=1e-10)
        assert t["dist"][0] == pytest.approx(0.0, abs=1e-7)
    # Opposite faces but 1 cm off each other's line: no net force, a couple of 0.02 N·m per unit force.
    offset = free_points_layout([[0.03, 0.01, 0], [-0.03, -0.01, 0]], [[-1, 0, 0], [1, 0, 0]])
    for t in _both(offset, box):
        assert t["fc"][0] == pytest.approx((0.02 / box.torque_length) ** 2, rel=1e-5)
    # A contact 5 mm out and one 3 mm in: distance 8 mm, penetration 3 mm.
    gaps = free_points_layout([[0.035, 0, 0], [-0.027, 0, 0]], [[-1, 0, 0], [1, 0, 0]])
    for t in _both(gaps, box):
        assert t["dist"][0] == pytest.approx(0.008, abs=1e-6)
        assert t["pen"][0] == pytest.approx(0.003, abs=1e-6)


def test_mesh_box_matches_the_analytic_box(layout: HandLayout) -> None:
    half = np.array([0.02, 0.03, 0.04])
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * half
    # Two outward (counter-clockwise seen from outside) triangles per face; corner index = 4 sx + 2 sy + sz.
    faces = [
        [0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
        [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3],
    ]  # fmt: skip
    mesh = ObjectShape.from_mesh(corners, np.array(faces), floor_z=-0.041)
    box = ObjectShape.box(half, floor_z=-0.041)
    x = random_grasps(layout, "top", 2 * half, 16, seed=4)
    weight = contact_weights(layout, "top")
    e_mesh, g_mesh = GraspEnergy(layout, mesh, len(x), weight).evaluate(x, grad=True)
    e_box, g_box = GraspEnergy(layout, box, len(x), weight).evaluate(x, grad=True)
    np.testing.assert_allclose(e_mesh, e_box, rtol=1e-4)
    np.testing.assert_allclose(g_mesh, g_box, rtol=1e-3, atol=1e-3 * np.abs(g_box).max())


# --------------------------------------------------------------------------------------------
# Descent.
# --------------------------------------------------------------------------------------------


def test_descent_on_a_sphere_reaches_a_pinch(layout: HandLayout) -> None:
    obj, extents = object_shape("sphere", 0.04)
    x0 = initial_params(layout, "pinch", extents, 16, np.random.default_rng(5))
    weight = contact_weights(layout, "pinch")
    result = descend(layout, x0, obj, weight, steps=400)
    first, last = result.history[0], result.history[-1]
    assert np.all(last < first)
    assert np.median(last) < 0.1 * np.median(first)
    best = int(np.argmin(last))
    chosen = np.flatnonzero(weight > 0)
    assert np.all(np.abs(result.terms["sd"][best, chosen]) < 0.002)  # both tips on the surface
    assert result.terms["sd"][best].min() > -0.001  # nothing sunk more than 1 mm
    assert result.terms["fc"][best] < 0.3  # the tips nearly oppose each other
    np.testing.assert_allclose(np.linalg.norm(result.params[:, 3:POSE_PARAMS], axis=1), 1.0, atol=1e-12)
    assert np.all(result.params[:, POSE_PARAMS:] >= layout.joint_lower - 1e-12)
    assert np.all(result.params[:, POSE_PARAMS:] <= layout.joint_upper + 1e-12)


def test_synthesise_returns_the_best_grasps_first() -> None:
    grasps = synthesise("box", 0.06, "top", starts=8, steps=40, seed=1, keep=3)
    assert len(grasps) == 3
    assert [g.energy for g in grasps] == sorted(g.energy for g in grasps)
    og = grasps[0].to_object_grasp()
    assert og.grasp == "top" and og.palm_pos.shape == (3,)
    assert abs(np.linalg.norm(og.palm_quat) - 1.0) < 1e-9
    assert len(grasps[0].contact_gap) == 4
    with pytest.raises(ValueError, match="grasp type"):
        synthesise("box", 0.06, "hook", starts=2, steps=1)
