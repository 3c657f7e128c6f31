"""The reward: the terms of ``d3grasp.kernels.rewards.TERM_NAMES``, computed by the Warp kernels of
``d3grasp.kernels.rewards`` for all worlds at once (their weights: ``GraspEnvConfig.rewards``), and
the terms computed in torch, declared once in :data:`TORCH_TERMS` (the residual penalty each step,
the success bonus at an episode's end).

Their per-step inputs are gathered from the state by ``d3grasp.kernels.world_state`` (which also
hands the scoring the object's position and whether the state is finite), in the same graph as the
reward kernels; :func:`reference_reward_inputs` is that gather in torch, the kernel's reference."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import torch
import warp as wp

from d3grasp.dexhand13 import NUM_FINGER_JOINTS, NUM_LINKS, NUM_PADS
from d3grasp.envs.physics import Replayed
from d3grasp.envs.scene import OBJECT_SOFT
from d3grasp.envs.sensors import wp_view
from d3grasp.kernels import rewards as rk
from d3grasp.kernels import world_state as ws
from d3grasp.vocabulary import PHASES

if TYPE_CHECKING:
    from d3grasp.envs.config import GraspEnvConfig
    from d3grasp.envs.grasp_env import GraspEnv

# Half-thickness of a finger link (m): hand-to-table distances are link frame heights above the
# table minus this.
FINGER_HALF_THICKNESS = 0.012

# The reward inputs the environment writes each step (the rest point at the true pad readings).
_STEP_INPUTS = (
    "alive",
    "joint_q",
    "joint_qd",
    "link_pos",
    "object_com",
    "obj_lin_vel",
    "obj_ang_vel",
    "env_dist",
    "eps_bar",
    "node_count",
    "object_rise",
)


@dataclass
class RewardState:
    """What the reward owns on the environment (``env.reward``): the gather's parameters, the reward
    kernels' inputs and outputs, torch views of the terms (W, terms) and total (W,), of the inputs
    written each step (``step_inputs``), the torch terms that are on (fixed when the env is built)
    with the step's values, and the replayed launch."""

    gather_params: ws.RewardGatherParams
    inputs: rk.RewardInputs
    out: rk.RewardBuffers
    terms: torch.Tensor
    total: torch.Tensor
    step_inputs: dict[str, torch.Tensor]
    torch_terms: tuple[TorchTerm, ...]  # the declared torch terms this configuration pays
    step_terms: dict[str, torch.Tensor]  # the values of those paid each step, by name (W,)
    launch: Replayed


