"""The grasp environment (an rsl-rl VecEnv), its configuration and the task registry."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from d3grasp.envs.config import GraspEnvConfig
from d3grasp.envs.registry import DEFAULT_TASK, TASKS, get_task

if TYPE_CHECKING:
    from d3grasp.envs.grasp_env import GraspEnv


def make_env(
    task: str = DEFAULT_TASK,
    num_envs: int | None = None,
    device: str = "cpu",
    seed: int = 0,
    **overrides: Any,
) -> GraspEnv:
    """Make the vectorised environment of a registered task.

    ``overrides`` set config fields (``sim__substeps=8``, ``objects={"split": "test"}``, ...).
    """
    from d3grasp.envs.grasp_env import GraspEnv
    from d3grasp.envs.registry import apply_overrides

    cfg = get_task(task).make_cfg()
    if num_envs is not None:
        cfg.num_envs = num_envs
    cfg.device = device
    cfg.seed = seed
    cfg = apply_overrides(cfg, overrides)
    return GraspEnv(cfg, task_name=task)


def close_env(env: Any) -> None:
    """Release an environment's resources; a VecEnv from a custom ``--env_factory`` need not have
    ``close()``."""
    close = getattr(env, "close", None)
    if close is not None:
        close()


__all__ = ["DEFAULT_TASK", "TASKS", "GraspEnvConfig", "close_env", "get_task", "make_env"]
