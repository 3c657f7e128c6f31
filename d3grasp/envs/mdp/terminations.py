"""Success scoring (the paper's s_grasp, s_lift, s_disturb), terminations and episode records.

The rules and thresholds live in the Warp kernel of ``d3grasp.kernels.scoring`` (with its NumPy twin);
here its buffers are allocated as the environment's ``env.scoring`` (:class:`Scoring`: the kernel's
arrays and their torch views, ``env.scoring.now.lift_ok``, ``.lift_start``, ...), its inputs are
filled each step and its launch is replayed as a graph: as torch operations the scoring cost ~0.2 ms
a step, a tenth of a 1-world step's physics.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import warp as wp

from d3grasp.dexhand13 import NUM_PADS, OPPOSING_PADS, PAD_NAMES, THUMB_PADS
from d3grasp.envs.config import PhaseConfig
from d3grasp.envs.physics import Replayed
from d3grasp.envs.script import DISTURB_NAMES, EpisodeScript
from d3grasp.envs.sensors import wp_view
from d3grasp.kernels import scoring as sk
from d3grasp.kernels.scoring import (  # noqa: F401  (the thresholds, by their names here too)
    BLOWUP_PAD_FORCE,
    DISTURB_TOLERANCE,
    GRASP_CONTACT_FORCE,
    LIFT_TOLERANCE,
    PUSHED_OFF_DISTANCE,
    ROSE_WITH_PALM,
)
from d3grasp.vocabulary import GRASP_TYPES

if TYPE_CHECKING:
    from d3grasp.envs.grasp_env import GraspEnv

FAILURES: tuple[str, ...] = (
    "no grasp",  # the pads never showed a grasp of the object and it was not lifted
    "not lifted",  # a grasp by touch, but the object never rose with the palm
    "slipped during the lift",  # it rose with the palm, then slid out before the lift's end
    "dropped in the hold",  # up at the lift's end, below the lift height during the hold
    *(f"lost under a push ({d})" for d in DISTURB_NAMES),  # moved > 2 cm against the palm in a push
    "pushed off the table",
    "contact blow-up",
    "non-finite state",
)
"""Why an episode failed, the first cause of each episode (``episode_records``' ``failure``); the
kernel's failure code c is ``FAILURES[c - 1]``."""
HELD = "held through the pushes"


def episode_ending(record: dict[str, Any]) -> str:
    """How an episode record ended: ``HELD``, or its failure reason (``"not scored"`` for a record
    with neither)."""
    if record["s_disturb"]:
        return HELD
    return str(record.get("failure") or "not scored")


def failure_label(code: int) -> str:
    """The failure cause of a kernel's failure code ("" for 0: none yet)."""
    return FAILURES[code - 1] if code else ""


def pad_roles() -> np.ndarray:
    """(11,) int32: each pad's role in a grasp (thumb, opposing finger or neither)."""
    role = np.full(NUM_PADS, sk.PAD_OTHER, dtype=np.int32)
    role[list(THUMB_PADS)] = sk.PAD_THUMB
    role[list(OPPOSING_PADS)] = sk.PAD_OPPOSING
    return role


@dataclass
class ScoreViews:
    """The scoring state as torch views, a row per world (the fields of ``kernels.scoring.ScoreState``,
    which resets write and the episode records read)."""

    lift_start: torch.Tensor  # the step each world's lift starts (touch-timed)
    touch_steps: torch.Tensor  # steps in a row the pads have shown a grasp before it
    s_grasp: torch.Tensor
    pads_at_lift: torch.Tensor  # which pads touch the object when the lift starts
    pads_at_hold: torch.Tensor  # ... and when it ends
    max_rise: torch.Tensor
    lift_ok: torch.Tensor
    disturb_ok: torch.Tensor
    push_ref: torch.Tensor
    max_push_motion: torch.Tensor  # m: the most the object moved against the palm in a push
    failure: torch.Tensor  # the first failure cause (FAILURES[c - 1]; 0: none)
    nonfinite_count: torch.Tensor  # (1,): non-finite states met since the environment was made
    done: torch.Tensor  # whether the step ended the episode

    @classmethod
    def of(cls, state: sk.ScoreState) -> ScoreViews:
        return cls(**{f.name: wp_view(getattr(state, f.name)) for f in fields(cls)})


@dataclass
class Scoring:
    """What the scoring owns on the environment (``env.scoring``): the kernel's parameters, schedule,
    inputs and state, the state's torch views (``now``), the torch views of the inputs written each
    step (``step_inputs``: ``t``, ``obj_pos``, ``finite``, ``rule_settled``) and the replayed launch."""

    params: sk.ScoreParams
    schedule: sk.ScoreSchedule
    inputs: sk.ScoreInputs
    state: sk.ScoreState
    now: ScoreViews
    step_inputs: dict[str, torch.Tensor]
    launch: Replayed


def score_params(
    script: EpisodeScript, phases: PhaseConfig, dt: float, eval_mode: bool, lift_on_pads: bool = True
) -> sk.ScoreParams:
    """The scoring kernel's parameters for an episode script and its phase settings; ``lift_on_pads``
    False: only the rule's settling times the lift (``BaselineConfig.stop_on`` "stall")."""
    prm = sk.ScoreParams()
    prm.grasp_start = script.phase_start["grasp"]
    prm.hold_start = script.phase_start["hold"]
    prm.max_episode_length = script.max_episode_length
    prm.settle_steps = max(1, round(phases.grasp_settle / dt))
    prm.lift_on_touch = int(phases.lift_on_touch)
    prm.lift_on_pads = int(lift_on_pads)
    prm.eval_mode = int(eval_mode)
    prm.lift_height = phases.lift_height
    return prm


def allocate(env: GraspEnv) -> None:
    """``env.scoring`` (:class:`Scoring`), its launch captured as a graph. Reads the script, the
    sensors' pad forces, the state's body poses, and ``env.draw.object_start`` and ``env.draw.disturb_order``
    (which resets write in place)."""
    W, dev, script, ph = env.num_envs, env.wp_device, env.script, env.cfg.phases
    prm = score_params(script, ph, env.dt, env.cfg.eval_mode, lift_on_pads=env.cfg.rule.stop_on == "touch")
    tab = script.tables(env.torch_device)
    schedule = sk.ScoreSchedule(
        in_hold_score=wp.from_torch(tab.in_hold_score),
        in_push_score=wp.from_torch(tab.in_push_score),
        push_started=wp.from_torch(tab.push_started),
        scored_push=wp.from_torch(tab.scored_push),
        pad_role=wp.array(pad_roles(), dtype=wp.int32, device=dev),
    )
    inputs = sk.ScoreInputs(
        t=wp.zeros(W, dtype=wp.int64, device=dev),
        obj_pos=wp.zeros(W, dtype=wp.vec3, device=dev),
        finite=wp.zeros(W, dtype=wp.bool, device=dev),
        rule_settled=wp.zeros(W, dtype=wp.bool, device=dev),
        pad_force_object=env.sensors.pad_force_object,
        pad_force_true=env.sensors.pad_force_true,
        body_q=env.physics.state_0.body_q,
        palm_body=wp.array(np.asarray(env.layout.palm_body, dtype=np.int32), dtype=wp.int32, device=dev),
        object_start=wp.from_torch(env.draw.object_start, dtype=wp.vec3),
        disturb_order=wp.from_torch(env.draw.disturb_order),
    )
    state = sk.ScoreState.allocate(W, NUM_PADS, script.phase_start["lift"], dev)
    env.scoring = Scoring(
        params=prm,
        schedule=schedule,
        inputs=inputs,
        state=state,
        now=ScoreViews.of(state),
        step_inputs={
            name: wp_view(getattr(inputs, name)) for name in ("t", "obj_pos", "finite", "rule_settled")
        },
        launch=Replayed(
            lambda: sk.score_step(prm, schedule, inputs, state), [sk], dev, env.cfg.sim.use_graph
        ),
    )


def score(env: GraspEnv) -> torch.Tensor:
    """Update every world's success metrics after the step; return which worlds' episodes ended. The
    step count, the object's position and whether the state is finite (``env.scoring.step_inputs``'
    ``"t"``, ``"obj_pos"``, ``"finite"``) are written before, by ``rewards.compute_rewards`` (its
    gather reads them too)."""
    i = env.scoring.step_inputs
    if env.residual_base is not None:
        # The rule runs inside the env (residual action modes): a hand closed as far as the object
        # lets it is ready to lift too (a hook or a palm grasp need not touch with the thumb's pads).
        i["rule_settled"].copy_(env.residual_base.settled())
    env.scoring.launch()
    sensors = env.sensors
    if sensors.strain_layout is not None:
        env.record.max_strain = torch.maximum(
            env.record.max_strain, sensors.soft_scalar(sensors.strain_buf.object_eps)
        )
    return env.scoring.now.done.clone()


def _pad_list(touching: np.ndarray) -> list[str]:
    return [PAD_NAMES[i] for i in np.flatnonzero(touching)]


def episode_records(env: GraspEnv, finished: torch.Tensor) -> list[dict[str, Any]]:
    """One record per finished world: object, grasp type, the three metrics, failure, strain, return."""
    records = []
    start = env.script.phase_start
    # One host copy of each per-world quantity (reading a tensor element is a call each).
    w_all = finished.tolist()
    idx = finished.cpu()
    now = env.scoring.now
    host = {
        name: x.detach().cpu()[idx].numpy()
        for name, x in (
            ("episode_length_buf", env.episode_length_buf),
            ("s_grasp", now.s_grasp),
            ("lift_ok", now.lift_ok),
            ("disturb_ok", now.disturb_ok),
            ("failure", now.failure),
            ("pads_at_lift", now.pads_at_lift),
            ("pads_at_hold", now.pads_at_hold),
            ("max_strain", env.record.max_strain),
            ("max_rise", now.max_rise),
            ("max_push_motion", now.max_push_motion),
            ("episode_return", env.record.returns),
            ("grasp_id", env.grasp.type_id),
        )
    }
    for j, w in enumerate(w_all):
        e = env.world_entries[w]
        t = int(host["episode_length_buf"][j])
        s_lift = bool(host["lift_ok"][j]) and t >= start["disturb"]
        s_disturb = (
            s_lift and bool(host["disturb_ok"][j]) and t >= start["release"] and env.script.disturb_dirs > 0
        )
        # A failed episode without a recorded cause was cut short before its hold: not lifted.
        label = failure_label(int(host["failure"][j]))
        failure = None if s_disturb else label or (None if s_lift else "not lifted")
        records.append(
            {
                "env": w,
                "object": e.id,
                "kind": e.kind,
                "family": e.family,
                "size_bin": e.size_bin,
                "grasp_type": GRASP_TYPES[int(host["grasp_id"][j])],
                "s_grasp": bool(host["s_grasp"][j]),
                "s_lift": s_lift,
                "s_disturb": s_disturb,
                "failure": failure,
                "pads_at_lift": _pad_list(host["pads_at_lift"][j]),
                "pads_at_hold": _pad_list(host["pads_at_hold"][j]),
                "max_strain": float(host["max_strain"][j]),
                "max_rise": float(host["max_rise"][j]),
                "max_push_motion": float(host["max_push_motion"][j]),
                "return": float(host["episode_return"][j]),
                "length": t,
                **env.record.localisation[w],  # camera perception: the episode's localisation error
            }
        )
    return records
