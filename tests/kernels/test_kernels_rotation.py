"""Deformable-object rotation and velocity against float64 NumPy/SciPy references."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.rotation import (
    MODE_NAMES,
    ObjectPoseBuffers,
    compute_object_pose,
    object_rotation,
    reset_object_history,
    update_object_velocity,
)
from d3grasp.kernels.strain import StrainBuffers, StrainLayout, compute_sigma
from d3grasp.kernels.strain_numpy import grid_tet_mesh
from scipy.spatial.transform import Rotation

wp.config.log_level = wp.LOG_WARNING


def quat_close(q: np.ndarray, ref: np.ndarray, tol: float) -> bool:
    """Same rotation (q and -q are equal)."""
    return 1.0 - abs(float(np.dot(q, ref))) < tol


def polar_rotation(A: np.ndarray) -> np.ndarray:
    """argmax_{R in SO(3)} tr(R^T A) via float64 SVD (Kabsch with determinant correction)."""
    U, _, Vt = np.linalg.svd(A)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def ref_rotations(points: np.ndarray, rest: np.ndarray) -> dict[str, np.ndarray]:
    x = points - points.mean(0)
    y = rest - rest.mean(0)
    A = x.T @ y
    C_ref = y.T @ y
    C_cur = x.T @ x
    ev_r, E = np.linalg.eigh(C_ref)
    ev_c, G = np.linalg.eigh(C_cur)
    E, G = E[:, ::-1], G[:, ::-1]
    s = np.array([G[:, k] @ A @ E[:, k] for k in range(3)])
    G = G * np.where(s < 0, -1.0, 1.0)
    R = G @ E.T
    if np.linalg.det(R) < 0:
        k = int(np.argmin(np.abs(s)))
        G[:, k] *= -1
        R = G @ E.T
    return {
        "rigid": polar_rotation(A),
        "average": polar_rotation(A @ np.linalg.inv(C_ref)),
        "principal": R,
    }


def anisotropic_cloud(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    return rng.normal(size=(n, 3)) * [0.06, 0.03, 0.015] + [0.3, -0.2, 0.1]


@pytest.mark.parametrize("mode", MODE_NAMES)
def test_rigid_motion_recovered_exactly_in_every_mode(mode: str) -> None:
    rng = np.random.default_rng(10)
    rest = anisotropic_cloud(rng)
    for seed in range(5):
        rot = Rotation.random(random_state=seed)
        pts = rest @ rot.as_matrix().T + rng.normal(size=3)
        q, m = object_rotation(pts, rest, force_mode=mode)
        assert m == mode
        assert abs(np.linalg.norm(q) - 1.0) < 1e-6 and q[3] >= 0.0
        assert quat_close(q, rot.as_quat(), 1e-9 + 2e-7), (mode, q, rot.as_quat())


def test_mode_follows_sigma_thresholds() -> None:
    rng = np.random.default_rng(11)
    rest = anisotropic_cloud(rng, 400)
    for scale, expected in ((0.03, "average"), (0.12, "principal"), (0.5, "rigid")):
        pts = rest + rng.normal(size=rest.shape) * scale
        d2 = np.sum((pts - rest) ** 2, axis=1)
        sigma = np.std(d2)
        assert expected == ("average" if sigma < 0.01 else "principal" if sigma < 0.1 else "rigid")
        assert object_rotation(pts, rest)[1] == expected
    # thresholds are parameters
    assert object_rotation(rest + 0.01, rest, tau1=0.0, tau2=0.0)[1] == "rigid"


def test_deformed_rotations_match_reference_definitions() -> None:
    rng = np.random.default_rng(12)
    rest = anisotropic_cloud(rng, 300)
    for seed in range(4):
        R = Rotation.random(random_state=100 + seed).as_matrix()
        S = np.eye(3) + 0.15 * rng.normal(size=(3, 3))
        S = 0.5 * (S + S.T)
        pts = (rest - rest.mean(0)) @ S.T @ R.T + rng.normal(size=3) + 0.002 * rng.normal(size=rest.shape)
        ref = ref_rotations(pts, rest)
        for mode in MODE_NAMES:
            q, _ = object_rotation(pts, rest, force_mode=mode)
            q_ref = Rotation.from_matrix(ref[mode]).as_quat()
            assert quat_close(q, q_ref, 1e-6), (mode, q, q_ref)


def test_batched_pose_and_velocity_multi_object() -> None:
    """Objects of 27, 48 and 8 nodes in one launch; velocity from two successive poses."""
    rng = np.random.default_rng(13)
    meshes = [grid_tet_mesh(3, 3, 3, 0.03), grid_tet_mesh(2, 4, 6, 0.01), grid_tet_mesh(2, 2, 2, 0.05)]
    rest = np.concatenate([m[0] * [1.0, 1.3, 0.7] + [k, 0, 0] for k, m in enumerate(meshes)])
    offsets = np.cumsum([0] + [len(m[0]) for m in meshes])
    tets = np.concatenate([m[1] + offsets[k] for k, m in enumerate(meshes)])
    tet_obj = np.concatenate([np.full(len(m[1]), k) for k, m in enumerate(meshes)])
    layout = StrainLayout.from_arrays(rest, tets, tet_obj)
    mass = rng.uniform(0.5, 2.0, len(rest))
    pose = ObjectPoseBuffers.allocate(layout, wp.array(mass.astype(np.float32), dtype=float))
    sbuf = StrainBuffers.allocate(layout)
    rots = [Rotation.random(random_state=k) for k in range(3)]
    dt = 1.0 / 60.0
    ang = np.array([[0.5, -1.0, 2.0], [0.0, 0.3, 0.0], [-3.0, 0.0, 1.0]])
    vel = rng.normal(size=(3, 3))

    def place(step: int) -> np.ndarray:
        out = rest.copy()
        for k in range(3):
            sl = slice(offsets[k], offsets[k + 1])
            rk = Rotation.from_rotvec(ang[k] * dt * step) * rots[k]
            c = np.average(rest[sl], axis=0, weights=mass[sl])
            out[sl] = (rest[sl] - c) @ rk.as_matrix().T + c + vel[k] * dt * step
        return out

    for step in range(2):
        pts = wp.array(place(step).astype(np.float32), dtype=wp.vec3)
        compute_sigma(layout, pts, sbuf)
        compute_object_pose(layout, pts, sbuf.sigma, pose, forced_mode=2)
        if step == 0:
            reset_object_history(pose, wp.ones(3, dtype=wp.int32))
            assert np.all(pose.lin_vel.numpy() == 0.0)
        else:
            update_object_velocity(pose, dt)
    q = pose.quat.numpy()
    for k in range(3):
        rk = Rotation.from_rotvec(ang[k] * dt) * rots[k]
        assert quat_close(q[k], rk.as_quat(), 1e-9 + 2e-7)
    # com of a rigid motion moves by vel*dt exactly; float32 positions ~1 m limit the precision
    np.testing.assert_allclose(pose.lin_vel.numpy(), vel, atol=2e-3)
    assert np.abs(pose.ang_vel.numpy() - ang).max() < 2e-3, pose.ang_vel.numpy() - ang
    assert pose.mode.numpy().tolist() == [2, 2, 2]


def test_bad_input_raises() -> None:
    with pytest.raises(ValueError, match="shape"):
        object_rotation(np.zeros((10, 3)), np.zeros((9, 3)))
    with pytest.raises(ValueError, match="force_mode"):
        object_rotation(np.eye(4, 3), np.eye(4, 3), force_mode="best")
