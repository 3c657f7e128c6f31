"""What drives the fingers in play and evaluation: a checkpoint's deterministic policy (a path or
``"shipped"``) or the rule-based baseline (``"baseline"``).

A policy is rebuilt from its checkpoint alone: the actor network as recorded (``infos["actor"]``,
rsl-rl 5.5's model classes), its weights and observation normaliser, after the checkpoint's
contract has been checked against the environment (``d3grasp.policies.checkpoint.check_fits``).
Training is not involved, so evaluation needs nothing of ``d3grasp.train``.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")  # rsl_rl imports GitPython; a git binary is optional

import torch  # noqa: E402

from d3grasp.console import library_output  # noqa: E402
from d3grasp.envs.config import policy_interface  # noqa: E402
from d3grasp.policies import BASELINE  # noqa: E402
from d3grasp.policies.checkpoint import (  # noqa: E402
    CheckpointError,
    check_fits,
    read_checkpoint,
)
from d3grasp.policies.teacher import TEACHER, PoseTeacher  # noqa: E402

__all__ = ["Controller", "first_episodes", "load_actor", "make_controller"]


@dataclass
class Controller:
    """Observations -> actions, and what to do when episodes end (a policy's recurrent state)."""

    act: Callable[[Any], torch.Tensor]
    on_dones: Callable[[torch.Tensor], None]
    actor: torch.nn.Module | None = None  # the policy's network (export, latency); None for the baseline


def make_controller(
    env: Any,
    task: str,
    checkpoint: str | os.PathLike[str],
    device: str,
    data: dict | None = None,
    *,
    trust: bool = False,
) -> Controller:
    """The controller of ``checkpoint`` (a path, ``"baseline"`` for the rule-based controller or
    ``"teacher"`` for the privileged teacher, d3grasp.policies.teacher).

    ``data``: the checkpoint already read (``read_checkpoint``), to read it once. ``trust``: read it
    even if it names code (``--trust-checkpoint``).
    """
    if str(checkpoint) == BASELINE:
        from d3grasp.envs.baseline import RuleBasedController

        # The rule resets a world itself when its episode starts (t = 0).
        return Controller(RuleBasedController(env).act, lambda dones: None)
    if str(checkpoint) == TEACHER:
        return Controller(PoseTeacher(env).act, lambda dones: None)
    actor = load_actor(env, task, checkpoint, device, data=data, trust=trust)
    actor.reset()
    return Controller(
        act=lambda obs: actor(obs.to(device)),
        on_dones=lambda dones: actor.reset(dones.to(device)),  # fresh LSTM state for new episodes
        actor=actor,
    )


def load_actor(
    env: Any,
    task: str,
    checkpoint: str | os.PathLike[str],
    device: str,
    data: dict | None = None,
    *,
    trust: bool = False,
) -> torch.nn.Module:
    """The checkpoint's actor for ``env``'s observations, in evaluation mode.

    ``CheckpointError`` (one line) for a missing or unreadable file, a checkpoint of other
    observation sizes or action count, one trained with other action-to-target settings, or one
    that does not record its actor network.
    """
    from rsl_rl.utils import resolve_class, resolve_obs_groups

    path = str(checkpoint)
    data = read_checkpoint(Path(path), map_location=str(device), trust=trust) if data is None else data
    infos = data.get("infos") or {}
    obs = env.get_observations()
    sizes = {str(k): int(obs[k].shape[-1]) for k in obs.keys()}  # noqa: SIM118 (TensorDict)
    groups = {
        "actor": ["policy"],
        "critic": ["policy", "privileged"] if "privileged" in sizes else ["policy"],
    }
    if isinstance(infos.get("obs_groups"), dict):
        groups.update({k: list(v) for k, v in infos["obs_groups"].items()})
    cfg = getattr(env, "cfg", None)
    check_fits(
        infos,
        path,
        task=task,
        obs_sizes=sizes,
        obs_groups=groups,
        num_actions=int(env.num_actions),
        policy_interface=policy_interface(cfg) if cfg is not None else None,
        models=("actor",),
    )
    if not isinstance(infos.get("actor"), dict):
        raise CheckpointError(f"checkpoint {path} does not record its actor network (infos['actor'])")
    try:
        actor_class, actor_cfg = resolve_class(infos["actor"])
    except (KeyError, ValueError, ImportError, AttributeError) as exc:
        raise CheckpointError(f"checkpoint {path} names an actor rsl-rl cannot build ({exc})") from None
    with library_output("rsl-rl, building the actor"):  # it prints the groups and the network
        groups = resolve_obs_groups(obs, groups, ["actor", "critic"])
        actor = actor_class(obs, groups, "actor", int(env.num_actions), **actor_cfg).to(device)
    try:
        actor.load_state_dict(data["actor_state_dict"], strict=True)
    except (RuntimeError, KeyError, ValueError) as exc:
        first = str(exc).strip().splitlines()[0]
        raise CheckpointError(f"checkpoint {path} does not match the configured networks: {first}") from None
    actor.eval()
    return actor


def first_episodes(
    env: Any, controller: Controller, on_episode: Callable[[], None] | None = None
) -> list[dict[str, Any]]:
    """The first finished episode record of every world of ``env`` under ``controller``, by world
    (evaluation and the grasp planner's trials). ``RuntimeError`` when a world does not finish one
    within an episode's length."""
    first: dict[int, dict[str, Any]] = {}
    obs = env.get_observations()
    with torch.inference_mode():
        for _ in range(int(env.max_episode_length)):
            obs, _, dones, extras = env.step(controller.act(obs).to(env.device))
            controller.on_dones(dones)
            for ep in extras.get("episodes", ()):
                if ep["env"] not in first:
                    first[ep["env"]] = ep
                    if on_episode is not None:
                        on_episode()
            if len(first) == env.num_envs:
                break
    if len(first) != env.num_envs:
        missing = sorted(set(range(env.num_envs)) - set(first))
        raise RuntimeError(f"worlds {missing} did not finish an episode in {env.max_episode_length} steps")
    return [first[w] for w in range(env.num_envs)]
