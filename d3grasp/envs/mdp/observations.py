"""The observation groups, as named terms (scales in ``ObservationConfig``).

``policy`` (the actor; what a real hand has): pad forces and contacts, finger joint positions
and velocities, the action history, the episode clock, the grasp type and phase, where the
scripted palm is along its path, and in the residual modes the rule's targets and the residual.
``privileged`` (the critic's extra group): the object's pose and velocity relative to the palm,
hand-object distances, strain and the deformable rotation's sigma, material, true pad forces.

The environment computes both groups with one Warp kernel (``d3grasp.kernels.observations``),
replayed as a graph: as ~70 torch operations they cost ~0.17 ms a step, most of what a 1-world step
spends beyond its physics. The terms below name each part and are the kernel's reference
(:func:`reference_observations`, the test's twin).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
import warp as wp
from tensordict import TensorDict

from d3grasp.envs.physics import Replayed
from d3grasp.envs.sensors import wp_view
from d3grasp.kernels import observations as ok
from d3grasp.vocabulary import GRASP_TYPES, PHASES

if TYPE_CHECKING:
    from d3grasp.envs.grasp_env import GraspEnv

Term = Callable[["GraspEnv"], torch.Tensor]


# ---------------------------------------------------------------------------------- policy terms


def pad_forces(env: GraspEnv) -> torch.Tensor:
    return torch.nan_to_num(env.view.pad_force).reshape(env.num_envs, -1) / env.cfg.obs.pad_force_per_unit


def pad_contacts(env: GraspEnv) -> torch.Tensor:
    return env.view.pad_contact


def joint_positions(env: GraspEnv) -> torch.Tensor:
    """Finger joint positions normalised over their limits to [-1, 1]."""
    return env.normalize_joints(torch.nan_to_num(env.view.joint_q[env.index.finger_q]))


def joint_velocities(env: GraspEnv) -> torch.Tensor:
    return env.cfg.obs.joint_vel_scale * torch.nan_to_num(env.view.joint_qd[env.index.finger_dof])


def action_history(env: GraspEnv) -> torch.Tensor:
    return env.act.history.reshape(env.num_envs, -1)


def episode_clock(env: GraspEnv) -> torch.Tensor:
    """t / T, sin(2 pi t / T), cos(2 pi t / T) (the paper's t_i; rows of the script's table)."""
    script = env.script
    return script.tables(env.torch_device).clock[script.row(env.episode_length_buf)]


def grasp_type(env: GraspEnv) -> torch.Tensor:
    return _one_hot(len(GRASP_TYPES), env.torch_device)[env.grasp.type_id]


def phase(env: GraspEnv) -> torch.Tensor:
    return _one_hot(len(PHASES), env.torch_device)[env.phase_of(env.episode_length_buf)]


@functools.cache
def _one_hot(n: int, device: torch.device) -> torch.Tensor:
    """(n, n) float identity: row i is the one-hot code of i (``one_hot`` checks its input's range
    on every call, a host round trip)."""
    return torch.eye(n, dtype=torch.float32, device=device)


def palm_offset(env: GraspEnv) -> torch.Tensor:
    """The palm command relative to the grasp pose (m, scaled)."""
    return (env.palm.cmd_pos - env.grasp.palm_pos) * env.cfg.obs.palm_offset_scale


def palm_orientation(env: GraspEnv) -> torch.Tensor:
    return env.grasp.palm_quat


def rule_targets(env: GraspEnv) -> torch.Tensor:
    """The rule's current joint targets (what the residual is added to), normalised."""
    return env.normalize_joints(env.residual_base.target)


def residual(env: GraspEnv) -> torch.Tensor:
    """The residual now applied, per joint."""
    return env.act.residual


def policy_terms(env: GraspEnv) -> list[tuple[str, Term]]:
    """The policy group's terms in order (tactile terms only with ``tactile_obs``)."""
    terms: list[tuple[str, Term]] = []
    if env.cfg.tactile_obs:
        terms += [("pad_forces", pad_forces), ("pad_contacts", pad_contacts)]
    terms += [
        ("joint_positions", joint_positions),
        ("joint_velocities", joint_velocities),
        ("action_history", action_history),
        ("episode_clock", episode_clock),
        ("grasp_type", grasp_type),
        ("phase", phase),
        ("palm_offset", palm_offset),
        ("palm_orientation", palm_orientation),
    ]
    if env.residual_base is not None:
        terms += [("rule_targets", rule_targets), ("residual", residual)]
    return terms