def allocate(env: GraspEnv) -> None:
    """The reward kernels' input and output buffers, and torch views of the inputs written per step."""
    W, dev, lay = env.num_envs, env.wp_device, env.layout
    inputs = rk.RewardInputs(
        alive=wp.zeros(W, dtype=float, device=dev),
        joint_q=wp.zeros((W, NUM_FINGER_JOINTS), dtype=float, device=dev),
        joint_q_ref=wp.zeros((W, NUM_FINGER_JOINTS), dtype=float, device=dev),
        joint_qd=wp.zeros((W, NUM_FINGER_JOINTS), dtype=float, device=dev),
        link_pos=wp.zeros((W, NUM_LINKS), dtype=wp.vec3, device=dev),
        object_com=wp.zeros(W, dtype=wp.vec3, device=dev),
        # The paper's r_contact rewards "contact between the fingertips and the object surface":
        # the pads' contacts with the object alone. With every contact counted, a pad pressing the
        # table at the permitted maximum (20 N) earned k_f f_m = 0.4 a step (a lifted object earns
        # k_l = 3). r_symmetry, from the same inputs, compares the forces on the object.
        pad_force=env.sensors.pad_force_object,
        pad_contact=env.sensors.pad_contact_object,
        obj_lin_vel=wp.zeros(W, dtype=wp.vec3, device=dev),
        obj_ang_vel=wp.zeros(W, dtype=wp.vec3, device=dev),
        env_dist=wp.zeros((W, NUM_LINKS), dtype=float, device=dev),
        eps_bar=wp.zeros(W, dtype=float, device=dev),
        node_count=wp.zeros(W, dtype=float, device=dev),
        is_deformable=wp.array((lay.object_kind == OBJECT_SOFT).astype("int32"), dtype=wp.int32, device=dev),
        object_rise=wp.zeros(W, dtype=float, device=dev),
    )
    out = rk.RewardBuffers.allocate(env.cfg.rewards, W, NUM_LINKS, NUM_PADS, device=dev)
    # The gather of the inputs above from the state (after the scoring's buffers: it reads the lift
    # starts and writes the scoring's object position and finiteness).
    prm = ws.RewardGatherParams()
    prm.table_height = env.cfg.sim.table_height
    prm.finger_half_thickness = FINGER_HALF_THICKNESS
    prm.grasp_phase, prm.lift_phase = PHASES.index("grasp"), PHASES.index("lift")
    # The gather and the five reward launches replayed as one graph (the buffers above never move):
    # a launch from Python costs ~0.15 ms on the CPU, the kernels at a few worlds microseconds.
    launch = Replayed(lambda: _launches(env, prm, inputs, out), [ws, rk], dev, env.cfg.sim.use_graph)
    on = tuple(t for t in TORCH_TERMS if t.on(env.cfg))
    env.reward = RewardState(
        gather_params=prm,
        inputs=inputs,
        out=out,
        terms=wp_view(out.terms),
        total=wp_view(out.total),
        step_inputs={name: wp_view(getattr(inputs, name)) for name in _STEP_INPUTS},
        torch_terms=on,
        step_terms={t.name: torch.zeros(W, device=env.torch_device) for t in on if t.paid == "step"},
        launch=launch,
    )


def _launches(
    env: GraspEnv, prm: ws.RewardGatherParams, inputs: rk.RewardInputs, out: rk.RewardBuffers
) -> None:
    si = env.scoring.inputs
    ws.gather_reward_inputs(
        prm,
        env.kernel.world,
        si.t,  # the step count and the objects' start positions: the scoring's inputs, shared
        si.object_start,
        inputs,
        si.obj_pos,
        si.finite,
    )
    rk.compute_rewards(inputs, out)


def compute_rewards(env: GraspEnv) -> torch.Tensor:
    """The step's reward of every world (W,), non-finite values zeroed and clipped at ``reward_clip``;
    writes the scoring's inputs on the way: the step count, the object's position and finiteness."""
    env.scoring.step_inputs["t"].copy_(env.episode_length_buf)
    r = env.reward
    r.launch()
    total = torch.nan_to_num(r.total.clone(), nan=0.0, posinf=0.0, neginf=0.0)
    for term in r.torch_terms:
        if term.paid == "step":
            r.step_terms[term.name][:] = term.value(env)  # kept for the step's log
            total += r.step_terms[term.name]
    clip = env.cfg.reward_clip
    return total.clamp(-clip, clip) if clip > 0 else total


def reward_log(env: GraspEnv) -> dict[str, torch.Tensor]:
    """The step's ``Reward/<name>`` means over the worlds: every kernel term and the torch step terms
    that are on (unclipped)."""
    log = {f"Reward/{n}": m for n, m in zip(rk.TERM_NAMES, env.reward.terms.mean(0).unbind(), strict=True)}
    for name, value in env.reward.step_terms.items():
        log[f"Reward/{name}"] = value.mean()
    return log


def pay_episode_terms(
    env: GraspEnv, rew: torch.Tensor, finished: torch.Tensor, episodes: list[dict[str, Any]]
) -> dict[str, float]:
    """Add the torch terms paid at an episode's end to the last step's reward of the ``finished``
    worlds (after the clip: a terminal outcome, not a blow-up); their sums over all worlds / W, by
    ``Reward/<name>``."""
    log = {}
    for term in env.reward.torch_terms:
        if term.paid == "episode":
            value = term.value(env, episodes).to(rew.dtype)
            rew[finished] += value
            log[f"Reward/{term.name}"] = float(value.sum()) / env.num_envs
    return log


