"""PPO for an outcome scored long after the actions that decide it, with the diagnostics that show
whether an update carries a signal.

``D3GraspPPO`` is rsl-rl 5.5.1's ``PPO`` (same storage, models, returns and clipped surrogate) with:

- **Steps whose action moves nothing are left out of the policy loss.** In the residual modes the
  environment ignores the actions before ``residual_start`` (``GraspEnv.action_takes_effect``); those
  samples' advantages are set to zero and the advantages are normalised over the other samples only,
  and the surrogate is averaged over the samples that count. Before, an update's batch of approach
  steps still made a full-size (normalised) policy step out of noise.
- **Rewards scaled into the critic's range** (``reward_scale``): returns of -70 to +600 in reward
  units make the value loss 1e2-1e4; 0.01 brings them to O(1-10), and the value loss is no longer
  clipped in return units (``use_clipped_value_loss`` off in the task config: a clip of 0.2 on returns
  of hundreds stopped a sample's value from moving after 0.2).
- **A bound loss on the action mean** (``bound_loss_coef``): the environment clamps actions to
  [-1, 1], so a mean past the clamp gets no gradient from the outcome; ``coef * relu(|mu| - 1)^2``
  brings it back (deterministic thumb means of +1.03 to +1.17 were measured, docs/design.md).
- **Diagnostics** (:meth:`diagnose`, before each update): episodes finished in the update's samples,
  the critic's explained variance on the update's returns (all samples and per phase), and the cosine
  between the policy-loss gradients of two disjoint halves of the worlds (split-half). A gradient that
  is mostly noise has a cosine near 0 between halves; an advantage signal-to-noise of 0.2 per sample
  batch gives ~0.02. Pooled over the ranks: every rank adds its sums, so the figures are those of all
  worlds in one batch.

RND, symmetry augmentation and mixed precision are not used by d3grasp's tasks and are refused.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from types import SimpleNamespace
from typing import Any

import torch
from rsl_rl.algorithms import PPO
from rsl_rl.storage import RolloutStorage

__all__ = [
    "D3GraspPPO",
    "explained_variance",
    "explained_variance_from_sums",
    "flat_cosine",
    "masked_normalise",
    "variance_sums",
]


def masked_normalise(x: torch.Tensor, mask: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """``x`` standardised over the entries where ``mask`` is true (mean 0, unbiased std 1 there),
    zero elsewhere. With fewer than two such entries: centred only (or all zero)."""
    mask = mask.to(torch.bool).expand_as(x)
    n = int(mask.sum())
    if n == 0:
        return torch.zeros_like(x)
    sel = x[mask]
    mean = sel.mean()
    std = sel.std() if n > 1 else torch.zeros((), dtype=x.dtype, device=x.device)
    return torch.where(mask, (x - mean) / (std + eps), torch.zeros_like(x))


def variance_sums(returns: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """(5,) float64 sums of a sample set for the explained variance: n, sum y, sum y^2, sum e,
    sum e^2 with y the returns and e = y - V. Sums add over ranks and batches."""
    y = returns.reshape(-1).double()
    e = y - values.reshape(-1).double()
    return torch.stack(
        [
            torch.tensor(float(y.numel()), dtype=torch.float64, device=y.device),
            y.sum(),
            (y * y).sum(),
            e.sum(),
            (e * e).sum(),
        ]
    )


def explained_variance_from_sums(s: torch.Tensor) -> float:
    """``1 - Var(y - V) / Var(y)`` from :func:`variance_sums` (population variances); NaN for fewer
    than two samples or returns without variance."""
    n = float(s[0])
    if n < 2:
        return math.nan
    var_y = float(s[2]) / n - (float(s[1]) / n) ** 2
    var_e = float(s[4]) / n - (float(s[3]) / n) ** 2
    if var_y <= 1e-12:
        return math.nan
    return 1.0 - var_e / var_y


def explained_variance(returns: torch.Tensor, values: torch.Tensor) -> float:
    """The critic's explained variance ``1 - Var(y - V) / Var(y)`` of returns ``y``."""
    return explained_variance_from_sums(variance_sums(returns, values))


def flat_cosine(a: torch.Tensor, b: torch.Tensor) -> float:
    """Cosine of two flat vectors; NaN if either is zero."""
    na, nb = float(a.norm()), float(b.norm())
    if na == 0.0 or nb == 0.0:
        return math.nan
    return float(torch.dot(a, b)) / (na * nb)


def _slice_hidden(saved: Any, a: int, b: int) -> Any:
    """Worlds ``a:b`` of the storage's saved hidden states (each (T, layers, W, hidden)), or None."""
    return None if saved is None else [h[:, :, a:b] for h in saved]


