"""The disturbance kernel: a rigid object's push at its body, a soft object's spread over its nodes in
proportion to their mass (a body force), against the hand-computed split; which solver iterations
solve the hand when a soft environment thins them."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from d3grasp.envs.physics import _apply_object_force_kernel

wp.config.log_level = wp.LOG_WARNING


def test_push_acts_on_the_rigid_body_and_on_soft_nodes_by_mass() -> None:
    force = np.array([[1.0, -2.0, 0.5], [0.0, 0.0, -2.5], [0.0, 0.0, 0.0]], dtype=np.float32)
    object_body = np.array([0, -1, 1], dtype=np.int32)  # world 0 rigid, 1 soft, 2 rigid (no push)
    particle_start = np.array([0, 0, 0], dtype=np.int32)
    particle_count = np.array([0, 3, 0], dtype=np.int32)
    mass = np.array([1e-3, 2e-3, 7e-3], dtype=np.float32)
    body_f = wp.zeros(2, dtype=wp.spatial_vector)
    particle_f = wp.array(np.full((3, 3), 0.1, dtype=np.float32), dtype=wp.vec3)  # forces already there add
    wp.launch(
        _apply_object_force_kernel,
        dim=3,
        inputs=[
            wp.array(force, dtype=wp.vec3),
            wp.array(object_body, dtype=wp.int32),
            wp.array(particle_start, dtype=wp.int32),
            wp.array(particle_count, dtype=wp.int32),
            wp.array(mass, dtype=float),
        ],
        outputs=[body_f, particle_f],
    )
    bf = body_f.numpy()
    np.testing.assert_allclose(bf[0], [1.0, -2.0, 0.5, 0, 0, 0], atol=1e-7)
    np.testing.assert_allclose(bf[1], 0.0, atol=1e-7)
    pf = particle_f.numpy() - 0.1
    expected = np.outer(mass / mass.sum(), force[1])
    np.testing.assert_allclose(pf, expected, rtol=1e-5, atol=1e-7)
    # Equal accelerations: the push strains nothing; the total is the push.
    np.testing.assert_allclose(pf / mass[:, None], np.tile(force[1] / mass.sum(), (3, 1)), rtol=1e-5)


def test_rigid_iterations_are_spread_evenly_and_end_on_the_last() -> None:
    from d3grasp.envs.physics import rigid_iterations_run

    runs = rigid_iterations_run(5, 20)
    assert [i for i, r in enumerate(runs) if r] == [3, 7, 11, 15, 19]  # every 4th, by hand
    assert rigid_iterations_run(20, 20) == [True] * 20
    assert rigid_iterations_run(1, 20) == [False] * 19 + [True]
    for n in range(1, 21):
        runs = rigid_iterations_run(n, 20)
        gaps = np.diff([-1] + [i for i, r in enumerate(runs) if r])
        assert sum(runs) == n and runs[-1] and gaps.max() - gaps.min() <= 1  # n of them, spaced within one
    for bad in (0, 21, -1):
        with pytest.raises(ValueError, match="soft_rigid_iterations"):
            rigid_iterations_run(bad, 20)
