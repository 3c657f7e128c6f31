"""Strain kernels against an independent float64 NumPy transcription and analytic cases."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.strain import StrainBuffers, StrainLayout, compute_sigma, compute_strain
from d3grasp.kernels.strain_numpy import (
    deformation_sigma,
    green_lagrange_max_eig,
    grid_tet_mesh,
    nodal_max_principal_strain,
)
from scipy.spatial.transform import Rotation

wp.config.log_level = wp.LOG_WARNING


def ref_strain(
    points: np.ndarray, rest: np.ndarray, tets: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-tet lambda_max, nodal eps_max, object mean (float64, written from the paper's equations)."""
    x, X = np.asarray(points, np.float64), np.asarray(rest, np.float64)
    lam = np.empty(len(tets))
    vol = np.empty(len(tets))
    for t, (a, b, c, d) in enumerate(tets):
        Dm = np.column_stack([X[b] - X[a], X[c] - X[a], X[d] - X[a]])
        Ds = np.column_stack([x[b] - x[a], x[c] - x[a], x[d] - x[a]])
        F = Ds @ np.linalg.inv(Dm)
        E = 0.5 * (F.T @ F - np.eye(3))
        lam[t] = np.linalg.eigvalsh(E)[-1]
        vol[t] = abs(np.linalg.det(Dm)) / 6.0
    num = np.zeros(len(x))
    den = np.zeros(len(x))
    for t, tet in enumerate(tets):
        for i in tet:
            num[i] += vol[t] * lam[t]
            den[i] += vol[t]
    nodes = den > 0
    eps = np.where(nodes, num / np.where(nodes, den, 1.0), 0.0)
    return lam, eps, float(eps[nodes].mean())


def random_deformation(rest: np.ndarray, rng: np.random.Generator, amp: float) -> np.ndarray:
    R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
    A = np.eye(3) + amp * rng.normal(size=(3, 3))
    return (rest @ A.T) @ R.T + rng.normal(size=3) + amp * 0.01 * rng.normal(size=rest.shape)


def test_green_lagrange_max_eig_random_and_analytic() -> None:
    rng = np.random.default_rng(0)
    F = np.eye(3) + 0.3 * rng.normal(size=(200, 3, 3))
    ref = np.array([np.linalg.eigvalsh(0.5 * (f.T @ f - np.eye(3)))[-1] for f in F])
    np.testing.assert_allclose(green_lagrange_max_eig(F), ref, atol=5e-6, rtol=1e-5)
    # pure rotation -> 0; uniaxial stretch lambda -> (lambda^2 - 1) / 2; shrink -> 0 is the largest
    R = Rotation.random(50, random_state=1).as_matrix()
    assert np.abs(green_lagrange_max_eig(R)).max() < 2e-6
    for lam in (1.1, 1.5, 2.0):
        F = np.diag([1.0, lam, 1.0])[None] @ R[:5].transpose(0, 2, 1)
        np.testing.assert_allclose(green_lagrange_max_eig(R[:5] @ F), (lam**2 - 1) / 2, rtol=1e-5)
    np.testing.assert_allclose(
        green_lagrange_max_eig(np.diag([0.8, 0.9, 0.7])[None]), [(0.9**2 - 1) / 2], rtol=1e-5
    )
    with pytest.raises(ValueError, match="shape"):
        green_lagrange_max_eig(np.zeros((3, 3)))


def test_nodal_strain_matches_reference_and_analytic() -> None:
    rng = np.random.default_rng(1)
    rest, tets = grid_tet_mesh(4, 3, 5, spacing=0.02)
    pts = random_deformation(rest, rng, 0.15)
    eps, mean = nodal_max_principal_strain(pts, rest, tets)
    _, ref_eps, ref_mean = ref_strain(pts, rest, tets)
    np.testing.assert_allclose(eps, ref_eps, atol=2e-5, rtol=1e-4)
    assert mean == pytest.approx(ref_mean, rel=1e-4, abs=1e-6)

    # rigid motion -> zero strain everywhere
    R = Rotation.random(random_state=3).as_matrix()
    eps, mean = nodal_max_principal_strain(rest @ R.T + [1.0, -2.0, 0.5], rest, tets)
    assert np.abs(eps).max() < 1e-4 and abs(mean) < 1e-4
    # uniaxial stretch of the whole body: every node (lambda^2 - 1)/2 (DESIGN: 10% -> 0.105)
    eps, mean = nodal_max_principal_strain(rest * [1.1, 1.0, 1.0], rest, tets)
    np.testing.assert_allclose(eps, 0.105, rtol=1e-4)
    assert mean == pytest.approx(0.105, rel=1e-4)


