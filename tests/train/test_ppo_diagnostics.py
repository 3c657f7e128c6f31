"""The training diagnostics and repairs of d3grasp.train.ppo against hand-worked cases.

Explained variance, masked normalisation and cosines on numbers worked by hand; the split-half
gradient cosine on rollouts built so the answer is known (two identical halves: +1; one half's
advantages negated: -1), and the half gradients against the same gradient recomputed by stepping
the LSTM through each world's rollout one step at a time (the rollout's own path, not the update's
padded batches); episodes per update from the dones; the bound loss from its formula.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from d3grasp.train.curves import diagnostics_markdown, diagnostics_summary, load_scalars
from d3grasp.train.ppo import (
    D3GraspPPO,
    explained_variance,
    explained_variance_from_sums,
    flat_cosine,
    masked_normalise,
    variance_sums,
)
from rsl_rl.models import MLPModel, RNNModel
from rsl_rl.storage import RolloutStorage
from tensordict import TensorDict

T, OBS, ACT = 6, 3, 2
PHASES = ("a", "b")


def test_explained_variance_hand_worked() -> None:
    # y = 1, 2, 3, 4 (population variance 1.25); V = 1, 2, 3, 3 -> e = 0, 0, 0, 1 (variance 0.1875)
    y = torch.tensor([1.0, 2.0, 3.0, 4.0])
    v = torch.tensor([1.0, 2.0, 3.0, 3.0])
    assert explained_variance(y, v) == pytest.approx(1.0 - 0.1875 / 1.25)
    assert explained_variance(y, y) == pytest.approx(1.0)  # a perfect critic
    # A constant offset is not explained variance lost: V = y - 1 leaves e = 1, Var(e) = 0.
    assert explained_variance(y, y - 1.0) == pytest.approx(1.0)
    # A critic predicting the mean explains nothing: 1 - Var(y - 2.5) / Var(y) = 0.
    assert explained_variance(y, torch.full((4,), 2.5)) == pytest.approx(0.0, abs=1e-12)
    # Sums add over ranks: the two halves' sums give the whole set's figure.
    both = variance_sums(y[:2], v[:2]) + variance_sums(y[2:], v[2:])
    assert explained_variance_from_sums(both) == pytest.approx(0.85)
    assert math.isnan(explained_variance(torch.ones(3), torch.zeros(3)))  # returns without variance
    assert math.isnan(explained_variance(torch.ones(1), torch.zeros(1)))


def test_masked_normalise_and_cosine_hand_worked() -> None:
    x = torch.tensor([[1.0], [2.0], [3.0], [100.0]])
    mask = torch.tensor([[True], [True], [True], [False]])
    # mean 2, unbiased std 1 over the first three; the masked entry is zero
    np.testing.assert_allclose(masked_normalise(x, mask).flatten().numpy(), [-1.0, 0.0, 1.0, 0.0], atol=1e-6)
    assert torch.equal(masked_normalise(x, torch.zeros_like(mask)), torch.zeros_like(x))
    assert flat_cosine(torch.tensor([1.0, 0.0]), torch.tensor([1.0, 1.0])) == pytest.approx(1 / math.sqrt(2))
    assert flat_cosine(torch.tensor([1.0, 2.0]), torch.tensor([-2.0, -4.0])) == pytest.approx(-1.0)
    assert math.isnan(flat_cosine(torch.zeros(2), torch.ones(2)))


def _algorithm(num_envs: int, **kwargs: object) -> D3GraspPPO:
    torch.manual_seed(0)
    obs = TensorDict({"policy": torch.zeros(num_envs, OBS)}, batch_size=[num_envs])
    groups = {"actor": ["policy"], "critic": ["policy"]}
    actor = RNNModel(
        obs,
        groups,
        "actor",
        ACT,
        hidden_dims=[8],
        rnn_type="lstm",
        rnn_hidden_dim=8,
        distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5, "std_type": "scalar"},
    )
    critic = MLPModel(obs, groups, "critic", 1, hidden_dims=[8])
    storage = RolloutStorage("rl", num_envs, T, obs, [ACT], "cpu")
    return D3GraspPPO(
        actor, critic, storage, gamma=1.0, lam=0.95, phase_names=PHASES, schedule="fixed", **kwargs
    )


def _mirrored_rollout(alg: D3GraspPPO, active: torch.Tensor | None = None) -> None:
    """A rollout whose worlds k and k + W/2 see the same observations, take the same actions and get
    the same rewards (so both halves of the worlds hold the same data); world 0 ends an episode at
    step 2. ``active`` (T, W) masks steps whose actions take effect."""
    W = alg.storage.num_envs
    h = W // 2
    rng = np.random.default_rng(3)
    obs_seq = rng.normal(size=(T + 1, h, OBS)).astype(np.float32)
    act_seq = rng.normal(size=(T, h, ACT)).astype(np.float32) * 0.5
    rew_seq = rng.normal(size=(T, h)).astype(np.float32)
    for t in range(T):
        obs = TensorDict({"policy": torch.as_tensor(np.concatenate([obs_seq[t]] * 2))}, batch_size=[W])
        alg.record_step(None if active is None else active[t], torch.full((W,), t % 2))
        with torch.inference_mode():
            alg.act(obs)
            alg.transition.actions = torch.as_tensor(np.concatenate([act_seq[t]] * 2))
            alg.transition.actions_log_prob = alg.actor.get_output_log_prob(alg.transition.actions).detach()
            dones = torch.zeros(W, dtype=torch.bool)
            if t == 2:
                dones[0] = dones[h] = True
            nxt = TensorDict(
                {"policy": torch.as_tensor(np.concatenate([obs_seq[t + 1]] * 2))}, batch_size=[W]
            )
            alg.process_env_step(nxt, torch.as_tensor(np.concatenate([rew_seq[t]] * 2)), dones, {})
    with torch.inference_mode():
        alg.compute_returns(TensorDict({"policy": torch.as_tensor(np.concatenate([obs_seq[T]] * 2))}, [W]))


def test_split_half_cosine_of_identical_and_opposed_halves() -> None:
    alg = _algorithm(4)
    _mirrored_rollout(alg)
    d = alg.diagnose()
    assert d["grad_cosine_split_half"] == pytest.approx(1.0, abs=1e-5)
    # Episodes finished in the update's samples: worlds 0 and 2 at step 2.
    assert d["episodes_per_update"] == 2
    # Negate the second half's advantages: its policy gradient points the other way.
    alg.storage.advantages[:, 2:] *= -1.0
    assert alg.diagnose()["grad_cosine_split_half"] == pytest.approx(-1.0, abs=1e-5)


def test_split_half_gradient_matches_a_step_by_step_rollout() -> None:
    """Each half's gradient equals -sum A grad log pi recomputed by stepping the LSTM through the
    stored observations one step at a time (the rollout's path), with masked steps left out."""
    W = 4
    active = torch.ones(T, W, dtype=torch.bool)
    active[:2] = False  # the first two steps' actions take no effect
    alg = _algorithm(W)
    _mirrored_rollout(alg, active)
    st = alg.storage
    # Masked steps carry no advantage; the others are standardised.
    assert torch.all(st.advantages[:2] == 0)
    sel = st.advantages[2:].flatten()
    assert float(sel.mean()) == pytest.approx(0.0, abs=1e-5) and float(sel.std()) == pytest.approx(
        1.0, rel=1e-4
    )

    halves = [alg._half_gradient(*half) for half in alg._world_halves()]
    for k, worlds in enumerate((slice(0, 2), slice(2, 4))):
        ref = _stepped_policy_gradient(alg, active, worlds)
        np.testing.assert_allclose(halves[k].numpy(), ref.numpy(), rtol=1e-4, atol=1e-6)


def test_world_gradients_sum_to_the_split_half_gradients() -> None:
    """The per-world rows d3grasp.train.gradient_noise collects, summed over each half, are the
    split-half diagnostic's half gradients (checked step by step above)."""
    alg = _algorithm(4)
    _mirrored_rollout(alg)
    rows = alg.world_gradients()
    assert rows.shape == (4, sum(p.numel() for p in alg.actor.parameters()))
    halves = [alg._half_gradient(*half) for half in alg._world_halves()]
    np.testing.assert_allclose(rows[:2].sum(0).numpy(), halves[0].detach().numpy(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(rows[2:].sum(0).numpy(), halves[1].detach().numpy(), rtol=1e-4, atol=1e-6)
    # Mirrored worlds (k and k + 2 hold the same data) have the same gradient.
    np.testing.assert_allclose(rows[0].numpy(), rows[2].numpy(), rtol=1e-5, atol=1e-7)


def test_explained_variance_by_phase_from_the_update() -> None:
    alg = _algorithm(4)
    _mirrored_rollout(alg)
    st = alg.storage
    d = alg.diagnose()
    y, v = st.returns[..., 0].double().numpy(), st.values[..., 0].double().numpy()
    phase = np.array([t % 2 for t in range(T)])[:, None].repeat(4, 1)

    def ev(m: np.ndarray) -> float:
        return 1.0 - np.var(y[m] - v[m]) / np.var(y[m])

    assert d["explained_variance"] == pytest.approx(ev(np.ones_like(y, dtype=bool)), rel=1e-6)
    for i, name in enumerate(PHASES):
        assert d[f"explained_variance_{name}"] == pytest.approx(ev(phase == i), rel=1e-6)


def test_rewards_are_scaled_and_the_bound_loss_follows_its_formula() -> None:
    alg = _algorithm(2, reward_scale=0.01, bound_loss_coef=10.0)
    obs = TensorDict({"policy": torch.zeros(2, OBS)}, batch_size=[2])
    alg.record_step(None, None)
    with torch.inference_mode():
        alg.act(obs)
        alg.process_env_step(obs, torch.tensor([100.0, -50.0]), torch.zeros(2, dtype=torch.bool), {})
    np.testing.assert_allclose(alg.storage.rewards[0, :, 0].numpy(), [1.0, -0.5])
    # relu(|mu| - 1)^2 summed over actions: means (1.2, -0.5) -> 0.04; (-1.5, 2.0) -> 0.25 + 1.0
    mu = torch.tensor([[1.2, -0.5], [-1.5, 2.0]])
    bound = torch.relu(mu.abs() - alg.action_bound).pow(2).sum(-1).mean()
    assert float(bound) == pytest.approx((0.04 + 1.25) / 2)


def test_curves_summarise_the_diagnostics(tmp_path: Path) -> None:
    from torch.utils.tensorboard import SummaryWriter

    writer = SummaryWriter(str(tmp_path))
    for it in range(60):
        writer.add_scalar("Diagnostics/grad_cosine_split_half", 0.01 * it, it)
        writer.add_scalar("Diagnostics/episodes_per_update", 52.0, it)
    writer.close()
    rows = {r.tag: r for r in diagnostics_summary(load_scalars(tmp_path), 10, 50)}
    # 0.10, 0.11, ..., 0.50: 41 values, median 0.30
    cos = rows["grad_cosine_split_half"]
    assert cos.count == 41 and cos.median == pytest.approx(0.30) and cos.low == pytest.approx(0.10)
    assert cos.high == pytest.approx(0.50) and cos.last == pytest.approx(0.59)
    assert rows["episodes_per_update"].median == 52.0
    assert "| grad_cosine_split_half | 0.300 |" in diagnostics_markdown(list(rows.values()), 10, 50)


def test_one_masked_update_against_the_loss_and_gradient_by_hand() -> None:
    """One epoch, one mini-batch: at the rollout's own parameters the ratio is 1, so the clipped
    surrogate the update reports is -sum(active A) / n_active, and the actor's gradient (before the
    optimiser's step) is that of -sum(active A log pi) / n_active, recomputed here by stepping the
    LSTM through the stored observations. Advantages on masked steps change neither."""
    W = 4
    active = torch.ones(T, W, dtype=torch.bool)
    active[:2] = False
    active[4, 1] = False

    def run(scale_masked: float) -> tuple[dict[str, float], list[torch.Tensor], D3GraspPPO, float]:
        alg = _algorithm(W, num_learning_epochs=1, num_mini_batches=1, max_grad_norm=1e9, entropy_coef=0.0)
        _mirrored_rollout(alg, active)
        st = alg.storage
        st.advantages[~active] = scale_masked  # masked steps' advantages: anything
        adv = st.advantages[..., 0]
        expected = -float((adv * active.float()).sum() / active.float().sum())
        grads: list[torch.Tensor] = []
        step = alg.optimizer.step

        def capture(*a: object, **k: object) -> None:
            grads.extend(
                (torch.zeros_like(p) if p.grad is None else p.grad.clone()) for p in alg.actor.parameters()
            )
            step(*a, **k)

        alg.optimizer.step = capture  # type: ignore[method-assign]
        # The reference gradient at the rollout's parameters, before the update moves them.
        reference = _stepped_policy_gradient(alg, active, slice(None), 1.0 / float(active.sum()))
        out = alg.update()
        return out, grads, reference, expected

    out, grads, reference, expected = run(0.0)
    assert out["surrogate"] == pytest.approx(expected, rel=1e-5, abs=1e-7)
    got = torch.cat([g.reshape(-1) for g in grads])
    np.testing.assert_allclose(got.numpy(), reference.numpy(), rtol=1e-4, atol=1e-6)
    out2, grads2, _, _ = run(1000.0)  # huge advantages where no action took effect
    assert out2["surrogate"] == pytest.approx(out["surrogate"], rel=1e-6, abs=1e-8)
    np.testing.assert_allclose(torch.cat([g.reshape(-1) for g in grads2]).numpy(), got.numpy(), rtol=1e-5)


def _stepped_policy_gradient(
    alg: D3GraspPPO, active: torch.Tensor, worlds: slice, scale: float = 1.0
) -> torch.Tensor:
    """d/dtheta of -scale * sum(active A log pi) over ``worlds``, the LSTM stepped through the stored
    observations one step at a time (the rollout's own path, not the update's padded batches)."""
    st, W = alg.storage, alg.storage.num_envs
    params = list(alg.actor.parameters())
    alg.actor.reset()
    alg.actor.hidden_state = None
    loss = torch.zeros(())
    for t in range(T):
        obs = TensorDict({"policy": st.observations["policy"][t].clone()}, batch_size=[W])
        alg.actor(obs, stochastic_output=True)
        logp = alg.actor.get_output_log_prob(st.actions[t])
        w = st.advantages[t, :, 0] * active[t].float()
        loss = loss - (w[worlds] * logp[worlds]).sum()
        alg.actor.reset(st.dones[t, :, 0].bool())
    grads = torch.autograd.grad(scale * loss, params, allow_unused=True)
    alg.actor.reset()
    alg.actor.hidden_state = None
    return torch.cat(
        [(torch.zeros_like(p) if g is None else g).reshape(-1) for p, g in zip(params, grads, strict=True)]
    ).detach()
