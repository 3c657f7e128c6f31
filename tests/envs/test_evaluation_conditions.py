"""The evaluation's conditions, pinned to the paper's protocol and to what the shipped figures were
measured under: the lift height, the tolerances, the push force, duration and six directions, and
the dynamics an evaluation episode does not draw (friction, masses, drive gains, latency). A grasp
that holds because one of these got easier does not count, so a change of any must fail here."""

from __future__ import annotations

import numpy as np
import pytest
from d3grasp.kernels import scoring

from d3grasp.envs import make_env
from d3grasp.envs.mdp import terminations
from d3grasp.envs.script import DISTURB_DIRECTIONS, DISTURB_NAMES


@pytest.fixture(scope="module")
def eval_env():
    env = make_env(
        "D3Grasp-DexHand13-Mixed-v0",
        num_envs=3,
        seed=11,
        eval_mode=True,
        objects={"ids": ("box_01", "bottle_09", "frustum_09")},
    )
    yield env
    env.close()


def test_success_thresholds_are_the_papers() -> None:
    # s_lift: held 0.1 m up, within 2 cm; s_disturb: six pushes of 2.5 N for 2 s, < 2 cm each.
    assert scoring.LIFT_TOLERANCE == 0.02
    assert scoring.DISTURB_TOLERANCE == 0.02
    assert terminations.DISTURB_TOLERANCE == 0.02


def test_evaluation_episode_pushes_six_directions_for_two_seconds(eval_env) -> None:
    ph = eval_env.cfg.phases
    assert ph.lift_height == 0.1 and ph.disturb_force == 2.5 and ph.disturb_per_direction == 2.0
    script = eval_env.script
    assert script.disturb_dirs == 6
    assert script.steps_per_push == 120  # 2 s at 60 Hz
    expected = np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float32
    )
    np.testing.assert_array_equal(DISTURB_DIRECTIONS, expected)
    assert DISTURB_NAMES == ("+x", "-x", "+y", "-y", "+z", "-z")
    # All six, in this order, in every evaluation world.
    np.testing.assert_array_equal(eval_env.draw.disturb_order.cpu().numpy(), np.tile(np.arange(6), (3, 1)))


def test_evaluation_draws_no_dynamics(eval_env) -> None:
    """Friction, masses and drive gains stay nominal and there is no action latency: the evaluation
    draws only the object's place, its yaw and the pads' sensor noise."""
    m, lay = eval_env.model, eval_env.layout
    np.testing.assert_array_equal(m.shape_material_mu.numpy(), eval_env.nominal.shape_mu)
    np.testing.assert_array_equal(m.body_mass.numpy(), eval_env.nominal.body_mass)
    np.testing.assert_array_equal(m.joint_target_ke.numpy(), eval_env.nominal.ke)
    assert int(eval_env.draw.latency.abs().sum()) == 0
    for w in range(3):
        assert float(m.shape_material_mu.numpy()[lay.object_shapes[w][0]]) == pytest.approx(1.0)
    dyn = eval_env.draw.dynamics.cpu().numpy()
    np.testing.assert_array_equal(dyn, np.tile([1.0, 1.0, 1.0, 0.0], (3, 1)))
    assert eval_env.cfg.randomization.tactile_noise_std == 0.05
    assert eval_env.sensors.tactile_cfg.noise_std == 0.05
    start = eval_env.draw.object_start.cpu().numpy()
    assert np.all(np.abs(start[:, :2]) <= 0.01 + 1e-6)  # placed within 1 cm
