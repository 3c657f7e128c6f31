"""DAgger: the privileged teacher distilled into the policy that reads only touch and proprioception.

Under camera perception the grasp is planned at the camera's estimate of the object's pose. The
teacher (``d3grasp.policies.teacher``) knows the true pose and moves the wrist onto the grasp at it;
the student is the task's recurrent actor (rsl-rl ``RNNModel``), which reads the policy group only:
touch, proprioception, the clock and the palm command relative to the planned grasp. It can find the
camera's error only through what it touches.

One iteration (Ross et al. 2011, DAgger):

1. Roll out one episode length in every world. Each episode is driven by the teacher with probability
   ``beta`` (drawn per world when its episode starts; ``beta`` falls linearly from 1 to 0 over
   ``beta_iterations``) and by the student's deterministic action otherwise. Either way the teacher
   labels every step with its action.
2. Keep the last ``buffer_rollouts`` rollouts (the aggregated data set, bounded in memory) and fit the
   student to the labels by mean-squared error over the steps whose action takes effect
   (``env.action_takes_effect``), the LSTM run over each rollout from its recorded initial state with
   its state reset where an episode ended.

The runner is ``D3GraspRunner``: the same run folders, checkpoints carrying the policy contract (so
``d3grasp-eval --checkpoint`` and PPO fine-tuning with ``d3grasp-train --resume`` load them), object
redraws, clean stops and ranks (gradients and normaliser statistics are averaged over ranks). Success
rates are logged for the student's episodes only (``Success/*``) and the teacher's apart
(``Distill/teacher_*``).
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Any

import torch
from d3grasp.train.run_log import EpisodeStats, IterationTiming
from d3grasp.train.runner import D3GraspRunner
from rsl_rl.models import MLPModel
from tensordict import TensorDict

from d3grasp.envs.mdp.actions import WRIST_ACTIONS
from d3grasp.policies.teacher import TEACHER, PoseTeacher

# The checkpoint's entry for the student's optimiser state (PPO's own stays under rsl-rl's key).
STUDENT_OPTIMIZER_KEY = "student_optimizer_state_dict"

__all__ = ["DaggerRunner", "Rollout", "masked_mse", "sequence_means"]


@dataclass
class Rollout:
    """One iteration's data: observations (T, W, ...), teacher labels (T, W, A), the steps whose action
    takes effect (T, W), the episode ends after each step (T, W) and the LSTM state before step 0."""

    obs: TensorDict
    labels: torch.Tensor
    active: torch.Tensor
    dones: torch.Tensor
    h0: tuple[torch.Tensor, torch.Tensor]

    def worlds(self, idx: torch.Tensor) -> Rollout:
        return Rollout(
            self.obs[:, idx],
            self.labels[:, idx],
            self.active[:, idx],
            self.dones[:, idx],
            (self.h0[0][:, idx], self.h0[1][:, idx]),
        )


def sequence_means(
    actor: Any, obs: TensorDict, dones: torch.Tensor, h0: tuple[torch.Tensor, torch.Tensor]
) -> torch.Tensor:
    """(T, W, A) the recurrent actor's deterministic actions over a rollout, step by step as in the
    rollout itself: the LSTM state starts at ``h0`` and is zeroed after a step that ended an episode
    (what ``RNNModel.reset(dones)`` does when acting)."""
    latent = MLPModel.get_latent(actor, obs)  # the groups concatenated and normalised, no recurrence
    lstm = actor.rnn.rnn
    h, c = h0
    outs = []
    for t in range(latent.shape[0]):
        out, (h, c) = lstm(latent[t : t + 1], (h, c))
        outs.append(out[0])
        keep = (1.0 - dones[t].float()).view(1, -1, 1)
        h, c = h * keep, c * keep
    return actor.distribution.deterministic_output(actor.mlp(torch.stack(outs)))


def masked_mse(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the masked steps (mask (T, W)), averaged over the action dimensions."""
    m = mask.float().unsqueeze(-1)
    return ((pred - target) ** 2 * m).sum() / (m.sum() * pred.shape[-1]).clamp(min=1.0)


def _zero_state(actor: Any, num_envs: int, device: str) -> tuple[torch.Tensor, torch.Tensor]:
    lstm = actor.rnn.rnn
    shape = (lstm.num_layers, num_envs, lstm.hidden_size)
    return torch.zeros(shape, device=device), torch.zeros(shape, device=device)