# ------------------------------------------------------------------------------ privileged terms


def object_offset(env: GraspEnv, obj: tuple[torch.Tensor, ...]) -> torch.Tensor:
    palm = env.view.body_q[env.index.palm, :3]
    return (obj[0] - palm) * env.cfg.obs.object_offset_scale


def link_distances(env: GraspEnv, obj: tuple[torch.Tensor, ...]) -> torch.Tensor:
    links = env.view.body_q[env.index.link_bodies, :3]
    return torch.linalg.norm(links - obj[0][:, None], dim=-1) * env.cfg.obs.link_distance_scale


def strain(env: GraspEnv) -> torch.Tensor:
    if env.sensors.strain_layout is None:
        return torch.zeros(env.num_envs, 1, device=env.torch_device)
    return env.sensors.soft_scalar(env.sensors.strain_buf.object_eps)[:, None]


def sigma(env: GraspEnv) -> torch.Tensor:
    if env.sensors.strain_layout is None:
        return torch.zeros(env.num_envs, 1, device=env.torch_device)
    return env.sensors.soft_scalar(env.sensors.strain_buf.sigma)[:, None] * env.cfg.obs.sigma_scale


def privileged(env: GraspEnv) -> torch.Tensor:
    """The critic's extra group: object state relative to the palm, distances, strain, material,
    true pad forces."""
    obj = env.object_state()
    o = env.cfg.obs
    return torch.cat(
        [
            object_offset(env, obj),
            obj[1],  # orientation (xyzw)
            obj[2],  # linear velocity
            o.object_ang_vel_scale * obj[3],
            link_distances(env, obj),
            strain(env),
            sigma(env),
            env.draw.object_mass[:, None],
            env.draw.object_friction[:, None],
            env.draw.object_log_e[:, None] / o.log_youngs_per_unit,
            torch.nan_to_num(env.view.pad_force_true).reshape(env.num_envs, -1) / o.pad_force_per_unit,
        ],
        dim=-1,
    )


def episode_draw(env: GraspEnv) -> torch.Tensor:
    """(W, 4) this episode's domain randomisation: mass (rigid) or Young's modulus (soft) scale,
    friction scale, drive gain scale and action latency (steps). The manifest's nominal mass and
    friction above do not show what decides a marginal hold in this episode; these do."""
    return env.draw.dynamics


def push_ahead(env: GraspEnv) -> torch.Tensor:
    """(W, 3) the direction of the push under way, or of the episode's first push before the
    disturb phase; zero once the pushes are over. With the clock it gives the critic the schedule."""
    script = env.script
    tab = script.tables(env.torch_device)
    slot = tab.push_slot[script.row(env.episode_length_buf)]
    before = env.episode_length_buf < env.script.phase_start["disturb"]
    slot = torch.where(before, torch.zeros_like(slot), slot)
    order = torch.cat([env.draw.disturb_order, torch.full_like(env.draw.disturb_order[:, :1], 6)], dim=1)
    return tab.push_dirs[order.gather(1, slot[:, None])[:, 0]]


def privileged_episode(env: GraspEnv) -> torch.Tensor:
    """The privileged group's terms that the observation kernel does not compute (a few values per
    world, appended in torch): the episode's draw and the push schedule."""
    return torch.cat([episode_draw(env), push_ahead(env)], dim=-1)


def reference_observations(env: GraspEnv) -> TensorDict:
    """Both groups from the torch terms above, non-finite values zeroed (what the kernel computes,
    with :func:`privileged_episode` appended)."""
    policy = torch.cat([term(env) for _, term in policy_terms(env)], dim=-1)
    priv = torch.cat([privileged(env), privileged_episode(env)], dim=-1)
    return TensorDict(
        {"policy": torch.nan_to_num(policy), "privileged": torch.nan_to_num(priv)},
        batch_size=[env.num_envs],
        device=env.torch_device,
    )


# The observation inputs the environment writes each step (the rest are views of its buffers).
_STEP_INPUTS = ("t", "action_hist", "palm_cmd", "rule_target", "residual")


