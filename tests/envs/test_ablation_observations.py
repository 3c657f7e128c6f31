"""The paper's three ablations, pinned by what each one's networks read: Base (no touch anywhere),
Base+Tactile (touch for the actor, a symmetric critic) and the asymmetric task (touch, and the critic
reads the privileged group too). Written as numbers: a term added, removed or resized fails here."""

from __future__ import annotations

import pytest
from d3grasp.train.configs import make_train_cfg

from d3grasp.envs import make_env
from d3grasp.envs.mdp.observations import policy_terms

PROPRIOCEPTION = [
    ("joint_positions", 16),
    ("joint_velocities", 16),
    ("action_history", 12),  # the last 3 actions of 4 finger synergies
    ("episode_clock", 3),  # t / T, sin, cos
    ("grasp_type", 3),
    ("phase", 6),
    ("palm_offset", 3),
    ("palm_orientation", 4),
    ("rule_targets", 16),
    ("residual", 16),
]
TOUCH = [("pad_forces", 33), ("pad_contacts", 11)]  # 11 pads x 3 axes, and their contact flags

ABLATIONS = {
    "D3Grasp-DexHand13-Base-v0": (PROPRIOCEPTION, ["policy"]),
    "D3Grasp-DexHand13-BaseTactile-v0": (TOUCH + PROPRIOCEPTION, ["policy"]),
    "D3Grasp-DexHand13-Mixed-v0": (TOUCH + PROPRIOCEPTION, ["policy", "privileged"]),
}
PRIVILEGED_SIZE = 75


@pytest.mark.parametrize("task", list(ABLATIONS))
def test_each_ablation_reads_what_the_paper_says(task: str) -> None:
    terms, critic = ABLATIONS[task]
    env = make_env(task, num_envs=1, eval_mode=True, objects={"ids": ("box_01",)})
    try:
        got = [(name, int(term(env).shape[-1])) for name, term in policy_terms(env)]
        assert got == terms
        obs = env.get_observations()
        assert int(obs["policy"].shape[-1]) == sum(size for _, size in terms)
        assert int(obs["privileged"].shape[-1]) == PRIVILEGED_SIZE
    finally:
        env.close()
    groups = make_train_cfg(task)["obs_groups"]
    assert groups == {"actor": ["policy"], "critic": critic}


@pytest.mark.parametrize(
    ("task", "kind"),
    [("D3Grasp-DexHand13-Diverse-v0", "rigid"), ("D3Grasp-DexHand13-Deformable-v0", "deformable")],
)
def test_the_single_kind_tasks_build_and_step(task: str, kind: str) -> None:
    """The quick build of the Diverse and Deformable tasks (their training runs are slow tests): two
    worlds of the task's own object kind, a zero action steps them to finite observations."""
    import torch

    env = make_env(task, num_envs=2, seed=0)
    try:
        assert {e.kind for e in env.world_entries} == {kind}
        obs, rew, dones, _ = env.step(torch.zeros(env.num_envs, env.num_actions))
        assert all(torch.isfinite(obs[k]).all() for k in obs.keys())  # noqa: SIM118 (TensorDict)
        assert torch.isfinite(rew).all() and dones.shape == (2,)
    finally:
        env.close()
