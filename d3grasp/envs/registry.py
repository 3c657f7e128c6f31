"""Task registry: a task name maps to a function that makes its environment config.

Names follow the gym/Isaac Lab convention ``D3Grasp-<Robot>-<Variant>-v<N>``. The training
package pairs each task with an rsl-rl runner config (``d3grasp.train.configs``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, fields, is_dataclass, replace
from typing import Any

from d3grasp.envs.config import GraspEnvConfig, ObjectSetConfig

DEFAULT_TASK = "D3Grasp-DexHand13-Mixed-v0"


@dataclass(frozen=True)
class TaskSpec:
    name: str
    description: str
    make_cfg: Callable[[], GraspEnvConfig]
    # Observation groups the critic reads: the asymmetric default adds "privileged".
    critic_groups: tuple[str, ...] = ("policy", "privileged")


def _mixed() -> GraspEnvConfig:
    return GraspEnvConfig(objects=ObjectSetConfig(kinds=("rigid", "deformable")))


def _diverse() -> GraspEnvConfig:
    return GraspEnvConfig(objects=ObjectSetConfig(kinds=("rigid",)))


def _deformable() -> GraspEnvConfig:
    return GraspEnvConfig(objects=ObjectSetConfig(kinds=("deformable",)))


def _base() -> GraspEnvConfig:
    # Paper ablation "Base": proprioception only, symmetric actor-critic. Its prior reads no touch
    # either: the rule's joints stop on stall and the lift starts when they all have.
    cfg = _mixed()
    cfg.rule.stop_on = "stall"
    cfg.tactile_obs = False
    cfg.privileged_obs = False
    return cfg


def _base_tactile() -> GraspEnvConfig:
    # Paper ablation "Base + Tactile": proprioception and touch, symmetric actor-critic.
    cfg = _mixed()
    cfg.privileged_obs = False
    return cfg


TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (
        TaskSpec(DEFAULT_TASK, "rigid and soft objects (the paper's mixed-asset training)", _mixed),
        TaskSpec("D3Grasp-DexHand13-Diverse-v0", "rigid objects in three size bins", _diverse),
        TaskSpec("D3Grasp-DexHand13-Deformable-v0", "FEM soft objects", _deformable),
        TaskSpec(
            "D3Grasp-DexHand13-Base-v0",
            "ablation: proprioception only, symmetric critic",
            _base,
            critic_groups=("policy",),
        ),
        TaskSpec(
            "D3Grasp-DexHand13-BaseTactile-v0",
            "ablation: proprioception + tactile, symmetric critic",
            _base_tactile,
            critic_groups=("policy",),
        ),
    )
}


class UnknownTaskError(KeyError):
    def __str__(self) -> str:  # KeyError quotes its message; say it plainly
        return str(self.args[0])


def get_task(name: str) -> TaskSpec:
    if name not in TASKS:
        known = "\n  ".join(sorted(TASKS))
        raise UnknownTaskError(f"unknown task '{name}'. Known tasks:\n  {known}")
    return TASKS[name]


def apply_overrides(cfg: Any, overrides: dict[str, Any]) -> Any:
    """Set config fields from keyword overrides; nested fields by ``section__field`` or dicts.

    ``apply_overrides(cfg, {"num_envs": 4, "sim__substeps": 8, "phases": {"grasp": 1.5}})``.
    Unknown names raise ``ValueError`` listing the valid ones.
    """
    for key, value in overrides.items():
        head, _, rest = key.partition("__")
        names = {f.name for f in fields(cfg)}
        if head not in names:
            raise ValueError(
                f"unknown config field '{head}' for {type(cfg).__name__}; valid: {sorted(names)}"
            )
        current = getattr(cfg, head)
        if rest:
            setattr(cfg, head, apply_overrides(current, {rest: value}))
        elif isinstance(value, dict) and is_dataclass(current):
            setattr(cfg, head, apply_overrides(current, value))
        else:
            if is_dataclass(cfg) and type(cfg).__dataclass_params__.frozen:
                cfg = replace(cfg, **{head: value})
            else:
                setattr(cfg, head, value)
    return cfg
