"""The residual penalty: -k * sum of squared offsets from the rule's targets, on hand-written offsets."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from d3grasp.envs.config import GraspEnvConfig
from d3grasp.envs.grasp_env import _check_config
from d3grasp.envs.mdp.rewards import residual_penalty


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
