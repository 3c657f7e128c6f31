"""rsl-rl 5.5 runner configuration of every registered task, in one place.

A task (``d3grasp.envs.registry``) names an environment config; this module pairs it with the
runner/PPO config that trains it. ``make_train_cfg(task)`` returns the plain dict rsl-rl 5.5's
``OnPolicyRunner`` reads (its 5.x schema: ``actor``/``critic`` model sections with their own
``obs_normalization`` and a ``distribution_cfg`` on the actor; 2.x-4.x keys such as ``policy`` or
``empirical_normalization`` raise errors there).

Why these hyper-parameters (docs/design.md, Training; Training from a delayed outcome): on a laptop
CPU a batch is small (~50 worlds x one episode), and rsl-rl's adaptive learning-rate schedule then
sees noisy KL estimates and drives the rate to its 1e-5 floor within a few dozen iterations, after
which nothing learns. A fixed rate of 1e-4 with 5 epochs x 4 mini-batches and clip 0.2 keeps the
per-update policy change bounded by the clip instead (with exploration noise 0.5 and no entropy
bonus, as the shipped policy was trained). The grasp's outcome is scored seconds after the fingers
close, so an update holds whole episodes, the discount is 1 and the end a true terminal
(d3grasp.train.ppo for the masks, the scaling and the bound loss). The recurrent actor (LSTM 128 ->
MLP [128, 64]) sees only what a real hand senses (touch, proprioception, phase clock); the critic MLP
reads the privileged group too (the asymmetric actor-critic of the paper) except in the Base /
BaseTactile ablations.
"""

from __future__ import annotations

import copy
from typing import Any

from d3grasp.envs.registry import DEFAULT_TASK, get_task
from d3grasp.vocabulary import PHASES

__all__ = ["DEFAULT_TASK", "experiment_name", "fit_mini_batches", "make_train_cfg", "set_cfg_value"]

# Shared by every task; per-task differences are applied in make_train_cfg.
_BASE_CFG: dict[str, Any] = {
    # Rollout length per world and iteration = the LSTM's truncated-BPTT window. "episode": the
    # environment's episode length, so every update holds whole episodes (~one per world) from every
    # phase. With 24-step rollouts ~70% of the worlds ended at the same step, a batch was mostly one
    # phase, ~9 episodes finished per update, and the LSTM never saw a grasp and its push in one window.
    "num_steps_per_env": "episode",
    "max_iterations": 1500,
    "save_interval": 50,
    # Rebuild the worlds with other objects every N iterations (0: never). A Newton model holds one
    # object per world for its lifetime, so 2 ranks x 20 worlds see 40 objects per draw; in a run that
    # kept its draw for hundreds of iterations each new draw dropped the training return from ~85 to
    # ~25 (redrawing every 50 iterations did not by itself raise the held-out success rate). A rebuild
    # costs ~10-20 s against ~7 min of 100 iterations.
    "resample_objects_every": 100,
    "check_for_nan": True,
    "logger": "tensorboard",
    "run_name": "",
    # Random initial episode lengths de-synchronise the worlds' phase schedules. Off by default: the
    # grasp episode is a scripted phase sequence, and starting a world mid-lift is not meaningful
    # physics. Worlds de-synchronise anyway through early terminations.
    "init_at_random_ep_len": False,
    "obs_groups": {"actor": ["policy"], "critic": ["policy", "privileged"]},
    # Scale of the actor's action-mean output layer at initialisation (None: rsl-rl's own): 0.01
    # starts the residual policy at the rule-based controller (d3grasp.train.runner.scale_actor_output).
    "actor_output_init_scale": 0.01,
    # PPO iterations at the start in which only the critic learns (0: none). The residual policy
    # starts at the rule-based controller, and the advantages of a critic that has not yet fitted
    # returns of -70 (no grasp) to +400 (held through the push) are noise. Measured: without warm-up the
    # training s_lift was 0.30-0.37 over iterations 20-50, with 30 warm-up iterations (and lr 1e-4,
    # std 0.15) 0.53-0.64; the decline came later all the same (docs/design.md, Fine-tuning the residual).
    # With whole-episode rollouts an iteration holds ~11x the samples of the 24-step ones these 20
    # iterations were measured with: 3 give the critic about as many samples.
    "critic_warmup_iterations": 3,
    "actor": {
        "class_name": "RNNModel",
        "rnn_type": "lstm",
        "rnn_hidden_dim": 128,
        "rnn_num_layers": 1,
        "hidden_dims": [128, 64],
        "activation": "elu",
        "obs_normalization": True,
        "distribution_cfg": {
            "class_name": "GaussianDistribution",
            # The low-pass synergy residual (residual_scale 0.1): per-step noise of 0.5 (0.05 rad) is
            # filtered to a jitter of ~0.02 rad, which leaves the rule's grasps intact; with the 0.4 rad
            # scale of earlier runs 0.5 broke most grasps (docs/design.md, Fine-tuning the residual).
            "init_std": 0.5,
            "std_type": "scalar",
        },
    },
    "critic": {
        "class_name": "MLPModel",
        "hidden_dims": [256, 128, 64],
        "activation": "elu",
        "obs_normalization": True,
    },
    "algorithm": {
        # rsl-rl's PPO with action-effect masks, scaled rewards, a bound loss and diagnostics
        # (d3grasp.train.ppo)
        "class_name": "d3grasp.train.ppo:D3GraspPPO",
        "learning_rate": 1.0e-4,
        "schedule": "fixed",  # adaptive collapses to its floor at CPU batch sizes (module docstring)
        "desired_kl": 0.01,  # only read by the adaptive schedule
        "num_learning_epochs": 5,
        "num_mini_batches": 4,
        "clip_param": 0.2,
        # The outcome (the scored push) comes 120-240 control steps after the fingers close. With
        # gamma 0.99 and lam 0.95 (gamma * lam)^k fell by e in ~17 steps, so grasp-phase advantages were
        # the critic's one-step errors. The horizon is fixed and the clock observed, so no discount is
        # needed (gamma 1); lam 0.99 keeps e^-1 of the outcome's credit 100 steps back (docs/design.md,
        # Training from a delayed outcome).
        "gamma": 1.0,
        "lam": 0.99,
        "value_loss_coef": 1.0,
        "entropy_coef": 0.0,  # the residual starts at the rule: no reward for widening the noise
        "max_grad_norm": 1.0,
        # The clip is in return units: 0.2 on returns of hundreds froze each sample's value after it had
        # moved 0.2. Returns are scaled (reward_scale) and the value loss is not clipped.
        "use_clipped_value_loss": False,
        "normalize_advantage_per_mini_batch": False,
        "optimizer": "adam",
        # Rewards x 0.01 for PPO: returns of -70 to +600 become O(1-10), the critic's range.
        "reward_scale": 0.01,
        # coef * relu(|mean| - 1)^2: an action mean past the environment's clamp gets no gradient from
        # the outcome (thumb means of +1.03 to +1.17 were measured); this brings it back.
        "bound_loss_coef": 10.0,
        "phase_names": list(PHASES),
    },
    # DAgger from the privileged teacher (d3grasp.train.distill) instead of PPO when "teacher" is set
    # (d3grasp-train --distill teacher). The teacher's share of the episodes falls from 1 to 0 over
    # beta_iterations; the last buffer_rollouts rollouts are refitted each iteration (the aggregated
    # data set, bounded); a supervised loss on a fixed target takes a larger rate than PPO's 1e-4.
    "distillation": {
        "teacher": None,
        "beta_iterations": 8,
        "buffer_rollouts": 4,
        "epochs": 2,
        "mini_batches": 2,
        "learning_rate": 1.0e-3,
        "max_grad_norm": 1.0,
    },
}


