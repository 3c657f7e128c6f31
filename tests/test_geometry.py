"""d3grasp.geometry against independent references: literal matrices of quarter turns, rotations
written here from the axis-angle formula and the Hamilton product, and round trips. Tolerances
only; no test depends on the last digits of a float."""

from __future__ import annotations

import math

import numpy as np
import pytest

from d3grasp.geometry import (
    axis_angle_matrix,
    homogeneous,
    matrix_to_quat_xyzw_nonneg_w,
    matrix_to_quat_xyzw_pivot_sign,
    quat_xyzw_to_matrix,
    rot_y,
    rot_z,
    rpy_matrix,
    wrap_angle,
)

MATRIX_TO_QUAT = [matrix_to_quat_xyzw_nonneg_w, matrix_to_quat_xyzw_pivot_sign]

# ---------------------------------------------------------------- independent references


def _quat_of(axis, angle: float) -> np.ndarray:
    """(x, y, z, w) of a turn by ``angle`` about ``axis``: (sin(a/2) n, cos(a/2))."""
    n = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return np.array([*(math.sin(0.5 * angle) * n), math.cos(0.5 * angle)])


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
    return np.array([*(aw * bv + bw * av + np.cross(av, bv)), aw * bw - av @ bv])


def _rotate(q: np.ndarray, v) -> np.ndarray:
    """``q v q*`` for a unit quaternion ``q``."""
    conj = np.array([-q[0], -q[1], -q[2], q[3]])
    return _hamilton(_hamilton(q, np.array([*v, 0.0])), conj)[:3]


def _matrix_of_quat(q: np.ndarray) -> np.ndarray:
    return np.stack([_rotate(q, e) for e in np.eye(3)], axis=1)


