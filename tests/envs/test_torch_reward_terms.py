"""The reward terms computed in torch: the residual penalty (-k * sum of squared offsets from the rule's
targets) and the success bonus on hand-written values, and a term added by its declaration alone."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from d3grasp.envs import make_env
from d3grasp.envs.config import GraspEnvConfig
from d3grasp.envs.grasp_env import _check_config
from d3grasp.envs.mdp import rewards
from d3grasp.envs.mdp.rewards import residual_penalty, success_bonus


def _env(residual: np.ndarray, k: float, residual_mode: bool = True) -> SimpleNamespace:
    cfg = GraspEnvConfig(residual_penalty=k)
    return SimpleNamespace(
        cfg=cfg,
        num_envs=residual.shape[0],
        torch_device=torch.device("cpu"),
        residual_base=object() if residual_mode else None,
        act=SimpleNamespace(residual=torch.as_tensor(residual, dtype=torch.float32)),
    )


def test_penalty_is_minus_k_times_the_squared_offsets() -> None:
    r = np.zeros((3, 16))
    r[1, [1, 2, 3]] = 0.5  # a half squeeze of the index finger's three flexion joints
    r[2, 13] = -1.0  # the thumb's first flexion joint fully opened
    got = residual_penalty(_env(r, k=0.02)).numpy()
    np.testing.assert_allclose(got, [0.0, -0.02 * 0.75, -0.02 * 1.0], rtol=1e-6)


def test_penalty_off_without_weight_or_residual() -> None:
    r = np.full((2, 16), 0.3)
    assert not residual_penalty(_env(r, k=0.0)).any()
    assert not residual_penalty(_env(r, k=0.5, residual_mode=False)).any()


def test_negative_weight_is_refused() -> None:
    with pytest.raises(ValueError, match="residual_penalty"):
        _check_config(GraspEnvConfig(residual_penalty=-0.1), num_envs=1)


def test_success_bonus_is_50_a_lift_and_100_more_a_hold() -> None:
    env = SimpleNamespace(cfg=GraspEnvConfig(), torch_device=torch.device("cpu"))
    episodes = [
        {"s_lift": 0, "s_disturb": 0},
        {"s_lift": 1, "s_disturb": 0},
        {"s_lift": 1, "s_disturb": 1},
    ]
    np.testing.assert_array_equal(success_bonus(env, episodes).numpy(), [0.0, 50.0, 150.0])


def _box_env():
    """One world with the medium box, no randomisation: two such envs step identically."""
    return make_env(
        "D3Grasp-DexHand13-Mixed-v0",
        num_envs=1,
        objects={"ids": ("box_01",)},
        seed=0,
        randomization__enabled=False,
    )


def test_a_term_added_to_the_declaration_is_paid_and_logged(monkeypatch) -> None:
    """What adding a torch term takes: its entry in ``TORCH_TERMS``. Two envs step the same episode
    with zero actions (the rule), one with a step term of -0.25 and an episode term of 7 declared."""
    plain = _box_env()
    added = (
        rewards.TorchTerm(
            "wrist_cost", "step", lambda env: torch.full((env.num_envs,), -0.25), lambda cfg: True
        ),
        rewards.TorchTerm(
            "finish", "episode", lambda env, eps: torch.full((len(eps),), 7.0), lambda cfg: True
        ),
    )
    monkeypatch.setattr(rewards, "TORCH_TERMS", rewards.TORCH_TERMS + added)
    extended = _box_env()
    clip = plain.cfg.reward_clip
    zero = torch.zeros(1, plain.num_actions)
    for _ in range(plain.max_episode_length):
        _, rew_plain, done, log_plain = plain.step(zero)
        _, rew_ext, done_ext, log_ext = extended.step(zero)
        assert torch.equal(done, done_ext)
        assert log_ext["log"]["Reward/wrist_cost"] == pytest.approx(-0.25)
        if done[0]:
            break
        expected = (rew_plain - 0.25).clamp(-clip, clip)
        torch.testing.assert_close(rew_ext, expected, rtol=0, atol=1e-5)
    assert done[0], "the episode did not end"
    # The episode's last step: the step term inside the clip, the episode terms (the success bonus
    # and the added one) after it.
    bonus = log_plain["log"]["Reward/success_bonus"]  # one world: the sum over worlds / W is its own
    expected = (rew_plain - bonus - 0.25).clamp(-clip, clip) + bonus + 7.0
    torch.testing.assert_close(rew_ext, expected, rtol=0, atol=1e-4)
    assert log_ext["log"]["Reward/finish"] == pytest.approx(7.0)
    assert "Reward/finish" not in log_plain["log"] and "Reward/wrist_cost" not in log_plain["log"]
