"""Success scoring (the paper's s_grasp, s_lift, s_disturb), terminations and episode records."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import torch

from d3grasp.dexhand13 import OPPOSING_PADS, THUMB_PADS
from d3grasp.envs.sensors import wp_view
from d3grasp.vocabulary import GRASP_TYPES

if TYPE_CHECKING:
    from d3grasp.envs.grasp_env import GraspEnv

GRASP_CONTACT_FORCE = 0.3  # N: a pad "in contact" for s_grasp
LIFT_TOLERANCE = 0.02  # m: s_lift needs the object raised by lift_height - this during the hold
DISTURB_TOLERANCE = 0.02  # m: s_disturb allows this much motion relative to the palm per push
PUSHED_OFF_DISTANCE = 0.25  # m of horizontal travel from the object's start: it left the table
BLOWUP_PAD_FORCE = 500.0  # N on one pad: the contact solve diverged


def score(
    env: GraspEnv, t: torch.Tensor, obj_pos: torch.Tensor, finite: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Update every world's success metrics after step ``t``; return (done, time_out)."""
    _update_metrics(env, t, obj_pos)
    return _terminations(env, t, obj_pos, finite)


def _update_metrics(env: GraspEnv, t: torch.Tensor, obj_pos: torch.Tensor) -> None:
    script, ph = env.script, env.cfg.phases
    palm = wp_view(env.state_0.body_q)[env.i_palm, :3]
    rise = obj_pos[:, 2] - env.object_start[:, 2]
    sensors = env.sensors
    if sensors.strain_layout is not None:
        env.max_strain = torch.maximum(env.max_strain, sensors.soft_scalar(sensors.strain_buf.object_eps))
    # s_grasp: at the end of the grasp phase, a thumb pad and an opposing finger pad in contact.
    end_grasp = t == script.phase_start["lift"]
    f = torch.linalg.norm(env.t_pad_force_true, dim=-1)
    thumb = (f[:, list(THUMB_PADS)] > GRASP_CONTACT_FORCE).any(-1)
    opposing = (f[:, list(OPPOSING_PADS)] > GRASP_CONTACT_FORCE).any(-1)
    env.s_grasp = torch.where(end_grasp, thumb & opposing, env.s_grasp)
    # s_lift: raised by lift_height (within tolerance) through the whole hold phase.
    in_hold = (t > script.phase_start["hold"]) & (t <= script.phase_start["disturb"])
    env.lift_ok &= ~(in_hold & (rise < ph.lift_height - LIFT_TOLERANCE))
    # s_disturb: under each push, object motion relative to the palm below the tolerance.
    rel = obj_pos - palm
    k_in = (t - script.phase_start["disturb"] - 1).clamp(min=0) % script.steps_per_push
    in_dist = (t > script.phase_start["disturb"]) & (t <= script.phase_start["release"])
    start_push = in_dist & (k_in == 0)
    env.push_ref = torch.where(start_push[:, None], rel, env.push_ref)
    moved = torch.linalg.norm(rel - env.push_ref, dim=-1)
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
    done = pushed_off | dropped | blowup | nonfinite | time_out
    for w in torch.nonzero(done & ~time_out).flatten().tolist():
        if env.failure[w] and not nonfinite[w]:
            continue  # evaluation runs on after a failure: keep the first cause
        env.failure[w] = (
            "non-finite state"
            if nonfinite[w]
            else "contact blow-up"
            if blowup[w]
            else "pushed off the table"
            if pushed_off[w]
            else "dropped"
        )
    if env.cfg.eval_mode:
        # Evaluation scores whole episodes: only a broken simulation ends one early.
        done = nonfinite | time_out
    return done, time_out & ~nonfinite


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
        failure = env.failure[w] or None
        if failure is None:
            failure = (
                None
                if s_disturb
                else "moved under disturbance"
                if s_lift
                else "not lifted"
                if bool(env.s_grasp[w])
                else "no grasp"
            )
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
                "max_strain": float(env.max_strain[w]),
                "return": float(env.episode_return[w]),
                "length": int(t[w]),
                **env.loc_records[w],  # camera perception: the episode's localisation error
            }
        )
    return records