def experiment_name(task: str) -> str:
    """Log folder name of a task: ``D3Grasp-DexHand13-Mixed-v0`` -> ``d3grasp_dexhand13_mixed_v0``."""
    return task.lower().replace("-", "_")


def make_train_cfg(task: str = DEFAULT_TASK, **overrides: Any) -> dict[str, Any]:
    """The rsl-rl 5.5 runner config of a registered task (a fresh dict each call).

    ``overrides`` replace top-level keys; nested sections merge one level deep, e.g.
    ``make_train_cfg(task, num_steps_per_env=8, algorithm={"learning_rate": 1e-3})``.
    Raises ``UnknownTaskError`` for an unregistered task and ``ValueError`` for an unknown key.
    """
    spec = get_task(task)
    cfg = copy.deepcopy(_BASE_CFG)
    cfg["experiment_name"] = experiment_name(task)
    cfg["task"] = task
    # Symmetric ablations: the critic sees the actor's input only.
    cfg["obs_groups"]["critic"] = list(spec.critic_groups)
    for key, value in overrides.items():
        if key not in cfg:
            raise ValueError(f"unknown runner config key '{key}'; valid: {sorted(cfg)}")
        if isinstance(value, dict) and isinstance(cfg[key], dict) and key != "obs_groups":
            unknown = set(value) - set(cfg[key]) - {"distribution_cfg"}
            if key == "algorithm":
                unknown -= {"rnd_cfg", "symmetry_cfg", "grad_reduce_bucket_mb", "use_mixed_precision"}
            if unknown:
                raise ValueError(f"unknown '{key}' config keys {sorted(unknown)}; valid: {sorted(cfg[key])}")
            cfg[key].update(copy.deepcopy(value))
        else:
            cfg[key] = copy.deepcopy(value)
    return cfg


def set_cfg_value(cfg: dict[str, Any], dotted: str, value: Any) -> None:
    """Set ``cfg["a"]["b"]`` for ``dotted="a.b"``: the key must exist, so a typo fails (``ValueError``)
    instead of training with the default."""
    *path, last = dotted.split(".")
    node: Any = cfg
    for i, key in enumerate(path):
        if not isinstance(node, dict) or key not in node:
            raise ValueError(f"--agent {dotted}: no '{'.'.join(path[: i + 1])}' in the runner config")
        node = node[key]
    if not isinstance(node, dict) or last not in node:
        valid = sorted(node) if isinstance(node, dict) else []
        raise ValueError(f"--agent {dotted}: unknown key '{last}'; valid: {valid}")
    node[last] = copy.deepcopy(value)


def fit_mini_batches(requested: int, num_envs: int) -> int:
    """Largest mini-batch count <= ``requested`` that divides ``num_envs``.

    rsl-rl splits recurrent rollouts into mini-batches *of worlds* (``num_envs // num_mini_batches``
    worlds each): more mini-batches than worlds gives empty batches (NaN losses), and a count that
    does not divide the worlds silently drops the remainder from every update.
    """
    if num_envs < 1:
        raise ValueError(f"num_envs must be positive, got {num_envs}")
    for n in range(min(requested, num_envs), 0, -1):
        if num_envs % n == 0:
            return n
    return 1
