"""Scoring candidate grasps in simulation: each candidate in a world of its own, the rule-based
closing, the lift, the hold and a short push along each of the six directions, many candidates of
many objects in one multi-world environment.

A trial's score: 1 for a lift (s_lift), 1 more for holding through the six pushes (s_disturb), and up
to 0.5 for how little the object moved against the palm under the pushes (0.5 at rest, 0 at the
2 cm tolerance), so among held grasps the firmer one wins. A grasp is scored by the mean over its
trials: the nominal one and trials with the object a few millimetres and degrees away from where the
planner thinks it is, so a grasp that holds only at one exact placement (a knife's edge) loses.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from d3grasp.envs.grasps import ObjectGrasp
from d3grasp.envs.mdp.terminations import DISTURB_TOLERANCE
from d3grasp.envs.registry import DEFAULT_TASK


@dataclass(frozen=True)
class ScoringConfig:
    """The trial episode: the evaluation's schedule and rule, shorter pushes, no randomisation."""

    push_seconds: float = 0.3  # per direction (evaluation: 2 s); losses under a push are sudden
    worlds_per_batch: int = 48
    task: str = DEFAULT_TASK
    device: str = "cpu"
    seed: int = 0


def trial_environment(cfg: ScoringConfig) -> dict[str, Any]:
    """The simulation and rule settings the trials of ``cfg`` run under (its task's: the trials
    override the schedule and randomisation only), as the grasp file records them."""
    from d3grasp.envs.grasp_file import environment_record
    from d3grasp.envs.registry import get_task

    env_cfg = get_task(cfg.task).make_cfg()
    return environment_record(env_cfg.sim, env_cfg.rule)


@dataclass(frozen=True)
class Trial:
    """One candidate (``grasp``) of one object, placed as given."""

    object_id: str
    grasp: ObjectGrasp


def trial_score(record: dict[str, Any]) -> float:
    """The score of one trial's episode record (module docstring)."""
    score = float(record["s_lift"]) + float(record["s_disturb"])
    if record["s_lift"]:
        motion = record.get("max_push_motion") or 0.0
        score += 0.5 * max(0.0, 1.0 - float(motion) / DISTURB_TOLERANCE)
    return score


def run_trials(
    trials: Sequence[Trial],
    manifest: str | None,
    cfg: ScoringConfig | None = None,
    on_batch: Callable[[int], None] | None = None,
) -> list[dict[str, Any]]:
    """Episode records of ``trials``, in order (``worlds_per_batch`` worlds per environment)."""
    from d3grasp.controllers import first_episodes, make_controller
    from d3grasp.envs import close_env, make_env
    from d3grasp.policies import BASELINE

    cfg = cfg or ScoringConfig()
    records: list[dict[str, Any]] = []
    for start in range(0, len(trials), cfg.worlds_per_batch):
        chunk = trials[start : start + cfg.worlds_per_batch]
        objects: dict[str, Any] = {"ids": tuple(t.object_id for t in chunk)}
        if manifest is not None:
            objects["manifest"] = str(manifest)
        with warnings.catch_warnings():
            # The trials place their own candidates (grasp_override below), not the stored grasps,
            # so the settings those were planned under do not matter here.
            warnings.filterwarnings("ignore", message="the grasps of .* planned under other settings")
            env = make_env(
                cfg.task,
                num_envs=len(chunk),
                device=cfg.device,
                seed=cfg.seed,
                eval_mode=True,
                objects=objects,
                randomization={"enabled": False},
                phases={"disturb_per_direction": cfg.push_seconds},
            )
        try:
            env.grasp_override = [t.grasp for t in chunk]
            env.reset_all()
            records += first_episodes(env, make_controller(env, cfg.task, BASELINE, cfg.device))
        finally:
            close_env(env)
        if on_batch is not None:
            on_batch(len(chunk))
    return records
