"""Scoring candidate grasps in simulation: each candidate in a world of its own, the rule-based
closing, the lift, the hold and a push along each of the six directions, many candidates of many
objects in one multi-world environment.

A trial's score: 1 for a lift (s_lift), 1 more for holding through the six pushes (s_disturb), and up
to 0.5 for how little the object moved against the palm under the pushes (0.5 at rest, 0 at the
2 cm tolerance), so among held grasps the firmer one wins.

Trials run under the evaluation's own conditions when ``ScoringConfig.randomise`` is set (the
``evaluation`` schedule of d3grasp.planner.plan): the evaluation environment (``eval_mode``: nominal
friction, masses and drive gains, all six pushes in their fixed order) with its draws, the object
anywhere within 1 cm at any yaw (so the world-fixed pushes meet the grasp from every side) and the
pads' sensor noise, and the grasp placed where the trial's perception puts it: the true pose
(``oracle``) or the RGB-D camera's registered estimate (``camera``, the main command's protocol,
with its calibration error and the turns of a symmetric footprint it cannot tell apart). Without it
(the ``legacy`` schedule) the object sits at the origin unturned and the pads read no noise.
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
    """The trial episode: the evaluation's schedule and rule, pushes of ``push_seconds``, with or
    without the evaluation's draws (module docstring)."""

    push_seconds: float = 0.3  # per direction (evaluation: 2 s); losses under a push are sudden
    randomise: bool = False  # the evaluation's draws: pose within 1 cm at any yaw, tactile noise
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
    """One candidate (``grasp``) of one object, placed at the pose ``perception`` gives (``oracle``:
    the true pose; ``camera``: the RGB-D camera's estimate)."""

    object_id: str
    grasp: ObjectGrasp
    perception: str = "oracle"


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
    stream: int = 0,
) -> list[dict[str, Any]]:
    """Episode records of ``trials``, in order (``worlds_per_batch`` worlds per environment, one
    environment per perception). With the evaluation's draws, batch ``b`` of a call is seeded
    ``seed + 1000 * stream + b``: the rounds of a plan pass their own ``stream``, so a grasp tried
    again meets new draws."""
    cfg = cfg or ScoringConfig()
    records: list[dict[str, Any] | None] = [None] * len(trials)
    batch = 0
    for perception in dict.fromkeys(t.perception for t in trials):
        idx = [k for k, t in enumerate(trials) if t.perception == perception]
        for start in range(0, len(idx), cfg.worlds_per_batch):
            chunk = idx[start : start + cfg.worlds_per_batch]
            # Legacy trials draw nothing: every batch ran at the planner's seed (kept, so old plans
            # reproduce).
            seed = cfg.seed + (1000 * stream + batch if cfg.randomise else 0)
            found = _run_batch([trials[k] for k in chunk], manifest, cfg, perception, seed)
            for k, rec in zip(chunk, found, strict=True):
                records[k] = rec
            batch += 1
            if on_batch is not None:
                on_batch(len(chunk))
    assert all(r is not None for r in records)
    return records  # type: ignore[return-value]


def _run_batch(
    chunk: Sequence[Trial], manifest: str | None, cfg: ScoringConfig, perception: str, seed: int
) -> list[dict[str, Any]]:
    from d3grasp.controllers import first_episodes, make_controller
    from d3grasp.envs import close_env, make_env
    from d3grasp.policies import BASELINE

    objects: dict[str, Any] = {"ids": tuple(t.object_id for t in chunk)}
    if manifest is not None:
        objects["manifest"] = str(manifest)
    # Legacy trials: the object at the origin, unturned, no sensor noise. The evaluation's: its draws.
    draws = {} if cfg.randomise else {"randomization": {"enabled": False}}
    with warnings.catch_warnings():
        # The trials place their own candidates (grasp_override below), not the stored grasps,
        # so the settings those were planned under do not matter here.
        warnings.filterwarnings("ignore", message="the grasps of .* planned under other settings")
        env = make_env(
            cfg.task,
            num_envs=len(chunk),
            device=cfg.device,
            seed=seed,
            eval_mode=True,
            objects=objects,
            perception=perception,
            phases={"disturb_per_direction": cfg.push_seconds},
            **draws,
        )
    try:
        env.planning.override = [t.grasp for t in chunk]
        env.reset_all()
        return first_episodes(env, make_controller(env, cfg.task, BASELINE, cfg.device))
    finally:
        close_env(env)