class DaggerRunner(D3GraspRunner):
    """``D3GraspRunner`` whose ``learn`` distils the privileged teacher (module docstring). The runner
    config's ``distillation`` section holds the settings (d3grasp.train.configs)."""

    def __init__(self, env: Any, train_cfg: dict[str, Any], *args: Any, **kwargs: Any) -> None:
        super().__init__(env, train_cfg, *args, **kwargs)
        dcfg = self.cfg["distillation"]
        if dcfg.get("teacher") != TEACHER:
            raise ValueError(f"distillation.teacher must be '{TEACHER}', got {dcfg.get('teacher')!r}")
        rnn = getattr(getattr(self.alg.actor, "rnn", None), "rnn", None)
        if not isinstance(rnn, torch.nn.LSTM):
            raise ValueError("DAgger here trains an LSTM actor (actor.class_name RNNModel, rnn_type lstm)")
        PoseTeacher(env)  # a wrist and a residual action mode, or a one-line error now
        self.student_optimizer = torch.optim.Adam(
            self.alg.actor.parameters(), lr=float(dcfg["learning_rate"])
        )
        self.buffer: collections.deque[Rollout] = collections.deque(maxlen=int(dcfg["buffer_rollouts"]))
        self.teacher_stats = EpisodeStats()

    def extra_checkpoint_state(self) -> dict[str, Any]:
        """The student's Adam state, so a resumed DAgger run continues the same optimiser."""
        return {STUDENT_OPTIMIZER_KEY: self.student_optimizer.state_dict()}

    def restore_checkpoint_state(self, data: dict[str, Any], load_cfg: dict[str, Any]) -> None:
        """The student's Adam state where the checkpoint has one; a checkpoint written by PPO, or by
        DAgger before it saved the state, leaves a fresh Adam."""
        state = data.get(STUDENT_OPTIMIZER_KEY)
        if state is not None and load_cfg.get("optimizer"):
            self.student_optimizer.load_state_dict(state)
            # The moments carry over; the learning rate is this run's (load_state_dict restores the
            # saved one, which would silently override distillation.learning_rate).
            for group in self.student_optimizer.param_groups:
                group["lr"] = float(self.cfg["distillation"]["learning_rate"])

    def beta(self, iteration: int) -> float:
        """The teacher's share of the episodes at ``iteration``: 1 falling linearly to 0."""
        n = int(self.cfg["distillation"]["beta_iterations"])
        return max(0.0, 1.0 - iteration / n) if n > 0 else 0.0

    def learn(self, num_learning_iterations: int, init_at_random_ep_len: bool = False) -> None:
        env, actor = self.env, self.alg.actor
        steps = int(self.cfg["num_steps_per_env"])
        start_it = self.current_learning_iteration
        total_it = start_it + num_learning_iterations
        if self.is_distributed:
            self.alg.broadcast_parameters()
        self.logger.init_logging_writer()
        obs = env.get_observations().to(self.device)
        actor.reset()
        self._saved_at = -1
        t_learn = time.perf_counter()
        wall_before = self.progress.wall_clock_s
        # Which episodes the teacher drives: from torch's seeded generator (seed_everything, seed + rank).
        gen = torch.Generator().manual_seed(int(torch.randint(0, 2**31 - 1, (1,))))
        with self.stop_flag.installed() as stop:
            for it in range(start_it, total_it):
                t_start = time.perf_counter()
                beta = self.beta(it)
                rollout, obs, sim_s = self._collect(env, obs, steps, beta, gen)
                t_rollout = time.perf_counter()
                actor.update_normalization(rollout.obs.flatten(0, 1))  # averaged over ranks by rsl-rl
                self.buffer.append(rollout)
                loss, wrist_err = self._fit()
                t_end = time.perf_counter()
                self.current_learning_iteration = it + 1
                timing = IterationTiming(
                    it, sim_s, t_rollout - t_start, t_end - t_rollout, steps * self.worlds_all_ranks
                )
                self._count_iteration(timing, wall_before + (t_end - t_learn))
                self._log_distill(it, timing, beta, loss, wrist_err)
                stop_now, env, obs = self._end_iteration(total_it, stop.requested, env, obs)
                if stop_now:
                    break
        self._end_run()

    def _collect(
        self, env: Any, obs: TensorDict, steps: int, beta: float, gen: torch.Generator
    ) -> tuple[Rollout, TensorDict, float]:
        """One rollout of ``steps`` steps (the module docstring's step 1); returns it, the observation
        after its last step and the seconds spent in ``env.step``."""
        actor = self.alg.actor
        teacher = PoseTeacher(env)
        W = env.num_envs
        state = actor.get_hidden_state()
        h0 = _zero_state(actor, W, self.device) if state is None else (state[0].clone(), state[1].clone())
        by_teacher = torch.rand(W, generator=gen) < beta
        obs_seq, labels, active, dones_seq = [], [], [], []
        sim_s = 0.0
        with torch.no_grad():
            for _ in range(steps):
                act_mask = env.action_takes_effect().to(self.device)
                student = actor(obs)
                label = teacher.actions().to(self.device)
                action = torch.where(by_teacher[:, None].to(self.device), label, student)
                obs_seq.append(obs.clone())
                labels.append(label)
                active.append(act_mask)
                t0 = time.perf_counter()
                obs, _, dones, extras = env.step(action.to(env.device))
                sim_s += time.perf_counter() - t0
                obs, dones = obs.to(self.device), dones.to(self.device)
                actor.reset(dones)
                dones_seq.append(dones.clone())
                for ep in extras.get("episodes", ()):
                    (self.teacher_stats if bool(by_teacher[int(ep["env"])]) else self.episode_stats).add([ep])
                ended = dones.bool().cpu()
                if ended.any():
                    by_teacher[ended] = torch.rand(int(ended.sum()), generator=gen) < beta
        rollout = Rollout(
            obs=torch.stack(obs_seq),
            labels=torch.stack(labels),
            active=torch.stack(active),
            dones=torch.stack(dones_seq),
            h0=h0,
        )
        return rollout, obs, sim_s

    def _fit(self) -> tuple[float, float]:
        """Epochs of masked MSE over the buffered rollouts, in mini-batches of worlds; returns the
        mean loss and the mean absolute wrist error of the last epoch."""
        dcfg = self.cfg["distillation"]
        actor = self.alg.actor
        epochs, mini = int(dcfg["epochs"]), int(dcfg["mini_batches"])
        max_norm = float(dcfg["max_grad_norm"])
        losses, wrist_errs = [], []
        for epoch in range(epochs):
            for rollout in self.buffer:
                W = rollout.labels.shape[1]
                perm = torch.randperm(W)
                for idx in perm.chunk(min(mini, W)):
                    part = rollout.worlds(idx)
                    means = sequence_means(actor, part.obs, part.dones, part.h0)
                    loss = masked_mse(means, part.labels, part.active)
                    self.student_optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if self.is_distributed:
                        self.alg.reduce_parameters()
                    torch.nn.utils.clip_grad_norm_(actor.parameters(), max_norm)
                    self.student_optimizer.step()
                    if epoch == epochs - 1:
                        losses.append(float(loss.detach()))
                        with torch.no_grad():
                            wrist = slice(-WRIST_ACTIONS, None)
                            err = (means[..., wrist] - part.labels[..., wrist]).abs().mean(-1)
                            m = part.active.float()
                            wrist_errs.append(float((err * m).sum() / m.sum().clamp(min=1.0)))
        return sum(losses) / max(len(losses), 1), sum(wrist_errs) / max(len(wrist_errs), 1)

    def _log_distill(
        self, it: int, timing: IterationTiming, beta: float, loss: float, wrist_err: float
    ) -> None:
        if self.is_distributed:
            self.episode_stats.all_reduce()
            self.teacher_stats.all_reduce()
        student, teacher = self.episode_stats.rates(), self.teacher_stats.rates()
        writer = self.logger.writer
        if writer is not None:
            writer.add_scalar("Distill/loss", loss, it)
            writer.add_scalar("Distill/wrist_abs_error", wrist_err, it)
            writer.add_scalar("Distill/beta", beta, it)
            writer.add_scalar("Progress/env_steps", self.progress.env_steps, it)
            writer.add_scalar("Progress/wall_clock_s", self.progress.wall_clock_s, it)
            for key, value in student.items():
                writer.add_scalar(key, value, it)
            for key, value in teacher.items():
                writer.add_scalar("Distill/teacher_" + key.removeprefix("Success/"), value, it)
        if self.gpu_global_rank == 0:

            def rate(r: dict[str, float], m: str) -> str:
                n = int(r.get("Success/episodes", 0))
                return f"{r[f'Success/{m}/all']:.2f} ({n})" if n else "-"

            print(
                f"[distill] it {it + 1} beta {beta:.2f} loss {loss:.4f} wrist |err| {wrist_err:.3f} | "
                f"student s_lift {rate(student, 's_lift')} s_disturb {rate(student, 's_disturb')} | "
                f"teacher s_lift {rate(teacher, 's_lift')} | {timing.total_s:.0f} s",
                flush=True,
            )
        self.episode_stats.clear()
        self.teacher_stats.clear()