def test_multi_object_layout_different_sizes_one_launch() -> None:
    """Three objects (27, 60, 8 nodes) in three worlds plus unrelated particles, interleaved ids."""
    rng = np.random.default_rng(2)
    meshes = [grid_tet_mesh(3, 3, 3, 0.03), grid_tet_mesh(3, 4, 5, 0.01), grid_tet_mesh(2, 2, 2, 0.05)]
    rest_all, cur_all, tets_all, tet_obj = [np.zeros((5, 3))], [rng.normal(size=(5, 3))], [], []
    offset = 5  # five free particles (e.g. cloth or debris) that belong to no tet
    for k, (r, t) in enumerate(meshes):
        rest_all.append(r + [k, 0.0, 0.0])
        cur_all.append(random_deformation(r, rng, 0.1 * (k + 1)))
        tets_all.append(t + offset)
        tet_obj.append(np.full(len(t), k))
        offset += len(r)
    rest = np.concatenate(rest_all)
    cur = np.concatenate(cur_all)
    tets = np.concatenate(tets_all)
    layout = StrainLayout.from_arrays(rest, tets, np.concatenate(tet_obj), object_world=np.array([0, 1, 2]))
    assert layout.node_counts.tolist() == [27, 60, 8]
    buf = StrainBuffers.allocate(layout)
    pts = wp.array(cur.astype(np.float32), dtype=wp.vec3)
    compute_strain(layout, pts, buf)
    compute_sigma(layout, pts, buf)

    _, ref_eps, _ = ref_strain(cur, rest, tets)
    np.testing.assert_allclose(buf.node_eps.numpy(), ref_eps, atol=2e-5, rtol=1e-4)
    offset = 5
    for k, (r, _) in enumerate(meshes):
        sl = slice(offset, offset + len(r))
        _, _, ref_mean = ref_strain(cur[sl], rest[sl], meshes[k][1])
        assert buf.object_eps.numpy()[k] == pytest.approx(ref_mean, rel=1e-4, abs=1e-6)
        d2 = np.sum((cur[sl] - rest[sl]) ** 2, axis=1)
        assert buf.sigma.numpy()[k] == pytest.approx(np.std(d2), rel=1e-4, abs=1e-7)
        offset += len(r)
    assert np.all(buf.node_eps.numpy()[:5] == 0.0)


def test_deformation_sigma() -> None:
    rng = np.random.default_rng(3)
    rest = rng.normal(size=(300, 3)) * 0.05
    cur = rest + rng.normal(size=(300, 3)) * 0.02
    d2 = np.sum((cur - rest) ** 2, axis=1)
    assert deformation_sigma(cur, rest) == pytest.approx(np.std(d2), rel=1e-4)
    assert deformation_sigma(rest + [0.3, 0.0, 0.0], rest) == pytest.approx(0.0, abs=1e-6)  # pure translation
    with pytest.raises(ValueError, match="shape"):
        deformation_sigma(cur[:10], rest)


