"""Success scoring (the paper's s_grasp, s_lift, s_disturb), terminations and episode records."""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Any

import torch

from d3grasp.dexhand13 import OPPOSING_PADS, PAD_NAMES, THUMB_PADS
from d3grasp.envs.script import DISTURB_NAMES
from d3grasp.vocabulary import GRASP_TYPES

if TYPE_CHECKING:
    from d3grasp.envs.grasp_env import GraspEnv

GRASP_CONTACT_FORCE = 0.3  # N: a pad touching the object (its contacts with the object alone)
LIFT_TOLERANCE = 0.02  # m: s_lift needs the object raised by lift_height - this during the hold
ROSE_WITH_PALM = 0.02  # m: an object that rose this far during the lift was lifted (then slipped)
DISTURB_TOLERANCE = 0.02  # m: s_disturb allows this much motion relative to the palm per push
PUSHED_OFF_DISTANCE = 0.25  # m of horizontal travel from the object's start: it left the table
BLOWUP_PAD_FORCE = 500.0  # N on one pad: the contact solve diverged

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
"""Why an episode failed, the first cause of each episode (``episode_records``' ``failure``)."""
HELD = "held through the pushes"


def episode_ending(record: dict[str, Any]) -> str:
    """How an episode record ended: ``HELD``, or its failure reason (``"not scored"`` for a record
    with neither)."""
    if record["s_disturb"]:
        return HELD
    return str(record.get("failure") or "not scored")


def pads_touching(pad_force_object: torch.Tensor) -> torch.Tensor:
    """(W, 11) bool: the pads with more than ``GRASP_CONTACT_FORCE`` of contact force from the object."""
    return torch.linalg.norm(pad_force_object, dim=-1) > GRASP_CONTACT_FORCE


def pad_grasp(pad_force_object: torch.Tensor) -> torch.Tensor:
    """(W,) bool: the pads show a grasp of the object: a thumb pad and an opposing finger pad each
    with more than ``GRASP_CONTACT_FORCE`` of contact force from the object (table contacts never
    count: ``pad_force_object`` holds the contacts with the object alone)."""
    return thumb_opposed(pads_touching(pad_force_object))


def thumb_opposed(touching: torch.Tensor) -> torch.Tensor:
    """(W,) bool: of the (W, 11) touching pads (:func:`pads_touching`), a thumb pad and an opposing
    finger pad."""
    thumb, opposing = _pad_masks(touching.device)
    return (touching & thumb).any(-1) & (touching & opposing).any(-1)