class D3GraspPPO(PPO):
    """rsl-rl PPO with action-effect masks, scaled rewards, a bound loss and diagnostics (module
    docstring). The runner calls :meth:`record_step` before each ``act`` and :meth:`diagnose` between
    ``compute_returns`` and ``update``."""

    def __init__(
        self,
        actor: Any,
        critic: Any,
        storage: RolloutStorage,
        reward_scale: float = 1.0,
        bound_loss_coef: float = 0.0,
        action_bound: float = 1.0,
        phase_names: Sequence[str] = (),
        **kwargs: Any,
    ) -> None:
        for key in ("rnd_cfg", "symmetry_cfg"):
            if kwargs.get(key):
                raise ValueError(f"D3GraspPPO does not support {key}")
        if kwargs.get("use_mixed_precision"):
            raise ValueError("D3GraspPPO does not support use_mixed_precision")
        if kwargs.get("normalize_advantage_per_mini_batch"):
            raise ValueError("D3GraspPPO normalises advantages over the acting samples of the whole batch")
        super().__init__(actor, critic, storage, **kwargs)
        if reward_scale <= 0.0:
            raise ValueError(f"reward_scale must be > 0, got {reward_scale}")
        self.reward_scale = float(reward_scale)
        self.bound_loss_coef = float(bound_loss_coef)
        self.action_bound = float(action_bound)
        self.phase_names = tuple(phase_names)
        T, W = storage.num_transitions_per_env, storage.num_envs
        self.active = torch.ones(T, W, 1, dtype=torch.bool, device=self.device)
        self.phase_ids = torch.full((T, W), -1, dtype=torch.long, device=self.device)
        self._advantages = torch.zeros(T, W, 1, device=self.device)
        # Set by the runner during the critic's warm-up: the actor's weights and its observation
        # normaliser both stay as they are, so the critic fits the values of one fixed policy.
        self.actor_frozen = False
        self.diagnostics: dict[str, float] = {}

    # ---------------------------------------------------------------------------- rollout
    def record_step(self, active: torch.Tensor | None, phase: torch.Tensor | None) -> None:
        """Whether each world's coming action takes effect, and the phase it acts in (``None``: all
        act, phase unknown). Call before ``act`` for the same step."""
        i = self.storage.step
        self.active[i, :, 0] = True if active is None else active.to(self.device, torch.bool)
        self.phase_ids[i] = -1 if phase is None else phase.to(self.device, torch.long)

    def process_env_step(self, obs: Any, rewards: torch.Tensor, dones: torch.Tensor, extras: dict) -> None:
        super().process_env_step(obs, rewards * self.reward_scale, dones, extras)

    def compute_returns(self, obs: Any) -> None:
        super().compute_returns(obs)
        st = self.storage
        # Written into a buffer made outside inference mode (the runner computes returns inside it):
        # the diagnostics and the update multiply the advantages into tensors that need gradients.
        self._advantages.copy_(masked_normalise(st.returns - st.values, self.active))
        st.advantages = self._advantages

    # ---------------------------------------------------------------------------- diagnostics
    def _world_batch(self, a: int, b: int) -> tuple[Any, torch.Tensor]:
        """Worlds ``a:b`` of the storage as ``(batch, active mask)``, laid out as the update's batches
        are (rsl-rl's trajectory generator run on a view of these worlds only, when recurrent)."""
        st = self.storage
        if self.actor.is_recurrent:
            part = SimpleNamespace(
                training_type=st.training_type,
                num_envs=b - a,
                observations=st.observations[:, a:b],
                dones=st.dones[:, a:b],
                actions=st.actions[:, a:b],
                values=st.values[:, a:b],
                advantages=st.advantages[:, a:b],
                returns=st.returns[:, a:b],
                actions_log_prob=st.actions_log_prob[:, a:b],
                distribution_params=tuple(p[:, a:b] for p in st.distribution_params),
                saved_hidden_state_a=_slice_hidden(st.saved_hidden_state_a, a, b),
                saved_hidden_state_c=_slice_hidden(st.saved_hidden_state_c, a, b),
            )
            (batch,) = RolloutStorage.recurrent_mini_batch_generator(part, 1, 1)  # type: ignore[arg-type]
            return batch, self.active[:, a:b]
        batch = RolloutStorage.Batch(
            observations=st.observations[:, a:b].flatten(0, 1),
            actions=st.actions[:, a:b].flatten(0, 1),
            advantages=st.advantages[:, a:b].flatten(0, 1),
            hidden_states=(None, None),
        )
        return batch, self.active[:, a:b].flatten(0, 1)

    def _world_halves(self) -> Iterator[tuple[Any, torch.Tensor] | None]:
        """The storage's two halves of the worlds (indices below ``W // 2`` and the rest) as
        ``(batch, active mask)``, or ``None`` for an empty half (a rank of one world: every rank must
        take part in the same all-reduces)."""
        h = self.storage.num_envs // 2
        for a, b in ((0, h), (h, self.storage.num_envs)):
            yield None if b == a else self._world_batch(a, b)

    @contextlib.contextmanager
    def _actor_gradients(self) -> Iterator[None]:
        """Gradients on, for every actor parameter: they may be frozen (the critic's warm-up), and the
        policy gradient is measured all the same. Each parameter's flag is restored after."""
        flags = [p.requires_grad for p in self.actor.parameters()]
        for p in self.actor.parameters():
            p.requires_grad_(True)
        try:
            with torch.enable_grad():
                yield
        finally:
            for p, f in zip(self.actor.parameters(), flags, strict=True):
                p.requires_grad_(f)

    def _half_gradient(self, batch: Any, active: torch.Tensor) -> torch.Tensor:
        """Flat gradient, over the actor's parameters, of ``-sum A log pi(a)`` on the acting samples of
        one half: the policy loss's gradient at the rollout's parameters (ratio 1: the clip is inactive)."""
        params = list(self.actor.parameters())
        self.actor(
            batch.observations, masks=batch.masks, hidden_state=batch.hidden_states[0], stochastic_output=True
        )
        logp = self.actor.get_output_log_prob(batch.actions)
        adv = batch.advantages.squeeze(-1)
        loss = -(adv * logp * active.squeeze(-1).to(logp.dtype)).sum()
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        return torch.cat(
            [
                (torch.zeros_like(p) if g is None else g).reshape(-1)
                for p, g in zip(params, grads, strict=True)
            ]
        )

    def diagnose(self) -> dict[str, float]:
        """The update's diagnostics (module docstring), pooled over the ranks; also kept in
        ``self.diagnostics``. Call after ``compute_returns`` and before ``update``."""
        st = self.storage
        out: dict[str, float] = {}
        episodes = st.dones.sum().to(torch.float64).reshape(1)
        groups = [torch.ones_like(self.phase_ids, dtype=torch.bool)] + [
            self.phase_ids == i for i in range(len(self.phase_names))
        ]
        sums = torch.stack([variance_sums(st.returns[g], st.values[g]) for g in groups])
        with self._actor_gradients():
            n = sum(p.numel() for p in self.actor.parameters())
            halves = [
                torch.zeros(n, device=self.device) if half is None else self._half_gradient(*half)
                for half in self._world_halves()
            ]
        if self.is_multi_gpu:
            torch.distributed.all_reduce(episodes)
            torch.distributed.all_reduce(sums)
            for g in halves:
                torch.distributed.all_reduce(g)
        out["episodes_per_update"] = float(episodes[0])
        out["explained_variance"] = explained_variance_from_sums(sums[0])
        for i, name in enumerate(self.phase_names):
            if float(sums[1 + i, 0]) > 0:  # a phase the episodes do not have (training's release) is left out
                out[f"explained_variance_{name}"] = explained_variance_from_sums(sums[1 + i])
        out["grad_cosine_split_half"] = flat_cosine(*halves)
        self.diagnostics = out
        return out

    def world_gradients(self) -> torch.Tensor:
        """This rank's per-world policy-loss gradients, ``(W, n_params)``: row ``w`` is the flat
        gradient of ``-sum A log pi(a)`` over world ``w``'s acting samples (about one episode per
        world in a whole-episode rollout), at the rollout's parameters. Rows of any set of worlds sum to that
        set's gradient, so the split-half cosine of any split follows from their Gram matrix
        (d3grasp.train.gradient_noise). Call after ``compute_returns``; nothing is updated."""
        with self._actor_gradients():
            rows = [self._half_gradient(*self._world_batch(w, w + 1)) for w in range(self.storage.num_envs)]
        return torch.stack(rows)

    # ---------------------------------------------------------------------------- update
    def update(self) -> dict[str, float]:
        """PPO epochs over the stored rollout: clipped surrogate averaged over the acting samples,
        value loss (optionally clipped), bound loss on the action mean, entropy bonus."""
        totals = {"value": 0.0, "surrogate": 0.0, "entropy": 0.0, "bound": 0.0}
        st = self.storage
        recurrent = self.actor.is_recurrent or self.critic.is_recurrent
        # The generators do not know the mask: it travels in the advantages' place as a second pass
        # of the same generator over a storage whose advantages hold the mask (same order).
        if recurrent:
            batches = st.recurrent_mini_batch_generator(self.num_mini_batches, self.num_learning_epochs)
            masks = self._mask_batches()
        else:
            batches, masks = self._flat_batches()
        updates = 0
        for batch, active in zip(batches, masks, strict=True):
            active = active.squeeze(-1).to(torch.float32)
            n_active = active.sum().clamp(min=1.0)
            self.actor(
                batch.observations,
                masks=batch.masks,
                hidden_state=batch.hidden_states[0],
                stochastic_output=True,
            )
            logp = self.actor.get_output_log_prob(batch.actions)
            mean = self.actor.output_mean
            entropy = self.actor.output_entropy
            values = self.critic(batch.observations, masks=batch.masks, hidden_state=batch.hidden_states[1])
            self._adapt_learning_rate(batch)

            adv = batch.advantages.squeeze(-1)
            ratio = torch.exp(logp - batch.old_actions_log_prob.squeeze(-1))
            surrogate = torch.max(
                -adv * ratio, -adv * ratio.clamp(1.0 - self.clip_param, 1.0 + self.clip_param)
            )
            surrogate_loss = (surrogate * active).sum() / n_active
            if self.use_clipped_value_loss:
                clipped = batch.values + (values - batch.values).clamp(-self.clip_param, self.clip_param)
                value_loss = torch.max(
                    (values - batch.returns).pow(2), (clipped - batch.returns).pow(2)
                ).mean()
            else:
                value_loss = (batch.returns - values).pow(2).mean()
            bound_loss = torch.relu(mean.abs() - self.action_bound).pow(2).sum(-1).mean()
            loss = (
                surrogate_loss
                + self.value_loss_coef * value_loss
                + self.bound_loss_coef * bound_loss
                - self.entropy_coef * entropy.mean()
            )
            self.optimizer.zero_grad()
            loss.backward()
            if self.is_multi_gpu:
                self.reduce_parameters()
            torch.nn.utils.clip_grad_norm_(self.actor.parameters(), self.max_grad_norm)
            torch.nn.utils.clip_grad_norm_(self.critic.parameters(), self.max_grad_norm)
            self.optimizer.step()
            totals["value"] += value_loss.item()
            totals["surrogate"] += surrogate_loss.item()
            totals["entropy"] += entropy.mean().item()
            totals["bound"] += bound_loss.item()
            updates += 1

        obs = st.observations.flatten(0, 1)
        if not self.actor_frozen:
            self.actor.update_normalization(obs)
        self.critic.update_normalization(obs)
        st.clear()
        return {k: v / max(updates, 1) for k, v in totals.items()}

    def _mask_batches(self) -> Iterator[torch.Tensor]:
        """The acting mask of each recurrent mini-batch, in the generator's order (worlds in
        ``num_mini_batches`` consecutive blocks, every epoch)."""
        size = self.storage.num_envs // self.num_mini_batches
        for _ in range(self.num_learning_epochs):
            for i in range(self.num_mini_batches):
                yield self.active[:, i * size : (i + 1) * size]

    def _flat_batches(self) -> tuple[Iterator[Any], Iterator[torch.Tensor]]:
        """Shuffled flat mini-batches with their acting masks (feed-forward actor and critic)."""
        st = self.storage
        n = st.num_envs * st.num_transitions_per_env
        size = n // self.num_mini_batches
        obs = st.observations.flatten(0, 1)
        flat = {
            "actions": st.actions.flatten(0, 1),
            "values": st.values.flatten(0, 1),
            "returns": st.returns.flatten(0, 1),
            "advantages": st.advantages.flatten(0, 1),
            "old_actions_log_prob": st.actions_log_prob.flatten(0, 1),
        }
        active = self.active.flatten(0, 1)
        batches, masks = [], []
        for _ in range(self.num_learning_epochs):
            order = torch.randperm(size * self.num_mini_batches, device=self.device)
            for i in range(self.num_mini_batches):
                idx = order[i * size : (i + 1) * size]
                batches.append(
                    RolloutStorage.Batch(
                        observations=obs[idx],
                        hidden_states=(None, None),
                        masks=None,
                        old_distribution_params=tuple(p.flatten(0, 1)[idx] for p in st.distribution_params),
                        **{k: v[idx] for k, v in flat.items()},
                    )
                )
                masks.append(active[idx])
        return iter(batches), iter(masks)

    def _adapt_learning_rate(self, batch: Any) -> None:
        """rsl-rl's adaptive schedule (KL against ``desired_kl``), when configured."""
        if self.desired_kl is None or self.schedule != "adaptive":
            return
        with torch.inference_mode():
            kl = self.actor.get_kl_divergence(
                batch.old_distribution_params, self.actor.output_distribution_params
            )
            kl_mean = kl.mean()
            if self.is_multi_gpu:
                torch.distributed.all_reduce(kl_mean)
                kl_mean /= self.gpu_world_size
            if kl_mean > self.desired_kl * 2.0:
                self.learning_rate = max(1e-5, self.learning_rate / 1.5)
            elif 0.0 < kl_mean < self.desired_kl / 2.0:
                self.learning_rate = min(1e-2, self.learning_rate * 1.5)
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate
