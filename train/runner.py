"""rsl-rl's on-policy runner extended for d3grasp: CPU multi-process, safe checkpoints, grasp metrics.

What ``D3GraspRunner`` changes in rsl-rl 5.5.1's ``OnPolicyRunner`` and why:

- Distributed training: rsl-rl initialises NCCL and requires ``cuda:<local_rank>``. Here CPU ranks use
  gloo (one process per core, each simulating its own worlds) and CUDA ranks NCCL, and each rank's
  gradient is weighed by its share of the worlds (``train/distributed.py``).
- Checkpoints are written atomically (temp file in the same folder, fsync, ``os.replace``) and carry
  the task name and observation sizes, so loading a checkpoint of another task fails with a clear
  message before any weights are touched. SIGINT/SIGTERM stop training at the next environment step
  and save a checkpoint of the last completed update; a hard kill leaves the previous checkpoint
  intact.
- The iteration counter in a checkpoint is the number of *completed* iterations, and resuming starts
  at that number (rsl-rl stores the index of the last iteration and repeats it on resume).
- Per-iteration timings (simulation vs policy vs update) and grasp outcomes from the environment's
  ``extras["episodes"]`` (success per object kind, size bin and grasp type, summed over ranks) go to
  TensorBoard next to rsl-rl's own scalars (``train/run_log.py``).
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from typing import Any

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")  # rsl_rl imports GitPython; a git binary is optional

import torch  # noqa: E402
from d3grasp.train import distributed  # noqa: E402
from d3grasp.train.run_log import EpisodeStats, IterationTiming, TrainingProgress, format_diagnostics  # noqa: E402
from d3grasp.train.stop_flag import StopFlag  # noqa: E402
from rsl_rl.runners import OnPolicyRunner  # noqa: E402
from rsl_rl.utils import check_nan  # noqa: E402

from d3grasp.envs import close_env  # noqa: E402
from d3grasp.envs.config import policy_interface  # noqa: E402
from d3grasp.policies.checkpoint import (  # noqa: E402  (re-exported: the runner's checkpoint API)
    CheckpointError,
    atomic_torch_save,
    check_fits,
    checkpoint_iteration,
    latest_checkpoint,
    observation_sizes,
    read_checkpoint,
)

__all__ = [
    "CheckpointError",
    "D3GraspRunner",
    "atomic_torch_save",
    "checkpoint_iteration",
    "latest_checkpoint",
    "read_checkpoint",
]


def scale_actor_output(actor: torch.nn.Module, scale: float, num_actions: int) -> None:
    """Multiply the action-mean rows of the actor's last linear layer by ``scale`` and zero their bias.

    With a residual action space the zero action is the rule-based controller; a freshly initialised
    network instead outputs an O(0.3) function of its inputs that jitters from step to step, i.e. the
    baseline plus noise the grasp cannot stand. Scaling the output layer (0.01, the usual choice for
    policy heads) starts the deterministic policy at the baseline; training grows the residual. Rows
    beyond ``num_actions`` (a state-dependent std) are left alone. Applied to fresh runs; a resumed run
    loads its weights over it.
    """
    linears = [m for m in actor.modules() if isinstance(m, torch.nn.Linear)]
    if not linears:
        raise ValueError("actor has no linear layer to scale")
    last = linears[-1]
    with torch.no_grad():
        last.weight[:num_actions] *= scale
        last.bias[:num_actions] = 0.0


class D3GraspRunner(OnPolicyRunner):
    """rsl-rl ``OnPolicyRunner`` with CPU (gloo) multi-process training, atomic checkpoints that
    know their task, a clean stop on SIGINT/SIGTERM, and grasp-outcome logging (module docstring)."""

    def __init__(
        self,
        env: Any,
        train_cfg: dict[str, Any],
        log_dir: str | os.PathLike[str] | None = None,
        device: str = "cpu",
        task_name: str | None = None,
        env_builder: Callable[[int], Any] | None = None,
    ) -> None:
        self.task_name = task_name if task_name is not None else train_cfg.get("task")
        if train_cfg.get("num_steps_per_env") == "episode":
            # Whole episodes per update (the task config's default): rollouts as long as the episode.
            train_cfg["num_steps_per_env"] = int(env.max_episode_length)
        # draw index -> a fresh environment with other objects (``resample_objects_every``)
        self.env_builder = env_builder
        super().__init__(env, train_cfg, None if log_dir is None else str(log_dir), device)
        self.log_dir = None if log_dir is None else str(log_dir)
        if self.gpu_global_rank != 0:
            self.log_dir = None
        self.timings: list[IterationTiming] = []
        self.progress = TrainingProgress()
        self.episode_stats = EpisodeStats()
        self.stop_flag = StopFlag()
        self.logger._store_code_state = self._safe_store_code_state  # type: ignore[method-assign]
        scale = train_cfg.get("actor_output_init_scale")
        if scale is not None:
            scale_actor_output(self.alg.actor, float(scale), int(env.num_actions))
        # Ranks may hold different numbers of worlds (--rank_num_envs): count the steps of all of them.
        # rsl-rl's logger counts num_envs x world size; its per-world buffers are already allocated.
        # Once here, not per learn(): a second learn() would weigh the gradients twice.
        self.worlds_all_ranks = int(distributed.sum_over_ranks(env.num_envs, self.ranks, self.device))
        self.logger.num_envs, self.logger.gpu_world_size = self.worlds_all_ranks, 1
        if self.is_distributed:
            weight = env.num_envs * self.gpu_world_size / self.worlds_all_ranks
            distributed.pool_rank_gradients(self.alg, weight)

    def _configure_multi_gpu(self) -> None:
        """Called by rsl-rl's ``__init__``: its ranks, with gloo for CPU ranks (``train/distributed.py``)."""
        self.ranks = r = distributed.init_ranks(self.device)
        self.gpu_world_size, self.gpu_local_rank = r.world_size, r.local_rank
        self.gpu_global_rank = r.global_rank
        self.is_distributed = r.distributed
        self.cfg["multi_gpu"] = (
            {"global_rank": r.global_rank, "local_rank": r.local_rank, "world_size": r.world_size}
            if r.distributed
            else None
        )

    # ----------------------------------------------------------------- training loop
    def learn(self, num_learning_iterations: int, init_at_random_ep_len: bool = False) -> None:
        """Run ``num_learning_iterations`` PPO iterations after the ``current_learning_iteration``
        already completed; stops early (saving) on SIGINT/SIGTERM."""
        env = self.env
        if init_at_random_ep_len:
            env.episode_length_buf = torch.randint_like(
                env.episode_length_buf, high=int(env.max_episode_length)
            )
        obs = env.get_observations().to(self.device)
        self.alg.train_mode()
        if self.is_distributed:
            self.alg.broadcast_parameters()  # identical initial weights on every rank
        self.logger.init_logging_writer()

        steps = int(self.cfg["num_steps_per_env"])
        start_it = self.current_learning_iteration
        total_it = start_it + num_learning_iterations
        nan_check = self.cfg.get("check_for_nan", True)
        critic_warmup = int(self.cfg.get("critic_warmup_iterations") or 0)
        self._saved_at = -1
        t_learn = time.perf_counter()
        wall_before = self.progress.wall_clock_s
        with self.stop_flag.installed() as stop:
            for it in range(start_it, total_it):
                t_start = time.perf_counter()
                obs, sim_s, interrupted = self._collect_rollout(env, obs, steps, stop, nan_check)
                if interrupted:
                    break
                t_rollout = time.perf_counter()
                with torch.inference_mode():
                    self.alg.compute_returns(obs)
                diagnostics = self.alg.diagnose() if hasattr(self.alg, "diagnose") else {}
                self.alg.actor_frozen = it < critic_warmup  # the actor's normaliser too (D3GraspPPO)
                with self._actor_frozen(it < critic_warmup):
                    loss_dict = self.alg.update()
                t_end = time.perf_counter()
                self.current_learning_iteration = it + 1

                timing = IterationTiming(
                    iteration=it,
                    sim_s=sim_s,
                    rollout_s=t_rollout - t_start,
                    update_s=t_end - t_rollout,
                    env_steps=steps * self.worlds_all_ranks,
                )
                self._count_iteration(timing, wall_before + (t_end - t_learn))
                self._log_iteration(it, start_it, total_it, timing, loss_dict, diagnostics)
                stop_now, env, obs = self._end_iteration(total_it, stop.requested, env, obs)
                if stop_now:
                    break
        self._end_run()

    def _collect_rollout(
        self, env: Any, obs: Any, steps: int, stop: Any = None, nan_check: bool = True
    ) -> tuple[Any, float, bool]:
        """``steps`` environment steps into the algorithm's storage. Returns (the last observation,
        seconds inside ``env.step``, whether a stop request cut the rollout short)."""
        sim_s = 0.0
        with torch.inference_mode():
            for _ in range(steps):
                if stop is not None and stop.requested and not self.is_distributed:
                    return obs, sim_s, True  # weights are those of the last update: save them
                self._record_step(env)
                actions = self.alg.act(obs)
                t_sim = time.perf_counter()
                obs, rewards, dones, extras = env.step(actions.to(env.device))
                sim_s += time.perf_counter() - t_sim
                if nan_check:
                    check_nan(obs, rewards, dones)
                obs, rewards, dones = obs.to(self.device), rewards.to(self.device), dones.to(self.device)
                self.alg.process_env_step(obs, rewards, dones, extras)
                self.logger.process_env_step(rewards, dones, extras, None)
                self.episode_stats.add(extras.get("episodes", ()))
        return obs, sim_s, False

    def probe_world_gradients(
        self, rollouts: int, progress: Callable[[int], None] | None = None
    ) -> torch.Tensor:
        """Per-world policy-loss gradients of ``rollouts`` whole-episode rollouts at the loaded
        parameters, nothing updated (weights and normalisers stay): ``(rollouts x worlds, n_params)``
        for this rank's worlds (``D3GraspPPO.world_gradients``). For d3grasp.train.gradient_noise."""
        env, steps = self.env, int(self.cfg["num_steps_per_env"])
        obs = env.get_observations().to(self.device)
        self.alg.train_mode()  # sampled actions, as in training
        rows = []
        for k in range(rollouts):
            obs, _, _ = self._collect_rollout(env, obs, steps)
            with torch.inference_mode():
                self.alg.compute_returns(obs)
            rows.append(self.alg.world_gradients())
            self.alg.storage.clear()
            if progress is not None:
                progress(k + 1)
        return torch.cat(rows)

    def _count_iteration(self, timing: IterationTiming, wall_clock_s: float) -> None:
        """Record a completed iteration's timing and the run's cumulative env-steps and wall-clock."""
        self.timings.append(timing)
        self.progress.env_steps += timing.env_steps
        self.progress.wall_clock_s = wall_clock_s

    def _end_iteration(
        self, total_it: int, stop_requested: bool, env: Any, obs: Any
    ) -> tuple[bool, Any, Any]:
        """After an iteration: a checkpoint every ``save_interval``, the ranks' agreement to stop, and
        a new draw of objects every ``resample_objects_every`` iterations. Returns (stop, the
        environment, its observation): a new draw's and its first, or ``env`` and ``obs`` as given."""
        done = self.current_learning_iteration
        if self.log_dir is not None and done % int(self.cfg["save_interval"]) == 0:
            self.save(os.path.join(self.log_dir, f"model_{done}.pt"))
            self._saved_at = done
        if distributed.agree_to_stop(stop_requested, self.ranks, self.device):
            return True, env, obs
        every = int(self.cfg.get("resample_objects_every") or 0)
        if every and self.env_builder is not None and done % every == 0 and done < total_it:
            env = self._resample_objects(done // every)
            return False, env, env.get_observations().to(self.device)
        return False, env, obs

    def _end_run(self) -> None:
        """On rank 0: the last completed iteration's checkpoint (unless the interval wrote it),
        ``timings.json`` and the logger closed."""
        if self.log_dir is None:
            return
        if self._saved_at != self.current_learning_iteration:
            self.save(os.path.join(self.log_dir, f"model_{self.current_learning_iteration}.pt"))
        with open(os.path.join(self.log_dir, "timings.json"), "w", encoding="utf-8") as f:
            import json

            json.dump([asdict(t) for t in self.timings], f, indent=1)
        self.logger.stop_logging_writer()
        if self.logger.writer is not None and hasattr(self.logger.writer, "close"):
            self.logger.writer.close()

    def _resample_objects(self, draw: int) -> Any:
        """Replace the environment by ``env_builder(draw)``: the same task and world count holding
        other objects (a Newton model cannot swap an object's geometry in place).

        Why: without it a run's 2 x 20 worlds keep their 40 objects for the whole run, and a new draw
        dropped the training return from ~85 to ~25 (measured; redrawing every 50 iterations did not by
        itself raise the held-out success rate). Episodes in progress are abandoned: recurrent states
        and the logger's running episode sums restart.
        """
        old = self.env
        close_env(old)
        env = self.env_builder(draw)  # type: ignore[misc]
        if env.num_envs != old.num_envs or env.num_actions != old.num_actions:
            raise ValueError("env_builder must keep the number of worlds and actions")
        self.env = env
        self.alg.actor.reset()
        self.alg.critic.reset()
        for name in ("cur_reward_sum", "cur_episode_length"):
            buf = getattr(self.logger, name, None)
            if isinstance(buf, torch.Tensor):
                buf.zero_()
        return env

    @contextlib.contextmanager
    def _actor_frozen(self, frozen: bool) -> Iterator[None]:
        """During the critic's warm-up only the critic learns: the actor's parameters (its action std
        included) get no gradient, so Adam leaves them as they are."""
        if not frozen:
            yield
            return
        params = [p for p in self.alg.actor.parameters() if p.requires_grad]
        for param in params:
            param.requires_grad_(False)
        try:
            yield
        finally:
            for param in params:
                param.requires_grad_(True)

    def _record_step(self, env: Any) -> None:
        """Tell the algorithm which worlds' coming actions take effect and in which phase (for its
        masks and the per-phase diagnostics); environments without these report nothing."""
        record = getattr(self.alg, "record_step", None)
        if record is None:
            return
        active = env.action_takes_effect() if hasattr(env, "action_takes_effect") else None
        phase = env.phase_of(env.episode_length_buf) if hasattr(env, "phase_of") else None
        record(active, phase)

    def _log_iteration(
        self,
        it: int,
        start_it: int,
        total_it: int,
        timing: IterationTiming,
        loss_dict: dict[str, float],
        diagnostics: dict[str, float] | None = None,
    ) -> None:
        if self.is_distributed:
            self.episode_stats.all_reduce()  # every rank takes part, rank 0 writes
        self.logger.log(
            it=it,
            start_it=start_it,
            total_it=total_it,
            collect_time=timing.rollout_s,
            learn_time=timing.update_s,
            loss_dict=loss_dict,
            learning_rate=self.alg.learning_rate,
            action_std=self.alg.get_policy().output_std,
            rnd_weight=None,
        )
        writer = self.logger.writer
        if writer is not None:
            writer.add_scalar("Perf/env_steps_per_s", timing.env_steps / max(timing.total_s, 1e-9), it)
            writer.add_scalar("Perf/simulation_time", timing.sim_s, it)
            writer.add_scalar("Perf/simulation_share", timing.sim_s / max(timing.total_s, 1e-9), it)
            writer.add_scalar("Perf/update_share", timing.update_s / max(timing.total_s, 1e-9), it)
            # Cumulative, over resumed runs too: the curves' env-steps and wall-clock axes.
            writer.add_scalar("Progress/env_steps", self.progress.env_steps, it)
            writer.add_scalar("Progress/wall_clock_s", self.progress.wall_clock_s, it)
            for key, value in self.episode_stats.rates().items():
                writer.add_scalar(key, value, it)
            for key, value in (diagnostics or {}).items():
                writer.add_scalar(f"Diagnostics/{key}", value, it)
        if diagnostics and self.gpu_global_rank == 0:
            print(format_diagnostics(diagnostics))
        self.episode_stats.clear()

    def _safe_store_code_state(self) -> list[str]:
        """rsl-rl records ``git diff`` of the code; without a git binary that raises: skip it then."""
        try:
            return type(self.logger)._store_code_state(self.logger)
        except Exception as exc:  # GitPython raises its own command/exec errors
            print(f"[d3grasp] not storing the code state (git unavailable: {type(exc).__name__})")
            return []

    # ----------------------------------------------------------------- checkpoints
    def observation_sizes(self) -> dict[str, int]:
        return observation_sizes(self.env.get_observations())

    def env_policy_interface(self) -> dict[str, Any] | None:
        """How this env turns actions into joint targets (``d3grasp.envs.config.POLICY_INTERFACE``)."""
        cfg = getattr(self.env, "cfg", None)
        return policy_interface(cfg) if cfg is not None else None

    def checkpoint_infos(self) -> dict[str, Any]:
        """What a checkpoint must match to be loaded: task, observation sizes, action count, models,
        and the settings that map its actions to joint targets."""
        infos = {
            "task": self.task_name,
            "obs_sizes": self.observation_sizes(),
            "obs_groups": {k: list(v) for k, v in self.cfg["obs_groups"].items()},
            "num_actions": int(self.env.num_actions),
            "actor": self.cfg["actor"],
            "critic": self.cfg["critic"],
        }
        interface = self.env_policy_interface()
        if interface is not None:
            infos["policy_interface"] = interface
        return infos

    def extra_checkpoint_state(self) -> dict[str, Any]:
        """What a subclass's learning loop adds to each checkpoint beside rsl-rl's entries (none here)."""
        return {}

    def restore_checkpoint_state(self, data: dict[str, Any], load_cfg: dict[str, Any]) -> None:
        """Restore what ``extra_checkpoint_state`` saved (nothing here)."""

    def save(self, path: str, infos: dict | None = None) -> None:
        """Atomically save models, optimizer, completed-iteration count and ``checkpoint_infos()``."""
        data = self.alg.save()
        data["iter"] = self.current_learning_iteration
        data["progress"] = asdict(self.progress)
        data["infos"] = {**self.checkpoint_infos(), **(infos or {})}
        data.update(self.extra_checkpoint_state())
        atomic_torch_save(data, path)
        self.logger.save_model(path, self.current_learning_iteration)

    def check_compatible(self, infos: dict[str, Any] | None, path: str, models: tuple[str, ...]) -> None:
        """Raise ``CheckpointError`` if the checkpoint does not fit this runner's environment."""
        if not infos or "obs_sizes" not in infos:
            return  # a foreign rsl-rl checkpoint: load_state_dict will judge the shapes
        check_fits(
            infos,
            path,
            task=self.task_name,
            obs_sizes=self.observation_sizes(),
            obs_groups=self.cfg["obs_groups"],
            num_actions=int(self.env.num_actions),
            policy_interface=self.env_policy_interface(),
            models=models,
        )

    def load(
        self,
        path: str,
        load_cfg: dict | None = None,
        strict: bool = True,
        map_location: str | None = None,
        *,
        trust: bool = False,
    ) -> dict:
        """Load after checking the checkpoint fits this task; ``CheckpointError`` otherwise. Read as
        data through ``read_checkpoint`` (rsl-rl's own load unpickles anything); ``trust``: also a
        file that names code (``--trust-checkpoint``)."""
        data = read_checkpoint(path, map_location=map_location or str(self.device), trust=trust)
        load_cfg = load_cfg or {"actor": True, "critic": True, "optimizer": True, "iteration": True}
        models = tuple(m for m in ("actor", "critic") if load_cfg.get(m))
        self.check_compatible(data.get("infos"), str(path), models)
        try:
            self.alg.load(data, load_cfg, strict)
        except (RuntimeError, KeyError, ValueError) as exc:
            first = str(exc).strip().splitlines()[0]
            raise CheckpointError(
                f"checkpoint {path} does not match the configured networks: {first}"
            ) from None
        self.restore_checkpoint_state(data, load_cfg)
        if load_cfg.get("iteration"):
            self.current_learning_iteration = int(data["iter"])
            self.progress = TrainingProgress(**data.get("progress", {}))
        return data.get("infos") or {}
