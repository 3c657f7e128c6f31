"""Chebyshev semi-iterative acceleration of SolverVBD's particle iterations.

Vertex block descent is a Gauss-Seidel sweep over the soft body's nodes; a FEM body squeezed between
fingertips is a stiff coupled system that plain sweeps converge to slowly (docs/design.md, Soft
objects under the push: 5 iterations leave it much softer than its modulus, 20 hold it). Chen et
al.'s VBD paper accelerates the sweeps with Chebyshev's semi-iterative method: after sweep k the
nodes move to

    x_k = w_k (xbar_k - x_{k-2}) + x_{k-2},
    w_1 = 1,  w_2 = 2 / (2 - rho^2),  w_k = 4 / (4 - rho^2 w_{k-1}),

where xbar_k is the sweep's result and rho estimates the sweep's spectral radius (rho = 0 is the
plain sweep). The weights depend on k and rho only, so they are Python floats baked into each launch
(a captured graph replays them unchanged).
"""

from __future__ import annotations

import numpy as np
import warp as wp

__all__ = ["chebyshev_weights", "chebyshev_step", "chebyshev_step_numpy", "use_chebyshev"]


def chebyshev_weights(rho: float, iterations: int) -> list[float]:
    """w_1..w_n of the recurrence above; all 1 for rho = 0."""
    if not 0.0 <= rho < 1.0:
        raise ValueError(f"Chebyshev rho must be in [0, 1), got {rho}")
    w: list[float] = []
    for k in range(1, iterations + 1):
        if k == 1:
            w.append(1.0)
        elif k == 2:
            w.append(2.0 / (2.0 - rho * rho))
        else:
            w.append(4.0 / (4.0 - rho * rho * w[-1]))
    return w


@wp.kernel
def chebyshev_step(
    omega: float,
    x: wp.array(dtype=wp.vec3),
    x_prev1: wp.array(dtype=wp.vec3),
    x_prev2: wp.array(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
):
    # One thread per node: x <- w (x - x_{k-2}) + x_{k-2}; then shift the two previous iterates.
    i = wp.tid()
    old2 = x_prev2[i]
    xi = omega * (x[i] - old2) + old2
    x[i] = xi
    x_out[i] = xi
    x_prev2[i] = x_prev1[i]
    x_prev1[i] = xi


def chebyshev_step_numpy(
    omega: float, x: np.ndarray, x_prev1: np.ndarray, x_prev2: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NumPy twin of :data:`chebyshev_step`: returns (x, x_prev1, x_prev2) after the step."""
    xi = omega * (x - x_prev2) + x_prev2
    return xi, xi.copy(), x_prev1.copy()


def use_chebyshev(solver, rho: float) -> None:
    """Accelerate ``solver``'s (a SolverVBD) particle iterations with weight ``rho`` (0: unchanged).

    Wraps the solver's step (to restart the recurrence each substep) and its particle iteration (to
    record the substep's start and extrapolate after each sweep)."""
    weights = chebyshev_weights(rho, solver.iterations)  # first: a bad rho is refused on any model
    if rho == 0.0 or solver.model.particle_count == 0:
        return
    n, device = solver.model.particle_count, solver.device
    prev1 = wp.zeros(n, dtype=wp.vec3, device=device)
    prev2 = wp.zeros(n, dtype=wp.vec3, device=device)
    step, iterate = solver.step, solver._solve_particle_iteration
    sweep = [0]

    def step_restarting(*args, **kwargs):
        sweep[0] = 0
        return step(*args, **kwargs)

    def iterate_accelerated(state_in, state_out, contacts, dt):
        if sweep[0] == 0:
            wp.copy(prev1, state_in.particle_q)  # x_0: the substep's initial guess
        iterate(state_in, state_out, contacts, dt)
        k = sweep[0]
        sweep[0] += 1
        if k < len(weights):
            wp.launch(
                chebyshev_step,
                dim=n,
                inputs=[weights[k], state_in.particle_q, prev1, prev2, state_out.particle_q],
                device=device,
            )

    solver.step = step_restarting
    solver._solve_particle_iteration = iterate_accelerated