def _random_rotations(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    qs = rng.normal(size=(n, 4))
    return [_matrix_of_quat(q / np.linalg.norm(q)) for q in qs]


# Half turns and near-half turns (trace <= 0: the branches off the trace pivot), and the identity.
SPECIAL = [
    np.eye(3),
    *(
        _matrix_of_quat(_quat_of(axis, angle))
        for axis in np.eye(3)
        for angle in (math.pi, 0.9 * math.pi, 3.5)
    ),
    _matrix_of_quat(_quat_of((1.0, 1.0, 0.0), math.pi)),
    _matrix_of_quat(_quat_of((1.0, -2.0, 3.0), 3.0)),
]

Z90 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # x -> y, y -> -x
Y90 = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # z -> x, x -> -z
X90 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # y -> z, z -> -y


# ---------------------------------------------------------------- elementary rotations


def test_axis_rotations_by_known_angles() -> None:
    np.testing.assert_allclose(rot_z(0.5 * math.pi), Z90, atol=1e-12)
    np.testing.assert_allclose(rot_y(0.5 * math.pi), Y90, atol=1e-12)
    np.testing.assert_allclose(rot_z(math.pi), np.diag([-1.0, -1.0, 1.0]), atol=1e-12)
    for a in np.linspace(-4.0, 4.0, 17):
        np.testing.assert_allclose(rot_z(a), _matrix_of_quat(_quat_of((0, 0, 1), a)), atol=1e-12)
        np.testing.assert_allclose(rot_y(a), _matrix_of_quat(_quat_of((0, 1, 0), a)), atol=1e-12)


def test_rpy_matrix_is_urdf_z_y_x() -> None:
    np.testing.assert_allclose(rpy_matrix((0.5 * math.pi, 0.0, 0.0)), X90, atol=1e-12)
    np.testing.assert_allclose(rpy_matrix((0.0, 0.5 * math.pi, 0.0)), Y90, atol=1e-12)
    np.testing.assert_allclose(rpy_matrix((0.0, 0.0, 0.5 * math.pi)), Z90, atol=1e-12)
    rng = np.random.default_rng(1)
    for _ in range(20):
        r, p, y = rng.uniform(-3.0, 3.0, 3)
        # Rz(y) Ry(p) Rx(r) as one quaternion: q_z * q_y * q_x.
        q = _hamilton(_hamilton(_quat_of((0, 0, 1), y), _quat_of((0, 1, 0), p)), _quat_of((1, 0, 0), r))
        np.testing.assert_allclose(rpy_matrix((r, p, y)), _matrix_of_quat(q), atol=1e-12)


def test_axis_angle_matrix() -> None:
    np.testing.assert_allclose(axis_angle_matrix(np.array([0.0, 0.0, 0.5 * math.pi])), Z90, atol=1e-12)
    np.testing.assert_allclose(axis_angle_matrix(np.zeros(3)), np.eye(3), atol=0.0)
    np.testing.assert_allclose(axis_angle_matrix(np.array([1e-13, 0.0, 0.0])), np.eye(3), atol=1e-12)
    rng = np.random.default_rng(2)
    for _ in range(20):
        w = rng.normal(size=3)
        r = axis_angle_matrix(w)
        np.testing.assert_allclose(r, _matrix_of_quat(_quat_of(w, float(np.linalg.norm(w)))), atol=1e-12)
        np.testing.assert_allclose(r @ w, w, atol=1e-12)  # the axis stays put


def test_homogeneous() -> None:
    m = homogeneous((1.0, 2.0, 3.0), Z90)
    np.testing.assert_allclose(m @ np.array([1.0, 0.0, 0.0, 1.0]), [1.0, 3.0, 3.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(m[3], [0.0, 0.0, 0.0, 1.0])


def test_wrap_angle() -> None:
    for a, want in [
        (0.3, 0.3),
        (2.0 * math.pi + 0.3, 0.3),
        (1.5 * math.pi, -0.5 * math.pi),
        (-7.0, -7.0 + 2 * math.pi),
    ]:
        assert wrap_angle(a) == pytest.approx(want, abs=1e-12)
    assert wrap_angle(math.pi) == pytest.approx(math.pi, abs=1e-12)
    for a in np.linspace(-20.0, 20.0, 101):
        w = wrap_angle(float(a))
        assert -math.pi - 1e-12 <= w <= math.pi + 1e-12
        assert math.cos(w) == pytest.approx(math.cos(a), abs=1e-9)
        assert math.sin(w) == pytest.approx(math.sin(a), abs=1e-9)


# ---------------------------------------------------------------- quaternions


def test_quat_to_matrix_against_hamilton_product() -> None:
    np.testing.assert_allclose(quat_xyzw_to_matrix(_quat_of((0, 0, 1), 0.5 * math.pi)), Z90, atol=1e-12)
    np.testing.assert_allclose(
        quat_xyzw_to_matrix((1.0, 0.0, 0.0, 0.0)), np.diag([1.0, -1.0, -1.0]), atol=1e-12
    )
    rng = np.random.default_rng(3)
    for _ in range(20):
        q = rng.normal(size=4)
        r = quat_xyzw_to_matrix(q)
        np.testing.assert_allclose(r, _matrix_of_quat(q / np.linalg.norm(q)), atol=1e-12)
        np.testing.assert_allclose(quat_xyzw_to_matrix(-3.0 * q), r, atol=1e-12)  # normalised, sign-free
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("to_quat", MATRIX_TO_QUAT, ids=lambda f: f.__name__)
def test_matrix_to_quat_round_trip(to_quat) -> None:
    for r in [*SPECIAL, *_random_rotations(200)]:
        q = to_quat(r)
        assert q.shape == (4,)
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(quat_xyzw_to_matrix(q), r, atol=1e-12)
        np.testing.assert_allclose(_matrix_of_quat(q), r, atol=1e-12)


@pytest.mark.parametrize("to_quat", MATRIX_TO_QUAT, ids=lambda f: f.__name__)
def test_matrix_to_quat_known_cases(to_quat) -> None:
    h = math.sqrt(0.5)
    np.testing.assert_allclose(to_quat(np.eye(3)), [0.0, 0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(to_quat(Z90), [0.0, 0.0, h, h], atol=1e-12)
    np.testing.assert_allclose(to_quat(X90), [h, 0.0, 0.0, h], atol=1e-12)


def test_the_two_variants_are_the_same_rotation() -> None:
    for r in [*SPECIAL, *_random_rotations(200, seed=4)]:
        a, b = matrix_to_quat_xyzw_nonneg_w(r), matrix_to_quat_xyzw_pivot_sign(r)
        assert abs(float(a @ b)) == pytest.approx(1.0, abs=1e-12)  # q or -q


def test_nonneg_w_sign_convention() -> None:
    for r in [*SPECIAL, *_random_rotations(200, seed=5)]:
        assert matrix_to_quat_xyzw_nonneg_w(r)[3] >= 0.0


def test_pivot_sign_convention() -> None:
    """The pivot component is positive: w where the trace is positive, else the component of the
    largest diagonal entry."""
    for r in [*SPECIAL, *_random_rotations(200, seed=6)]:
        q = matrix_to_quat_xyzw_pivot_sign(r)
        pivot = 3 if np.trace(r) > 0.0 else int(np.argmax(np.diag(r)))
        assert q[pivot] > 0.0


def test_conventions_differ_past_a_half_turn() -> None:
    """200 deg about x (trace < 0, x the pivot): the true half-angle quaternion has w < 0. The
    pivot-sign variant keeps it (x > 0, w < 0); the w >= 0 variant returns its negative."""
    r = _matrix_of_quat(_quat_of((1, 0, 0), math.radians(200.0)))
    want = np.array([math.sin(math.radians(100.0)), 0.0, 0.0, math.cos(math.radians(100.0))])
    assert want[3] < 0.0
    np.testing.assert_allclose(matrix_to_quat_xyzw_pivot_sign(r), want, atol=1e-12)
    np.testing.assert_allclose(matrix_to_quat_xyzw_nonneg_w(r), -want, atol=1e-12)
    # Below a half turn (160 deg) the two agree.
    r = _matrix_of_quat(_quat_of((1, 0, 0), math.radians(160.0)))
    np.testing.assert_allclose(matrix_to_quat_xyzw_pivot_sign(r), matrix_to_quat_xyzw_nonneg_w(r), atol=1e-12)
