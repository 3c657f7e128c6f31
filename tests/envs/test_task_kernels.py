"""The task's kernels against the torch code they replace (their references), on a running
environment with a rigid and a soft object: the observation groups after every step with random
actions and after a reset, and the reward inputs gathered from the state (with the scoring's object
position and finiteness) after every step; in the residual modes (the rule's targets in the policy
group) and the absolute one without touch."""

from __future__ import annotations

import pytest
import torch
import warp as wp

from d3grasp.envs import make_env
from d3grasp.envs.mdp import observations, rewards

wp.config.log_level = wp.LOG_WARNING


def _compare(env) -> None:
    got = observations.compute_observations(env)
    want = observations.reference_observations(env)
    for group in ("policy", "privileged"):
        assert got[group].shape == want[group].shape
        torch.testing.assert_close(got[group], want[group], rtol=1e-5, atol=1e-6, msg=group)


def _compare_reward_inputs(env) -> None:
    want = rewards.reference_reward_inputs(env)
    got = dict(env.reward.step_inputs)
    got["obj_pos"], got["finite"] = env.scoring.step_inputs["obj_pos"], env.scoring.step_inputs["finite"]
    for name, value in want.items():
        torch.testing.assert_close(got[name].reshape(value.shape), value, rtol=1e-5, atol=1e-6, msg=name)


@pytest.mark.parametrize(
    "settings",
    [{}, {"action_mode": "absolute", "tactile_obs": False, "randomization__enabled": False}],
    ids=["synergy residual", "absolute without touch"],
)
def test_kernel_matches_the_torch_terms(settings: dict) -> None:
    env = make_env(
        "D3Grasp-DexHand13-Mixed-v0",
        num_envs=2,
        objects={"ids": ("box_01", "sponge_block_m")},
        seed=5,
        **settings,
    )
    gen = torch.Generator().manual_seed(1)
    _compare(env)
    for _ in range(130):  # into the lift: a touch-timed lift changes the phase term
        env.step(2.0 * torch.rand(env.num_envs, env.num_actions, generator=gen) - 1.0)
        _compare(env)
        _compare_reward_inputs(env)
    env.reset_worlds(torch.tensor([1]))
    _compare(env)
    env.close()