def test_mean_strain_gradient_matches_finite_differences() -> None:
    """Tape gradient of eps_bar_max w.r.t. node positions vs central differences of the float64 reference."""
    rng = np.random.default_rng(4)
    rest, tets = grid_tet_mesh(3, 3, 2, spacing=0.1)
    cur = random_deformation(rest, rng, 0.2)
    layout = StrainLayout.from_arrays(rest, tets)
    buf = StrainBuffers.allocate(layout, requires_grad=True)
    pts = wp.array(cur.astype(np.float32), dtype=wp.vec3, requires_grad=True)
    tape = wp.Tape()
    with tape:
        compute_strain(layout, pts, buf)
    tape.backward(grads={buf.object_eps: wp.ones(1, dtype=float)})
    grad = pts.grad.numpy().astype(np.float64)

    h = 1e-6
    fd = np.zeros_like(cur)
    for i in range(len(cur)):
        for a in range(3):
            plus, minus = cur.copy(), cur.copy()
            plus[i, a] += h
            minus[i, a] -= h
            fd[i, a] = (ref_strain(plus, rest, tets)[2] - ref_strain(minus, rest, tets)[2]) / (2 * h)
    scale = np.abs(fd).max()
    assert scale > 1e-2  # the test can fail: the gradient is not trivially zero
    np.testing.assert_allclose(grad, fd, atol=2e-3 * scale)


def test_bad_input_raises() -> None:
    rest, tets = grid_tet_mesh(2, 2, 2)
    with pytest.raises(ValueError, match="tet indices"):
        nodal_max_principal_strain(rest, rest, tets + 100)
    with pytest.raises(ValueError, match="degenerate"):
        nodal_max_principal_strain(rest, rest, np.array([[0, 1, 2, 3]]) * 0)


def test_gradient_finite_at_rest_and_repeated_eigenvalues() -> None:
    """At rest (E = 0, triple eigenvalue) and under uniaxial stretch the gradient is finite and correct."""
    rest, tets = grid_tet_mesh(3, 2, 2, spacing=0.1)
    layout = StrainLayout.from_arrays(rest, tets)
    for stretch in (1.0, 1.2):
        cur = rest * [stretch, 1.0, 1.0]
        buf = StrainBuffers.allocate(layout, requires_grad=True)
        pts = wp.array(cur.astype(np.float32), dtype=wp.vec3, requires_grad=True)
        tape = wp.Tape()
        with tape:
            compute_strain(layout, pts, buf)
        tape.backward(grads={buf.object_eps: wp.ones(1, dtype=float)})
        grad = pts.grad.numpy()
        assert np.all(np.isfinite(grad))
        if stretch > 1.0:
            # the top eigenvalue is simple here: compare with one-sided-safe central differences
            h = 1e-6
            i = int(np.argmax(np.abs(grad[:, 0])))
            plus, minus = cur.copy(), cur.copy()
            plus[i, 0] += h
            minus[i, 0] -= h
            fd = (ref_strain(plus, rest, tets)[2] - ref_strain(minus, rest, tets)[2]) / (2 * h)
            assert grad[i, 0] == pytest.approx(fd, rel=2e-3)


def test_layout_from_newton_model_one_object_per_world() -> None:
    import newton  # a core dependency: its absence fails, not skips

    obj = newton.ModelBuilder()
    obj.add_soft_grid(
        pos=wp.vec3(0.0, 0.0, 0.01), rot=wp.quat_identity(), vel=wp.vec3(0.0), dim_x=2, dim_y=3, dim_z=2,
        cell_x=0.01, cell_y=0.01, cell_z=0.01, density=200.0, k_mu=5e4, k_lambda=2e5, k_damp=1e-2,
    )  # fmt: skip
    scene = newton.ModelBuilder()
    scene.replicate(obj, 3)
    model = scene.finalize(device="cpu")
    layout = StrainLayout.from_model(model)
    assert layout.node_counts.tolist() == [36, 36, 36] and layout.object_world.tolist() == [0, 1, 2]
    # Newton's own rest inverses agree with ours
    np.testing.assert_allclose(layout.inv_dm.numpy(), model.tet_poses.numpy(), rtol=1e-5, atol=1e-3)
    buf = StrainBuffers.allocate(layout)
    stretched = model.particle_q.numpy() * [1.0, 1.0, 1.1]
    compute_strain(layout, wp.array(stretched.astype(np.float32), dtype=wp.vec3), buf)
    np.testing.assert_allclose(buf.object_eps.numpy(), 0.105, rtol=1e-4)