@functools.cache
def _pad_masks(device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(11,) bool masks of the thumb's pads and the opposing fingers' pads on ``device``, made once
    (indexing with a Python list converts the list on every call)."""
    masks = torch.zeros(2, len(PAD_NAMES), dtype=torch.bool, device=device)
    masks[0, list(THUMB_PADS)] = True
    masks[1, list(OPPOSING_PADS)] = True
    return masks[0], masks[1]


def score(
    env: GraspEnv, t: torch.Tensor, obj_pos: torch.Tensor, finite: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Update every world's success metrics after step ``t``; return (done, time_out)."""
    touching = pads_touching(env.t_pad_force_object)
    _time_lift(env, t, touching)
    _update_metrics(env, t, obj_pos, touching)
    return _terminations(env, t, obj_pos, finite)


def _time_lift(env: GraspEnv, t: torch.Tensor, touching: torch.Tensor) -> None:
    """Touch-timed lift: a world whose pads have shown a grasp (or whose rule-closed fingers have
    all stopped on the object) for ``grasp_settle`` s in a row during the grasp phase starts its
    lift with the next step (else at the grasp phase's end)."""
    ph = env.cfg.phases
    if not ph.lift_on_touch:
        return
    waiting = (t >= env.phase_start["grasp"]) & (t < env.lift_start)
    touch = thumb_opposed(touching)
    if env.residual_base is not None:
        # The rule runs inside the env (residual action modes): a hand closed as far as the object
        # lets it is ready too (a hook or a palm grasp need not touch with the thumb's pads).
        touch = touch | env.residual_base.settled()
    env.touch_steps = torch.where(waiting & touch, env.touch_steps + 1, torch.zeros_like(env.touch_steps))
    settle = max(1, round(ph.grasp_settle / env.dt))
    ready = waiting & (env.touch_steps >= settle)
    env.lift_start = torch.where(ready, torch.minimum(t + 1, env.lift_start), env.lift_start)


def _fail(env: GraspEnv, worlds: torch.Tensor, reason: str) -> None:
    """Record ``reason`` for ``worlds`` (W,) bool that have no failure yet (the first cause stays)."""
    for w in torch.nonzero(worlds).flatten().tolist():
        if not env.failure[w]:
            env.failure[w] = reason


def _update_metrics(env: GraspEnv, t: torch.Tensor, obj_pos: torch.Tensor, touching: torch.Tensor) -> None:
    script, ph = env.script, env.cfg.phases
    palm = env.t_body_q[env.i_palm, :3]
    rise = obj_pos[:, 2] - env.object_start[:, 2]
    sensors = env.sensors
    if sensors.strain_layout is not None:
        env.max_strain = torch.maximum(env.max_strain, sensors.soft_scalar(sensors.strain_buf.object_eps))
    tab, row = script.tables(t.device), script.row(t)
    # s_grasp: when the lift starts, a thumb pad and an opposing finger pad touch the object.
    at_lift = t == env.lift_start
    env.s_grasp = torch.where(at_lift, thumb_opposed(touching), env.s_grasp)
    env.pads_at_lift = torch.where(at_lift[:, None], touching, env.pads_at_lift)
    env.pads_at_hold = torch.where((t == script.phase_start["hold"])[:, None], touching, env.pads_at_hold)
    lifting = (t >= env.lift_start) & (t <= script.phase_start["hold"])
    env.max_rise = torch.where(lifting, torch.maximum(env.max_rise, rise), env.max_rise)
    # s_lift: raised by lift_height (within tolerance) through the whole hold phase.
    low = tab.in_hold_score[row] & (rise < ph.lift_height - LIFT_TOLERANCE) & env.lift_ok
    if low.any():
        # Down at the first step of the hold: it never got up (or slid out on the way); later: dropped.
        first = t == script.phase_start["hold"] + 1
        rose = env.max_rise >= ROSE_WITH_PALM
        _fail(env, low & first & ~rose & ~env.s_grasp, "no grasp")
        _fail(env, low & first & ~rose & env.s_grasp, "not lifted")
        _fail(env, low & first & rose, "slipped during the lift")
        _fail(env, low & ~first, "dropped in the hold")
    env.lift_ok &= ~low
    # s_disturb: under each push, object motion relative to the palm below the tolerance.
    rel = obj_pos - palm
    in_dist = tab.in_push_score[row]
    env.push_ref = torch.where(tab.push_started[row][:, None], rel, env.push_ref)
    moved = torch.linalg.norm(rel - env.push_ref, dim=-1)
    env.max_push_motion = torch.where(in_dist, torch.maximum(env.max_push_motion, moved), env.max_push_motion)
    lost = in_dist & (moved > DISTURB_TOLERANCE) & env.disturb_ok & env.lift_ok
    if lost.any():
        k = ((t - script.phase_start["disturb"] - 1).clamp(min=0) // script.steps_per_push).clamp(max=5)
        direction = env.disturb_order[torch.arange(env.num_envs, device=t.device), k]
        for w in torch.nonzero(lost).flatten().tolist():
            if not env.failure[w]:
                env.failure[w] = f"lost under a push ({DISTURB_NAMES[int(direction[w])]})"
    env.disturb_ok &= ~(in_dist & (moved > DISTURB_TOLERANCE))


def _terminations(env: GraspEnv, t, obj_pos, finite) -> tuple[torch.Tensor, torch.Tensor]:
    rise = obj_pos[:, 2] - env.object_start[:, 2]
    horizontal = torch.linalg.norm(obj_pos[:, :2] - env.object_start[:, :2], dim=-1)
    pushed_off = horizontal > PUSHED_OFF_DISTANCE
    after_lift = t > env.script.phase_start["hold"]
    dropped = after_lift & (rise < 0.5 * env.cfg.phases.lift_height)
    blowup = torch.linalg.norm(env.t_pad_force_true, dim=-1).max(-1).values > BLOWUP_PAD_FORCE
    nonfinite = ~finite
    env.nonfinite_resets += int(nonfinite.sum())
    time_out = t >= env.max_episode_length
    for w in torch.nonzero(nonfinite).flatten().tolist():
        env.failure[w] = "non-finite state"  # overrides: a broken simulation scores nothing
    _fail(env, blowup, "contact blow-up")
    _fail(env, pushed_off, "pushed off the table")
    # A dropped object was labelled by the metrics when it went below the lift height.
    done = pushed_off | dropped | blowup | nonfinite | time_out
    if env.cfg.eval_mode:
        # Evaluation scores whole episodes: only a broken simulation ends one early.
        done = nonfinite | time_out
    return done, time_out & ~nonfinite


def _pad_list(touching: torch.Tensor) -> list[str]:
    return [PAD_NAMES[i] for i in torch.nonzero(touching).flatten().tolist()]


def episode_records(env: GraspEnv, finished: torch.Tensor) -> list[dict[str, Any]]:
    """One record per finished world: object, grasp type, the three metrics, failure, strain, return."""
    records = []
    t = env.episode_length_buf
    start = env.script.phase_start
    for w in finished.tolist():
        e = env.world_entries[w]
        s_lift = bool(env.lift_ok[w]) and int(t[w]) >= start["disturb"]
        s_disturb = (
            s_lift
            and bool(env.disturb_ok[w])
            and int(t[w]) >= start["release"]
            and env.script.disturb_dirs > 0
        )
        # A failed episode without a recorded cause was cut short before its hold: not lifted.
        failure = None if s_disturb else env.failure[w] or (None if s_lift else "not lifted")
        records.append(
            {
                "env": w,
                "object": e.id,
                "kind": e.kind,
                "family": e.family,
                "size_bin": e.size_bin,
                "grasp_type": GRASP_TYPES[int(env.grasp_id[w])],
                "s_grasp": bool(env.s_grasp[w]),
                "s_lift": s_lift,
                "s_disturb": s_disturb,
                "failure": failure,
                "pads_at_lift": _pad_list(env.pads_at_lift[w]),
                "pads_at_hold": _pad_list(env.pads_at_hold[w]),
                "max_strain": float(env.max_strain[w]),
                "max_rise": float(env.max_rise[w]),
                "max_push_motion": float(env.max_push_motion[w]),
                "return": float(env.episode_return[w]),
                "length": int(t[w]),
                **env.loc_records[w],  # camera perception: the episode's localisation error
            }
        )
    return records
