"""Chebyshev acceleration: the weights against their closed-form limit, the kernel against its NumPy
twin, and the acceleration itself on a Jacobi iteration whose spectral radius is known analytically."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from d3grasp.kernels.chebyshev import chebyshev_step, chebyshev_step_numpy, chebyshev_weights

wp.config.log_level = wp.LOG_WARNING


def test_weights_start_and_limit() -> None:
    rho = 0.9
    w = chebyshev_weights(rho, 200)
    assert w[0] == 1.0
    assert w[1] == pytest.approx(2.0 / (2.0 - rho**2))
    # The recurrence's fixed point w = 4 / (4 - rho^2 w): w = 2 / (1 + sqrt(1 - rho^2)).
    assert w[-1] == pytest.approx(2.0 / (1.0 + np.sqrt(1.0 - rho**2)), rel=1e-9)
    assert chebyshev_weights(0.0, 5) == [1.0] * 5
    with pytest.raises(ValueError):
        chebyshev_weights(1.0, 3)


def test_kernel_matches_numpy_twin() -> None:
    rng = np.random.default_rng(3)
    x, p1, p2 = (rng.normal(size=(17, 3)).astype(np.float32) for _ in range(3))
    omega = 1.37
    xs = [wp.array(a, dtype=wp.vec3, device="cpu") for a in (x, p1, p2)]
    out = wp.zeros(17, dtype=wp.vec3, device="cpu")
    wp.launch(chebyshev_step, dim=17, inputs=[omega, *xs, out], device="cpu")
    ref = chebyshev_step_numpy(omega, x.astype(np.float64), p1.astype(np.float64), p2.astype(np.float64))
    for got, want in zip((xs[0], xs[1], xs[2]), ref, strict=True):
        np.testing.assert_allclose(got.numpy(), want, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(out.numpy(), ref[0], rtol=1e-6, atol=1e-6)


def test_accelerates_jacobi_on_a_poisson_problem() -> None:
    """Jacobi on the 1D Poisson matrix tridiag(-1, 2, -1) of n unknowns has spectral radius
    cos(pi / (n + 1)); with that rho, Chebyshev's error after k sweeps is bounded by
    2 r^k / (1 + r^{2k}) (r = rho / (1 + sqrt(1 - rho^2))), far below the plain rho^k."""
    n, k = 30, 60
    rho = np.cos(np.pi / (n + 1))
    A = 2.0 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
    b = np.ones(n)
    exact = np.linalg.solve(A, b)

    def jacobi(x: np.ndarray) -> np.ndarray:
        return (b - (A - 2.0 * np.eye(n)) @ x) / 2.0

    x0 = np.zeros(n)
    plain = x0.copy()
    for _ in range(k):
        plain = jacobi(plain)
    weights = chebyshev_weights(rho, k)
    x, p1, p2 = x0.copy(), x0.copy(), x0.copy()
    for w in weights:  # the same bookkeeping as the solver hook: sweep, then extrapolate
        x, p1, p2 = chebyshev_step_numpy(w, jacobi(x), p1, p2)
    e0 = np.linalg.norm(x0 - exact)
    r = rho / (1.0 + np.sqrt(1.0 - rho**2))
    bound = 2.0 * r**k / (1.0 + r ** (2 * k))
    assert np.linalg.norm(x - exact) / e0 <= bound * 1.01
    assert np.linalg.norm(x - exact) < 0.05 * np.linalg.norm(plain - exact)