@dataclass
class ObservationState:
    """What the observation owns on the environment (``env.observation``): the kernel's parameters,
    inputs and output groups (``policy``, ``privileged`` without the episode's draw), their torch views
    (``out``), the torch views of the inputs written each step (``step_inputs``) and the launch."""

    params: ok.ObservationParams
    inputs: ok.ObservationInputs
    policy: wp.array
    privileged: wp.array
    out: dict[str, torch.Tensor]
    step_inputs: dict[str, torch.Tensor]
    launch: Replayed


def allocate(env: GraspEnv) -> None:
    """The observation kernel's parameters, inputs and outputs (sized by the terms above), and its
    launch captured as a graph. Needs the environment's state, sensors, scoring state and rule."""
    W, dev, o = env.num_envs, env.wp_device, env.cfg.obs
    sizes = reference_observations(env)
    prm = ok.ObservationParams()
    prm.pad_force_per_unit = o.pad_force_per_unit
    prm.joint_vel_scale = o.joint_vel_scale
    prm.palm_offset_scale = o.palm_offset_scale
    prm.object_offset_scale = o.object_offset_scale
    prm.object_ang_vel_scale = o.object_ang_vel_scale
    prm.link_distance_scale = o.link_distance_scale
    prm.sigma_scale = o.sigma_scale
    prm.log_youngs_per_unit = o.log_youngs_per_unit
    prm.tactile = int(env.cfg.tactile_obs)
    prm.residual_terms = int(env.residual_base is not None)
    prm.grasp_phase, prm.lift_phase = PHASES.index("grasp"), PHASES.index("lift")
    prm.num_grasp_types, prm.num_phases = len(GRASP_TYPES), len(PHASES)
    sensors, tables = env.sensors, env.kernel.tables

    def floats(*shape: int, dtype=float) -> wp.array:
        return wp.zeros(shape, dtype=dtype, device=dev)

    inputs = ok.ObservationInputs(
        t=wp.zeros(W, dtype=wp.int64, device=dev),
        pad_force=sensors.pad_force,
        pad_contact=sensors.pad_contact,
        pad_force_true=sensors.pad_force_true,
        lower=wp.from_torch(env.joints.lower),
        upper=wp.from_torch(env.joints.upper),
        action_hist=floats(W, env.act.history[0].numel()),
        clock=wp.from_torch(tables["clock"]),
        grasp_id=wp.from_torch(env.grasp.type_id),
        palm_cmd=floats(W, dtype=wp.vec3),
        grasp_palm_pos=wp.from_torch(env.grasp.palm_pos, dtype=wp.vec3),
        grasp_palm_quat=wp.from_torch(env.grasp.palm_quat),
        rule_target=floats(W, env.act.residual.shape[1]),
        residual=floats(W, env.act.residual.shape[1]),
        mass=wp.from_torch(env.draw.object_mass),
        friction=wp.from_torch(env.draw.object_friction),
        log_e=wp.from_torch(env.draw.object_log_e),
    )
    policy = floats(W, sizes["policy"].shape[1])
    privileged = floats(W, sizes["privileged"].shape[1] - privileged_episode(env).shape[1])
    env.observation = ObservationState(
        params=prm,
        inputs=inputs,
        policy=policy,
        privileged=privileged,
        out={"policy": wp_view(policy), "privileged": wp_view(privileged)},
        step_inputs={n: wp_view(getattr(inputs, n)) for n in _STEP_INPUTS},
        launch=Replayed(
            lambda: ok.compute_observations(prm, env.kernel.world, inputs, policy, privileged),
            [ok],
            dev,
            env.cfg.sim.use_graph,
        ),
    )


def compute_observations(env: GraspEnv) -> TensorDict:
    """Both groups (fresh tensors: a rollout keeps them while the next step runs)."""
    o = env.observation
    i = o.step_inputs
    # The inputs the environment rebinds each step, copied into the kernel's buffers.
    i["t"].copy_(env.episode_length_buf)
    i["action_hist"].copy_(env.act.history.reshape(env.num_envs, -1))
    i["palm_cmd"].copy_(env.palm.cmd_pos)
    if env.residual_base is not None:
        i["rule_target"].copy_(env.residual_base.target)
        i["residual"].copy_(env.act.residual)
    o.launch()
    return TensorDict(
        {
            "policy": o.out["policy"].clone(),
            "privileged": torch.cat([o.out["privileged"], privileged_episode(env)], dim=-1),
        },
        batch_size=[env.num_envs],
        device=env.torch_device,
    )