def reference_reward_inputs(env: GraspEnv) -> dict[str, torch.Tensor]:
    """The reward kernels' per-step inputs from the state in torch (the gather kernel's reference),
    with the object's position and whether the state is finite."""
    obj_pos, _, obj_lin, obj_ang = env.object_state()
    finite = torch.isfinite(obj_pos).all(-1) & torch.isfinite(env.view.joint_q[env.index.finger_q]).all(-1)
    links = env.view.body_q[env.index.link_bodies, :3]
    height = links[..., 2] - env.cfg.sim.table_height - FINGER_HALF_THICKNESS
    sensors = env.sensors
    soft = sensors.strain_layout is not None
    # Rise above the resting height, counted from the lift phase on.
    lifting = env.phase_of(env.episode_length_buf) >= PHASES.index("lift")
    rise = torch.nan_to_num(obj_pos[:, 2] - env.draw.object_start[:, 2])
    return {
        "alive": finite.float(),
        "joint_q": torch.nan_to_num(env.view.joint_q[env.index.finger_q]),
        "joint_qd": torch.nan_to_num(env.view.joint_qd[env.index.finger_dof]),
        "link_pos": torch.nan_to_num(links),
        "object_com": torch.nan_to_num(obj_pos),
        "obj_lin_vel": torch.nan_to_num(obj_lin),
        "obj_ang_vel": torch.nan_to_num(obj_ang),
        "env_dist": torch.nan_to_num(height).clamp(min=0.0),
        "eps_bar": sensors.soft_scalar(sensors.strain_buf.object_eps)
        if soft
        else torch.zeros(env.num_envs, device=env.torch_device),
        "node_count": (
            sensors.soft_scalar(sensors.strain_layout.object_node_count)
            if soft
            else torch.zeros(env.num_envs, device=env.torch_device)
        ),
        "object_rise": torch.where(lifting, rise, torch.zeros_like(rise)),
        "obj_pos": obj_pos,
        "finite": finite,
    }


def success_bonus(env: GraspEnv, episodes: list[dict[str, Any]]) -> torch.Tensor:
    """(len(episodes),) ``bonus_lift * s_lift + bonus_disturb * s_disturb`` of each finished episode,
    its successes as the scoring counts them (d3grasp.kernels.scoring)."""
    lift, disturb = env.cfg.success_bonus_lift, env.cfg.success_bonus_disturb
    return torch.as_tensor(
        [lift * ep["s_lift"] + disturb * ep["s_disturb"] for ep in episodes],
        dtype=torch.float32,
        device=env.torch_device,
    )


def residual_penalty(env: GraspEnv) -> torch.Tensor:
    """(W,) ``-residual_penalty * sum_j r_j^2``: the cost of the policy's offset ``r`` (per joint, in
    [-1, 1]) from the rule's targets in the residual action modes; zeros in the absolute mode."""
    k = env.cfg.residual_penalty
    if k == 0.0 or env.residual_base is None:
        return torch.zeros(env.num_envs, device=env.torch_device)
    return -k * env.act.residual.square().sum(-1)


@dataclass(frozen=True)
class TorchTerm:
    """A reward term computed in torch beside the kernels' (logged as ``Reward/<name>``).

    ``paid``: ``"step"``, ``value(env) -> (W,)`` added to every step's reward before the clip; or
    ``"episode"``, ``value(env, episodes) -> (len(episodes),)`` added to the last step of each finished
    episode. ``on(cfg)``: whether the configuration pays it (its weight is not zero)."""

    name: str
    paid: Literal["step", "episode"]
    value: Callable[..., torch.Tensor]
    on: Callable[[GraspEnvConfig], bool]


# The torch terms, in the order they are added. The only place a torch term is declared: allocation,
# the step's sum, the episode's end and the log all read this tuple.
TORCH_TERMS: tuple[TorchTerm, ...] = (
    TorchTerm("residual", "step", residual_penalty, lambda cfg: cfg.residual_penalty != 0.0),
    TorchTerm(
        "success_bonus",
        "episode",
        success_bonus,
        lambda cfg: bool(cfg.success_bonus_lift or cfg.success_bonus_disturb),
    ),
)
