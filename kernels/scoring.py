"""The paper's success metrics and the episode's terminations for all worlds, one thread a world.

After each control step ``t`` (the state the step left), per world ``w``:

- **Touch-timed lift** (``lift_on_touch``): during the grasp phase, before its lift has started, a
  world whose pads show a grasp (a thumb pad and an opposing finger pad each with more than
  ``GRASP_CONTACT_FORCE`` from the object), or whose rule has settled (``rule_settled``; False where
  no rule runs in the environment), counts the steps in a row it has done so; after
  ``settle_steps`` its lift starts at ``t + 1``. With ``lift_on_pads`` 0 only the rule's settling
  counts (the proprioceptive closing prior of the Base ablation: no touch times its lift).
- **s_grasp**: at the step the lift starts, the pads show a grasp. The pads touching the object then
  and at the hold's start are kept for the records.
- **s_lift**: during the hold's scoring window the object stays within ``LIFT_TOLERANCE`` of
  ``lift_height`` above its start; the first step below ends it, with the cause: below at the hold's
  first step and never risen ``ROSE_WITH_PALM`` during the lift: "no grasp" (or "not lifted" with
  s_grasp); risen and fallen back: "slipped during the lift"; later: "dropped in the hold".
- **s_disturb**: in each push's scoring window the object moves less than ``DISTURB_TOLERANCE``
  relative to the palm from where it was at the push's first scored step; the first that moves more
  (while s_lift holds) is "lost under a push" in that push's direction.
- **Terminations**: pushed off the table (``PUSHED_OFF_DISTANCE`` of horizontal travel), dropped
  (below half the lift height after the lift), a contact blow-up (a pad over ``BLOWUP_PAD_FORCE``), a
  non-finite state (it overrides any earlier cause) and the time-out. In evaluation only a
  non-finite state or the time-out ends an episode.

Each world keeps the first failure cause as a code (:data:`FAILURE_CODES`). The schedule's windows
come from the episode script's tables; ``score_step_numpy`` is the NumPy twin of the kernel.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import warp as wp

__all__ = [
    "BLOWUP_PAD_FORCE",
    "DISTURB_TOLERANCE",
    "FAILURE_CODES",
    "GRASP_CONTACT_FORCE",
    "LIFT_TOLERANCE",
    "PUSHED_OFF_DISTANCE",
    "ROSE_WITH_PALM",
    "ScoreInputs",
    "ScoreParams",
    "ScoreSchedule",
    "ScoreState",
    "score_step",
    "score_step_numpy",
]

GRASP_CONTACT_FORCE = 0.3  # N: a pad touching the object (its contacts with the object alone)
LIFT_TOLERANCE = 0.02  # m: s_lift needs the object raised by lift_height - this during the hold
ROSE_WITH_PALM = 0.02  # m: an object that rose this far during the lift was lifted (then slipped)
DISTURB_TOLERANCE = 0.02  # m: s_disturb allows this much motion relative to the palm per push
PUSHED_OFF_DISTANCE = 0.25  # m of horizontal travel from the object's start: it left the table
BLOWUP_PAD_FORCE = 500.0  # N on one pad: the contact solve diverged

# The first failure cause of an episode; 0: none. A loss under a push is LOST_UNDER_PUSH plus the
# push's direction index (0-5: +x, -x, +y, -y, +z, -z).
NO_GRASP, NOT_LIFTED, SLIPPED, DROPPED, LOST_UNDER_PUSH = 1, 2, 3, 4, 5
PUSHED_OFF, BLOWUP, NON_FINITE = 11, 12, 13
FAILURE_CODES = {
    "no grasp": NO_GRASP,
    "not lifted": NOT_LIFTED,
    "slipped during the lift": SLIPPED,
    "dropped in the hold": DROPPED,
    "lost under a push": LOST_UNDER_PUSH,
    "pushed off the table": PUSHED_OFF,
    "contact blow-up": BLOWUP,
    "non-finite state": NON_FINITE,
}
"""Code of each failure cause (a loss under a push adds its direction's index to its code)."""

# Pad roles (``ScoreSchedule.pad_role``): a grasp needs a thumb pad and an opposing finger pad.
PAD_OTHER, PAD_THUMB, PAD_OPPOSING = 0, 1, 2


@wp.struct
class ScoreParams:
    """The schedule's step numbers and the settings the scoring reads."""

    grasp_start: int  # first step of the grasp phase
    hold_start: int  # first step of the hold phase
    max_episode_length: int
    settle_steps: int  # steps in a row of touch before a touch-timed lift starts
    lift_on_touch: int  # 1: touch times the lift
    lift_on_pads: int  # 1: the pads' grasp counts as touch; 0: only the rule's settling does
    eval_mode: int  # 1: only a non-finite state or the time-out ends an episode
    lift_height: float


@dataclass
class ScoreSchedule:
    """Read-only per-step and per-pad tables: the script's scoring windows by table row (bool, one row
    per step up to ``max_episode_length + 1``), the push whose result a step scores (int32) and each
    pad's role (int32)."""

    in_hold_score: wp.array
    in_push_score: wp.array
    push_started: wp.array
    scored_push: wp.array
    pad_role: wp.array


@dataclass
class ScoreInputs:
    """What the step left, per world: its step count ``t`` (int64), the object's position (vec3), whether
    the state is finite and whether the rule-based closing has settled (bool; in the residual action
    modes, where a hand closed as far as the object lets it is ready to lift too), the pads' forces
    from the object and in all (W, P) vec3, the bodies' poses (transform; the palm's by ``palm_body``
    int32), the object's start position (vec3) and the episode's push order (W, 6) int64."""

    t: wp.array
    obj_pos: wp.array
    finite: wp.array
    rule_settled: wp.array
    pad_force_object: wp.array
    pad_force_true: wp.array
    body_q: wp.array
    palm_body: wp.array
    object_start: wp.array
    disturb_order: wp.array


@dataclass
class ScoreState:
    """Per world, carried through an episode (a reset restarts it): the lift's start step and the
    steps of touch before it (int64), s_grasp, the pads touching at the lift's start and at the hold's
    (W, P), the highest rise during the lift, whether s_lift and s_disturb still hold, the push's
    reference offset from the palm, the most the object moved in a push, the first failure code
    (int32), the count of non-finite states met (1,) int32, and whether the step ended the episode
    (``done``; every end is a true terminal for PPO: the horizon is fixed and the clock observed)."""

    lift_start: wp.array
    touch_steps: wp.array
    s_grasp: wp.array
    pads_at_lift: wp.array
    pads_at_hold: wp.array
    max_rise: wp.array
    lift_ok: wp.array
    disturb_ok: wp.array
    push_ref: wp.array
    max_push_motion: wp.array
    failure: wp.array
    nonfinite_count: wp.array
    done: wp.array

    @classmethod
    def allocate(
        cls, num_worlds: int, num_pads: int, lift_start: int, device: wp.DeviceLike = None
    ) -> ScoreState:
        """A fresh state: every lift at ``lift_start``, s_lift and s_disturb holding, nothing else."""
        W, dev = num_worlds, wp.get_device(device)
        return cls(
            lift_start=wp.full(W, lift_start, dtype=wp.int64, device=dev),
            touch_steps=wp.zeros(W, dtype=wp.int64, device=dev),
            s_grasp=wp.zeros(W, dtype=wp.bool, device=dev),
            pads_at_lift=wp.zeros((W, num_pads), dtype=wp.bool, device=dev),
            pads_at_hold=wp.zeros((W, num_pads), dtype=wp.bool, device=dev),
            max_rise=wp.zeros(W, dtype=float, device=dev),
            lift_ok=wp.full(W, True, dtype=wp.bool, device=dev),
            disturb_ok=wp.full(W, True, dtype=wp.bool, device=dev),
            push_ref=wp.zeros(W, dtype=wp.vec3, device=dev),
            max_push_motion=wp.zeros(W, dtype=float, device=dev),
            failure=wp.zeros(W, dtype=wp.int32, device=dev),
            nonfinite_count=wp.zeros(1, dtype=wp.int32, device=dev),
            done=wp.zeros(W, dtype=wp.bool, device=dev),
        )

    def numpy(self) -> dict[str, np.ndarray]:
        """Host copies of every field (a CPU array's ``numpy()`` shares its memory)."""
        return {f.name: getattr(self, f.name).numpy().copy() for f in fields(self)}


@wp.func
def _nan_max(a: float, b: float) -> float:
    """max(a, b), NaN when either is (as torch.maximum)."""
    if wp.isnan(a):
        return a
    if wp.isnan(b):
        return b
    return wp.max(a, b)


@wp.func
def _first_failure(failure: wp.array(dtype=wp.int32), w: int, code: int):
    if failure[w] == 0:
        failure[w] = code


@wp.func
def _pads_show_grasp(
    pad_force_object: wp.array2d(dtype=wp.vec3), pad_role: wp.array(dtype=wp.int32), w: int
) -> bool:
    """Whether world ``w``'s pads show a grasp: a thumb pad and an opposing finger pad each touch the
    object (more than ``GRASP_CONTACT_FORCE`` from it)."""
    thumb = bool(False)  # noqa: UP018  (a typed variable: Warp mutates no literal in a loop)
    opposing = bool(False)  # noqa: UP018  (a typed variable: Warp mutates no literal in a loop)
    for p in range(pad_force_object.shape[1]):
        if wp.length(pad_force_object[w, p]) > GRASP_CONTACT_FORCE:
            if pad_role[p] == PAD_THUMB:
                thumb = True
            if pad_role[p] == PAD_OPPOSING:
                opposing = True
    return thumb and opposing


@wp.func
def _terminations(
    prm: ScoreParams,
    w: int,
    t: int,
    pos: wp.vec3,
    rise: float,
    object_start: wp.array(dtype=wp.vec3),
    pad_force_true: wp.array2d(dtype=wp.vec3),
    finite: wp.array(dtype=wp.bool),
    failure: wp.array(dtype=wp.int32),
    nonfinite_count: wp.array(dtype=wp.int32),
    done: wp.array(dtype=wp.bool),
):
    """World ``w``'s terminations at step ``t`` (module docstring): their failure causes and ``done``."""
    d = wp.vec2(pos[0] - object_start[w][0], pos[1] - object_start[w][1])
    pushed_off = wp.length(d) > PUSHED_OFF_DISTANCE
    dropped = t > prm.hold_start and rise < 0.5 * prm.lift_height
    # The largest pad force over the limit (a NaN among them makes the largest NaN: no blow-up).
    largest = float(0.0)  # noqa: UP018  (a typed variable: Warp mutates no literal in a loop)
    for p in range(pad_force_true.shape[1]):
        largest = _nan_max(largest, wp.length(pad_force_true[w, p]))
    blowup = largest > BLOWUP_PAD_FORCE
    nonfinite = not finite[w]
    ended = t >= prm.max_episode_length
    if nonfinite:
        wp.atomic_add(nonfinite_count, 0, 1)
        failure[w] = NON_FINITE  # overrides: a broken simulation scores nothing
    if blowup:
        _first_failure(failure, w, BLOWUP)
    if pushed_off:
        _first_failure(failure, w, PUSHED_OFF)
    if prm.eval_mode != 0:
        done[w] = nonfinite or ended
    else:
        done[w] = pushed_off or dropped or blowup or nonfinite or ended


@wp.kernel
def _score_kernel(
    prm: ScoreParams,
    in_hold_score: wp.array(dtype=wp.bool),
    in_push_score: wp.array(dtype=wp.bool),
    push_started: wp.array(dtype=wp.bool),
    scored_push: wp.array(dtype=wp.int32),
    pad_role: wp.array(dtype=wp.int32),
    t_step: wp.array(dtype=wp.int64),
    obj_pos: wp.array(dtype=wp.vec3),
    finite: wp.array(dtype=wp.bool),
    rule_settled: wp.array(dtype=wp.bool),
    pad_force_object: wp.array2d(dtype=wp.vec3),
    pad_force_true: wp.array2d(dtype=wp.vec3),
    body_q: wp.array(dtype=wp.transform),
    palm_body: wp.array(dtype=wp.int32),
    object_start: wp.array(dtype=wp.vec3),
    disturb_order: wp.array2d(dtype=wp.int64),
    lift_start: wp.array(dtype=wp.int64),
    touch_steps: wp.array(dtype=wp.int64),
    s_grasp: wp.array(dtype=wp.bool),
    pads_at_lift: wp.array2d(dtype=wp.bool),
    pads_at_hold: wp.array2d(dtype=wp.bool),
    max_rise: wp.array(dtype=float),
    lift_ok: wp.array(dtype=wp.bool),
    disturb_ok: wp.array(dtype=wp.bool),
    push_ref: wp.array(dtype=wp.vec3),
    max_push_motion: wp.array(dtype=float),
    failure: wp.array(dtype=wp.int32),
    nonfinite_count: wp.array(dtype=wp.int32),
    done: wp.array(dtype=wp.bool),
):
    w = wp.tid()
    t = int(t_step[w])
    row = wp.clamp(t, 0, prm.max_episode_length + 1)
    grasp = _pads_show_grasp(pad_force_object, pad_role, w)

    # Touch-timed lift.
    start = int(lift_start[w])
    if prm.lift_on_touch != 0:
        waiting = t >= prm.grasp_start and t < start
        touch = (grasp and prm.lift_on_pads != 0) or rule_settled[w]
        steps = int(0)  # noqa: UP018  (a typed variable: Warp mutates no literal in a loop)
        if waiting and touch:
            steps = int(touch_steps[w]) + 1
        touch_steps[w] = wp.int64(steps)
        if waiting and steps >= prm.settle_steps:
            start = wp.min(t + 1, start)
            lift_start[w] = wp.int64(start)

    # s_grasp, and the pads touching at the lift's start and the hold's.
    palm = wp.transform_get_translation(body_q[palm_body[w]])
    pos = obj_pos[w]
    rise = pos[2] - object_start[w][2]
    if t == start:
        s_grasp[w] = grasp
    for p in range(pad_force_object.shape[1]):
        touching = wp.length(pad_force_object[w, p]) > GRASP_CONTACT_FORCE
        if t == start:
            pads_at_lift[w, p] = touching
        if t == prm.hold_start:
            pads_at_hold[w, p] = touching
    if t >= start and t <= prm.hold_start:
        max_rise[w] = _nan_max(max_rise[w], rise)

    # s_lift: raised by lift_height (within tolerance) through the hold's scoring window.
    if in_hold_score[row] and rise < prm.lift_height - LIFT_TOLERANCE and lift_ok[w]:
        if t == prm.hold_start + 1:
            if max_rise[w] >= ROSE_WITH_PALM:
                _first_failure(failure, w, SLIPPED)
            elif s_grasp[w]:
                _first_failure(failure, w, NOT_LIFTED)
            else:
                _first_failure(failure, w, NO_GRASP)
        else:
            _first_failure(failure, w, DROPPED)
        lift_ok[w] = False

    # s_disturb: motion relative to the palm from where the push's scoring began.
    rel = pos - palm
    if push_started[row]:
        push_ref[w] = rel
    moved = wp.length(rel - push_ref[w])
    if in_push_score[row]:
        max_push_motion[w] = _nan_max(max_push_motion[w], moved)
        if moved > DISTURB_TOLERANCE:
            if disturb_ok[w] and lift_ok[w]:
                k = scored_push[row]
                _first_failure(failure, w, LOST_UNDER_PUSH + int(disturb_order[w, k]))
            disturb_ok[w] = False

    # Terminations.
    _terminations(prm, w, t, pos, rise, object_start, pad_force_true, finite, failure, nonfinite_count, done)


def score_step(prm: ScoreParams, sched: ScoreSchedule, inp: ScoreInputs, state: ScoreState) -> None:
    """Score every world after one step (one launch, no host sync: graph-capturable)."""
    wp.launch(
        _score_kernel,
        dim=state.lift_start.shape[0],
        inputs=[
            prm,
            sched.in_hold_score,
            sched.in_push_score,
            sched.push_started,
            sched.scored_push,
            sched.pad_role,
            inp.t,
            inp.obj_pos,
            inp.finite,
            inp.rule_settled,
            inp.pad_force_object,
            inp.pad_force_true,
            inp.body_q,
            inp.palm_body,
            inp.object_start,
            inp.disturb_order,
        ],
        outputs=[getattr(state, f.name) for f in fields(state)],
        device=state.lift_start.device,
    )


def _first_failure_numpy(failure: np.ndarray, worlds: np.ndarray, code: np.ndarray | int) -> None:
    code = np.broadcast_to(code, failure.shape)
    set_ = worlds & (failure == 0)
    failure[set_] = code[set_]


def score_step_numpy(
    prm: ScoreParams, sched: dict[str, np.ndarray], inp: dict[str, np.ndarray], s: dict
) -> None:
    """NumPy twin of :func:`score_step`: the same rules, vectorised over the worlds, on host arrays
    (``inp``: the fields of :class:`ScoreInputs` with ``body_q`` (B, 7) position and xyzw quaternion;
    ``sched`` and ``s``: those of :class:`ScoreSchedule` and :class:`ScoreState`); updates ``s``."""
    t = inp["t"].astype(np.int64)
    W = len(t)
    row = np.clip(t, 0, prm.max_episode_length + 1)
    touching = np.linalg.norm(inp["pad_force_object"], axis=-1) > GRASP_CONTACT_FORCE
    role = sched["pad_role"]
    grasp = (touching & (role == PAD_THUMB)).any(-1) & (touching & (role == PAD_OPPOSING)).any(-1)
    if prm.lift_on_touch:
        waiting = (t >= prm.grasp_start) & (t < s["lift_start"])
        touch = (grasp & bool(prm.lift_on_pads)) | inp["rule_settled"]
        s["touch_steps"] = np.where(waiting & touch, s["touch_steps"] + 1, 0)
        ready = waiting & (s["touch_steps"] >= prm.settle_steps)
        s["lift_start"] = np.where(ready, np.minimum(t + 1, s["lift_start"]), s["lift_start"])
    palm = inp["body_q"][inp["palm_body"], :3]
    pos = inp["obj_pos"]
    rise = pos[:, 2] - inp["object_start"][:, 2]
    at_lift = t == s["lift_start"]
    s["s_grasp"] = np.where(at_lift, grasp, s["s_grasp"])
    s["pads_at_lift"] = np.where(at_lift[:, None], touching, s["pads_at_lift"])
    s["pads_at_hold"] = np.where((t == prm.hold_start)[:, None], touching, s["pads_at_hold"])
    lifting = (t >= s["lift_start"]) & (t <= prm.hold_start)
    with np.errstate(invalid="ignore"):
        s["max_rise"] = np.where(lifting, np.maximum(s["max_rise"], rise), s["max_rise"])
        low = sched["in_hold_score"][row] & (rise < prm.lift_height - LIFT_TOLERANCE) & s["lift_ok"]
    first = t == prm.hold_start + 1
    rose = s["max_rise"] >= ROSE_WITH_PALM
    cause = np.where(~first, DROPPED, np.where(rose, SLIPPED, np.where(s["s_grasp"], NOT_LIFTED, NO_GRASP)))
    _first_failure_numpy(s["failure"], low, cause)
    s["lift_ok"] = s["lift_ok"] & ~low
    rel = pos - palm
    s["push_ref"] = np.where(sched["push_started"][row][:, None], rel, s["push_ref"])
    moved = np.linalg.norm(rel - s["push_ref"], axis=-1)
    in_push = sched["in_push_score"][row]
    with np.errstate(invalid="ignore"):
        s["max_push_motion"] = np.where(
            in_push, np.maximum(s["max_push_motion"], moved), s["max_push_motion"]
        )
        far = in_push & (moved > DISTURB_TOLERANCE)
    direction = inp["disturb_order"][np.arange(W), sched["scored_push"][row]]
    _first_failure_numpy(s["failure"], far & s["disturb_ok"] & s["lift_ok"], LOST_UNDER_PUSH + direction)
    s["disturb_ok"] = s["disturb_ok"] & ~far
    with np.errstate(invalid="ignore"):
        pushed_off = np.linalg.norm(pos[:, :2] - inp["object_start"][:, :2], axis=-1) > PUSHED_OFF_DISTANCE
        dropped = (t > prm.hold_start) & (rise < 0.5 * prm.lift_height)
        blowup = np.linalg.norm(inp["pad_force_true"], axis=-1).max(-1) > BLOWUP_PAD_FORCE
    nonfinite = ~inp["finite"]
    ended = t >= prm.max_episode_length
    s["nonfinite_count"] = s["nonfinite_count"] + int(nonfinite.sum())
    s["failure"][nonfinite] = NON_FINITE
    _first_failure_numpy(s["failure"], blowup, BLOWUP)
    _first_failure_numpy(s["failure"], pushed_off, PUSHED_OFF)
    s["done"] = (nonfinite | ended) if prm.eval_mode else (pushed_off | dropped | blowup | nonfinite | ended)
