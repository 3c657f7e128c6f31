"""Study: replay a lost episode under SolverVBD and under SolverMuJoCo (issue 60: physics or grasp?).

docs/studies/grasp_anatomy.md found most episodes lost under a push with "friction to spare by the
pad forces" (mu x grip above the push's load of weight + 2.5 N), mostly frustum_04 and frustum_09
under a top grasp. This tool tells the contact model from the grasp:

1. **Record**: one evaluation episode (``eval_mode``, the rule-based baseline, the true pose, one
   world) runs in the d3grasp environment under SolverVBD. Each control step's inputs to the physics
   are recorded through the environment's ``step_launcher`` hook: the finger joint targets, the
   kinematic palm's path (start and end position, orientation, wrist yaw) and the push.
2. **Replay open-loop** from the episode's initial state, in a fresh single-world model built by the
   same ``build_scene`` with the episode's masses, frictions and drive gains written into it:
   (a) SolverVBD through the environment's own ``Physics`` (same substeps, iterations, collision
   pipeline): it must reproduce the episode, which validates the replay;
   (b) SolverMuJoCo (MuJoCo's C engine on the CPU, ``use_mujoco_cpu=True``), elliptic cones, at
   ``impratio`` 1 and 10 (and whatever else ``--variants`` names).
   The finger targets and the palm path are the recorded ones; the pushes follow the evaluation's
   schedule (six 2 s pushes of 2.5 N) and stop, as in the environment, once the replay's own object
   has failed the lift or left the grip.
3. **Score** every run with the evaluation's rules (d3grasp.kernels.scoring): the lift (within 2 cm of
   the 10 cm rise through the hold) and, per push, the object's motion relative to the palm (2 cm).
   Per push: the maximum motion, the pads' normal force on the object (``Sensors.pad_force_object``,
   the anatomy study's grip) and every hand link's normal force on the object (the palm included).

What the MuJoCo model gets (SolverMuJoCo's own conversion of the Newton model, with three study
overrides, each printed):

- the same bodies, masses and inertias; the kinematic palm becomes a free body held by a weld that
  Newton re-centres every step on the pose written into ``state.joint_q`` (``BodyFlags.KINEMATIC``):
  the study writes the recorded path there (pose at the substep's start, velocity over the step);
- finger drives as position actuators with the environment's ``joint_target_ke`` / ``kd`` and a force
  limit of the hand's ``joint_effort_limit`` (10 N m: SolverVBD does not apply it);
- MuJoCo's own collision detection (the CPU backend cannot take Newton's contacts): the hand's boxes
  as boxes, the object's convex hull as a MuJoCo mesh (its convex hull), multi-CCD on by default;
- contact softness: MuJoCo's default solref (0.02, 1) / solimp (Newton's conversion), not VBD's
  penalty stiffness;
- override 1, friction: MuJoCo takes the larger of two geoms' coefficients, SolverVBD their geometric
  mean; every geom gets the geometric mean of the hand's and the object's (the pair value VBD uses);
- override 2, gap: Newton's 5 mm detection gap maps onto MuJoCo's ``gap``, which in MuJoCo makes
  contacts inactive until 5 mm of penetration (``includemargin = margin - gap``); set to 0;
- timestep: the environment's substep (1/600 s), implicitfast integrator, Newton solver.

    PYTHONPATH=/tmp/mjsite python tools/mujoco_replay_study.py --objects frustum_09 frustum_04 \\
        --seeds 0 --out /tmp/mjstudy/replay.json
    python tools/mujoco_replay_study.py --report /tmp/mjstudy/replay.json

MuJoCo is not a dependency of the project: install it for the study only (see
docs/studies/mujoco_replay.md). One process, one world per run.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

TASK = "D3Grasp-DexHand13-Mixed-v0"
PUSH_NAMES = ("+x", "-x", "+y", "-y", "+z", "-z")
# name -> SolverMuJoCo keyword arguments (use_mujoco_cpu and the study's overrides are added)
VARIANTS: dict[str, dict[str, Any]] = {
    "mujoco_elliptic": {"cone": "elliptic", "impratio": 1.0, "enable_multiccd": True},
    "mujoco_elliptic_imp10": {"cone": "elliptic", "impratio": 10.0, "enable_multiccd": True},
    "mujoco_elliptic_1ccd": {"cone": "elliptic", "impratio": 1.0, "enable_multiccd": False},
    "mujoco_pyramidal": {"cone": "pyramidal", "impratio": 1.0, "enable_multiccd": True},
}
DEFAULT_VARIANTS = ("mujoco_elliptic", "mujoco_elliptic_imp10")


def require_mujoco() -> None:
    """Exit with one line if MuJoCo's Python package is missing (the project does not depend on it)."""
    try:
        import mujoco  # noqa: F401
    except ImportError:
        sys.exit(
            "mujoco_replay_study: the 'mujoco' package is not importable; install it for the study only "
            '(pip install --target /tmp/mjsite --no-deps "mujoco~=3.17.0" "mujoco-warp~=3.17.0") '
            "and run with PYTHONPATH=/tmp/mjsite"
        )


# ----------------------------------------------------------------------------------------------
# Recording the environment's episode
# ----------------------------------------------------------------------------------------------


@dataclass
class Recording:
    object_id: str
    seed: int
    cfg: Any  # GraspEnvConfig
    entry: Any  # AssetEntry
    usd_path: Path
    model_arrays: dict[str, np.ndarray]
    state0: dict[str, np.ndarray]
    inputs: list[dict[str, np.ndarray]] = field(default_factory=list)  # per control step
    env_run: dict[str, Any] = field(default_factory=dict)  # the env's own trace and episode record


MODEL_ARRAYS = (
    "joint_q",
    "body_mass",
    "body_inv_mass",
    "body_inertia",
    "body_inv_inertia",
    "shape_material_mu",
    "joint_target_ke",
    "joint_target_kd",
)


def record_episode(object_id: str, seed: int, log=print, max_steps: int | None = None) -> Recording:
    """Run the evaluation's episode of ``object_id`` at ``seed`` (one world) and record its inputs."""
    import torch

    from d3grasp.authoring.manifest import resolve_asset_path
    from d3grasp.controllers import make_controller
    from d3grasp.envs import make_env
    from d3grasp.seeding import seed_everything

    seed_everything(seed)
    env = make_env(
        TASK,
        num_envs=1,
        device="cpu",
        seed=seed,
        eval_mode=True,
        objects={"ids": (object_id,)},
        perception="oracle",
    )
    ph, lay, model = env.physics, env.layout, env.model
    entry = env.world_entries[0]
    rec = Recording(
        object_id=object_id,
        seed=seed,
        cfg=env.cfg,
        entry=entry,
        usd_path=resolve_asset_path(env.manifest_path, entry),
        model_arrays={k: getattr(model, k).numpy().copy() for k in MODEL_ARRAYS},
        state0={
            k: getattr(ph.state_0, k).numpy().copy() for k in ("joint_q", "joint_qd", "body_q", "body_qd")
        },
    )
    rec.model_arrays["joint_target_q"] = ph.control.joint_target_q.numpy().copy()
    trace = Trace()

    def launcher() -> None:
        rec.inputs.append(
            {
                "target": ph.control.joint_target_q.numpy().copy(),
                "pos_start": ph.palm_pos_start.numpy()[0].copy(),
                "pos_end": ph.palm_pos_end.numpy()[0].copy(),
                "quat": ph.palm_quat.numpy()[0].copy(),
                "yaw_start": float(ph.palm_yaw_start.numpy()[0]),
                "yaw_end": float(ph.palm_yaw_end.numpy()[0]),
                "force": ph.object_force.numpy()[0].copy(),
            }
        )
        env.launch_step()
        trace.add(ph.state_0, lay, env.sensors, ph.contacts, ph.observables, update=False)

    env.step_launcher = launcher
    controller = make_controller(env, TASK, "baseline", "cpu")
    obs = env.get_observations()
    episode = None
    with torch.inference_mode():
        for _ in range(int(max_steps or env.max_episode_length)):
            obs, _, dones, extras = env.step(controller.act(obs).to(env.device))
            controller.on_dones(dones)
            if extras.get("episodes"):
                episode = extras["episodes"][0]
                break
    env.step_launcher = None
    keep = ("failure", "s_grasp", "s_lift", "s_disturb", "max_rise", "max_push_motion", "grasp_type")
    rec.env_run = {"episode": {k: episode.get(k) for k in keep} if episode else None, "trace": trace}
    rec.env_run["disturb_start"] = int(env.script.phase_start["disturb"])
    env.close()
    log(f"  recorded {object_id} seed {seed}: {len(rec.inputs)} steps, env outcome {rec.env_run['episode']}")
    return rec


# ----------------------------------------------------------------------------------------------
# Per-step trace: object, palm, grip
# ----------------------------------------------------------------------------------------------


class Trace:
    """Object and palm positions and the grip after every control step."""

    def __init__(self) -> None:
        self.obj: list[np.ndarray] = []
        self.palm: list[np.ndarray] = []
        self.pad_normal: list[float] = []  # sum of the pads' normal forces on the object (pad frames)
        self.hand_normal: list[float] = []  # every hand shape's normal force on the object (contacts)
        self.pads_touching: list[int] = []

    def add(self, state, lay, sensors, contacts, observables, update: bool = True) -> None:
        """Read the state after a control step; ``update``: run the sensors first (the environment's
        own step has already run them: they are read as they are, not run twice)."""
        bq = state.body_q.numpy()
        self.obj.append(bq[lay.object_body[0], :3].copy())
        self.palm.append(bq[lay.palm_body[0], :3].copy())
        if sensors is not None:
            if update:
                sensors.update(state, contacts, observables)
            f = sensors.pad_force_object.numpy()[0]
            self.pad_normal.append(float(np.abs(f[:, 2]).sum()))
            self.pads_touching.append(int((np.linalg.norm(f, axis=1) > 0.3).sum()))
        self.hand_normal.append(hand_object_normal(lay, contacts, observables))

    def to_arrays(self) -> dict[str, np.ndarray]:
        return {
            "obj": np.array(self.obj),
            "palm": np.array(self.palm),
            "pad_normal": np.array(self.pad_normal),
            "hand_normal": np.array(self.hand_normal),
            "pads_touching": np.array(self.pads_touching),
        }


def hand_object_normal(lay, contacts, observables) -> float:
    """Sum of |f . n| over the contacts between a hand shape and the object (N)."""
    n = int(contacts.rigid_contact_count.numpy()[0])
    if n == 0:
        return 0.0
    s0 = contacts.rigid_contact_shape0.numpy()[:n]
    s1 = contacts.rigid_contact_shape1.numpy()[:n]
    normal = contacts.rigid_contact_normal.numpy()[:n]
    f = observables.contact_f.numpy()[:n, :3]
    hand, obj = set(lay.hand_shapes[0].tolist()), set(lay.object_shapes[0].tolist())
    sel = np.array(
        [(a in hand and b in obj) or (a in obj and b in hand) for a, b in zip(s0, s1, strict=True)],
        dtype=bool,
    )
    return float(np.abs(np.einsum("ij,ij->i", f[sel], normal[sel])).sum())


# ----------------------------------------------------------------------------------------------
# Scoring (d3grasp.kernels.scoring's rules on the trace)
# ----------------------------------------------------------------------------------------------


class Scorer:
    """The evaluation's s_lift and s_disturb, step by step, and what the push should be."""

    def __init__(self, cfg, obj_start: np.ndarray) -> None:
        from d3grasp.envs.script import EpisodeScript

        self.script = EpisodeScript(cfg.phases, cfg.sim.control_hz, True, cfg.obs.clock_period)
        self.tab = self.script.tables(__import__("torch").device("cpu"))
        self.lift_height = cfg.phases.lift_height
        self.force = cfg.phases.disturb_force
        self.obj_start = obj_start
        self.lift_ok = True
        self.disturb_ok = True
        self.failure = None
        self.max_rise = 0.0
        self.push_ref = np.zeros(3)
        self.push_motion = np.zeros(6)
        self.push_profile = np.full((6, self.script.steps_per_push), np.nan)  # motion per scored step

    def push(self, n: int) -> np.ndarray:
        """The push applied during step ``n`` (1-based step count after it), zero once failed."""
        slot = int(self.tab.push_slot[min(n, self.script.max_episode_length + 1)])
        if slot >= 6 or not (self.lift_ok and self.disturb_ok):
            return np.zeros(3)
        return self.tab.push_dirs[slot].numpy().astype(np.float64) * self.force

    def score(self, n: int, obj: np.ndarray, palm: np.ndarray) -> None:
        from d3grasp.kernels.scoring import DISTURB_TOLERANCE, LIFT_TOLERANCE

        row = min(n, self.script.max_episode_length + 1)
        rise = float(obj[2] - self.obj_start[2])
        if n <= self.script.phase_start["hold"]:
            self.max_rise = max(self.max_rise, rise)
        if bool(self.tab.in_hold_score[row]) and rise < self.lift_height - LIFT_TOLERANCE and self.lift_ok:
            self.failure = self.failure or ("not lifted" if self.max_rise < 0.02 else "slipped / dropped")
            self.lift_ok = False
        rel = obj - palm
        if bool(self.tab.push_started[row]):
            self.push_ref = rel.copy()
        if bool(self.tab.in_push_score[row]):
            k = int(self.tab.scored_push[row])
            moved = float(np.linalg.norm(rel - self.push_ref))
            if self.lift_ok and self.disturb_ok:
                self.push_motion[k] = max(self.push_motion[k], moved)
                j = (n - self.script.phase_start["disturb"] - 1) % self.script.steps_per_push
                self.push_profile[k, j] = moved
            if moved > DISTURB_TOLERANCE and self.disturb_ok and self.lift_ok:
                self.failure = self.failure or f"lost under a push ({PUSH_NAMES[k]})"
                self.disturb_ok = False


def summarise(cfg, trace: dict[str, np.ndarray], obj_start: np.ndarray) -> dict[str, Any]:
    """Scores and per-phase figures of a run's trace (step n = index + 1)."""
    sc = Scorer(cfg, obj_start)
    for i in range(len(trace["obj"])):
        sc.score(i + 1, trace["obj"][i], trace["palm"][i])
    ps = sc.script.phase_start
    spp = sc.script.steps_per_push
    d0 = ps["disturb"]
    pushes = []
    for k in range(6):
        a, b = d0 + k * spp, d0 + (k + 1) * spp  # trace rows of push k's steps
        a, b = min(a, len(trace["obj"])), min(b, len(trace["obj"]))
        pad = trace["pad_normal"][a:b] if len(trace["pad_normal"]) else np.zeros(0)
        hand = trace["hand_normal"][a:b]
        pushes.append(
            {
                "dir": PUSH_NAMES[k],
                "motion_mm": 1000.0 * float(sc.push_motion[k]),
                # motion relative to the palm 0.25, 0.5, 1, 1.5 and 2 s into the push (creep or slip)
                "motion_profile_mm": [
                    1000.0 * float(sc.push_profile[k, min(spp - 1, round(f * spp) - 1)])
                    for f in (0.125, 0.25, 0.5, 0.75, 1.0)
                ],
                "pad_normal_start": float(pad[0]) if len(pad) else None,
                "pad_normal_mean": float(pad.mean()) if len(pad) else None,
                "hand_normal_start": float(hand[0]) if len(hand) else None,
                "hand_normal_mean": float(hand.mean()) if len(hand) else None,
            }
        )
    rise_hold = float(trace["obj"][d0 - 1, 2] - obj_start[2]) if len(trace["obj"]) >= d0 else float("nan")
    return {
        "s_lift": sc.lift_ok,
        "s_disturb": sc.lift_ok and sc.disturb_ok,
        "failure": sc.failure,
        "max_rise_mm": 1000.0 * sc.max_rise,
        "rise_at_push_mm": 1000.0 * rise_hold,
        "pad_normal_at_push": float(trace["pad_normal"][d0 - 1]) if len(trace["pad_normal"]) >= d0 else None,
        "hand_normal_at_push": float(trace["hand_normal"][d0 - 1])
        if len(trace["hand_normal"]) >= d0
        else None,
        "pushes": pushes,
    }


# ----------------------------------------------------------------------------------------------
# Replays
# ----------------------------------------------------------------------------------------------


def fresh_scene(rec: Recording, mu_override: np.ndarray | None = None, gap_zero: bool = False):
    """The episode's single-world model, built as the environment builds it, with its arrays."""
    import newton
    import warp as wp

    from d3grasp.envs.scene import build_scene

    sim = rec.cfg.sim
    model, lay = build_scene(
        [(rec.entry, rec.usd_path)],
        shape_mu=sim.shape_mu,
        particle_radius=sim.particle_radius,
        table_height=sim.table_height,
        kinematic_palm=sim.kinematic_palm,
        device="cpu",
    )
    for k, v in rec.model_arrays.items():
        if k == "joint_target_q":
            continue
        getattr(model, k).assign(v)
    if mu_override is not None:
        model.shape_material_mu.assign(mu_override.astype(np.float32))
    if gap_zero:
        model.shape_gap.assign(np.zeros(model.shape_count, dtype=np.float32))
    newton.eval_fk(model, model.joint_q, model.joint_qd, model)  # the model's body_q at the episode's start
    wp.synchronize()
    return model, lay


def set_state(state, rec: Recording) -> None:
    for k, v in rec.state0.items():
        getattr(state, k).assign(v)


def replay_vbd(rec: Recording, log=print, iterations: int | None = None) -> dict[str, np.ndarray]:
    """Open-loop replay under SolverVBD through the environment's own Physics and Sensors
    (``iterations``: SolverVBD's rigid iterations instead of the environment's)."""
    from dataclasses import replace

    import warp as wp

    from d3grasp.envs.physics import Physics
    from d3grasp.envs.sensors import Sensors

    model, lay = fresh_scene(rec)
    model.soft_contact_ke = rec.cfg.sim.soft_contact_ke
    model.soft_contact_kd = rec.cfg.sim.soft_contact_kd
    model.soft_contact_mu = rec.cfg.sim.soft_contact_mu
    dev = wp.get_device("cpu")
    sim = rec.cfg.sim if iterations is None else replace(rec.cfg.sim, iterations=iterations)
    ph = Physics(model, lay, sim, dev)
    sensors = Sensors(model, lay, rec.cfg, dev)
    set_state(ph.state_0, rec)
    set_state(ph.state_1, rec)
    # As the environment's reset does: the solver's previous poses and the sticky contacts from this
    # state, not from the model's build pose.
    ph.forget_history(np.array([0]))
    ph.control.joint_target_q.assign(rec.model_arrays["joint_target_q"])
    obj_start = rec.state0["body_q"][lay.object_body[0], :3].copy()
    sc = Scorer(rec.cfg, obj_start)
    trace = Trace()
    t0 = time.perf_counter()
    for i, inp in enumerate(rec.inputs):
        n = i + 1
        ph.control.joint_target_q.assign(inp["target"])
        ph.palm_pos_start.assign(inp["pos_start"][None].astype(np.float32))
        ph.palm_pos_end.assign(inp["pos_end"][None].astype(np.float32))
        ph.palm_quat.assign(inp["quat"][None].astype(np.float32))
        ph.palm_yaw_start.assign(np.array([inp["yaw_start"]], dtype=np.float32))
        ph.palm_yaw_end.assign(np.array([inp["yaw_end"]], dtype=np.float32))
        ph.object_force.assign(sc.push(n)[None].astype(np.float32))
        ph.substeps()
        trace.add(ph.state_0, lay, sensors, ph.contacts, ph.observables)
        sc.score(n, trace.obj[-1], trace.palm[-1])
    log(f"    vbd replay ({sim.iterations} iterations): {time.perf_counter() - t0:.0f} s")
    return trace.to_arrays()


def replay_mujoco(rec: Recording, variant: str, log=print) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Open-loop replay under SolverMuJoCo (MuJoCo C on the CPU)."""
    import newton
    import warp as wp

    from d3grasp.envs.sensors import Sensors

    kw = dict(VARIANTS[variant])
    probe_model, lay = fresh_scene(rec)
    mu = probe_model.shape_material_mu.numpy()
    hand_mu = float(np.unique(mu[lay.hand_shapes[0]])[0])
    obj_mu = float(mu[lay.object_shapes[0]][collide_mask(probe_model, lay.object_shapes[0])][0])
    pair_mu = math.sqrt(hand_mu * obj_mu)  # SolverVBD's pair friction (geometric mean)
    model, lay = fresh_scene(rec, mu_override=np.full(probe_model.shape_count, pair_mu), gap_zero=True)
    solver = newton.solvers.SolverMuJoCo(model, use_mujoco_cpu=True, **kw)
    m = solver.mj_model
    info = {
        "variant": variant,
        "kwargs": kw,
        "pair_mu": pair_mu,
        "hand_mu": hand_mu,
        "object_mu": obj_mu,
        "timestep": 1.0 / rec.cfg.sim.control_hz / rec.cfg.sim.substeps,
        "integrator": int(m.opt.integrator),
        "solver_iterations": int(m.opt.iterations),
        "actuator_forcerange": sorted({float(x) for x in np.abs(m.jnt_actfrcrange).ravel()}),
        "actuator_kp": sorted({float(x) for x in m.actuator_gainprm[:, 0]}),
        "actuator_kd": sorted({float(-x) for x in m.actuator_biasprm[:, 2]}),
        "geom_solref": np.unique(m.geom_solref, axis=0).tolist(),
        "geom_solimp": np.unique(m.geom_solimp, axis=0).tolist(),
        "geom_types": {
            int(t): int(c) for t, c in zip(*np.unique(m.geom_type, return_counts=True), strict=True)
        },
        "geom_gap": np.unique(m.geom_gap).tolist(),
        "geom_margin": np.unique(m.geom_margin).tolist(),
        "ngeom": int(m.ngeom),
        "neq_active": int(m.eq_active0.sum()),
    }
    state_0, state_1 = model.state(), model.state()
    control = model.control()
    set_state(state_0, rec)
    set_state(state_1, rec)
    contacts = newton.Contacts(rigid_contact_max=1024, soft_contact_max=0, device="cpu")
    observables = solver.observables(kinds={"contact_f"}, contacts=contacts)
    sensors = Sensors(model, lay, rec.cfg, wp.get_device("cpu"))
    sim = rec.cfg.sim
    substeps, ctrl_dt = sim.substeps, 1.0 / sim.control_hz
    dt = ctrl_dt / substeps
    root_q, root_dof = lay.root_q[0], lay.root_dof[0]
    obj_body = int(lay.object_body[0])
    obj_start = rec.state0["body_q"][obj_body, :3].copy()
    sc = Scorer(rec.cfg, obj_start)
    trace = Trace()
    palm_err = 0.0
    t0 = time.perf_counter()
    for i, inp in enumerate(rec.inputs):
        n = i + 1
        control.joint_target_q.assign(inp["target"])
        push = sc.push(n)
        ps, pe = inp["pos_start"].astype(np.float64), inp["pos_end"].astype(np.float64)
        if abs(inp["yaw_start"]) > 1e-9 or abs(inp["yaw_end"]) > 1e-9:
            raise NotImplementedError("a wrist yaw in the palm path (the rule has none)")
        vel = (pe - ps) / ctrl_dt
        for s in range(substeps):
            jq = state_0.joint_q.numpy()
            jqd = state_0.joint_qd.numpy()
            jq[root_q] = np.concatenate([ps + (s / substeps) * (pe - ps), inp["quat"]])
            jqd[root_dof] = np.concatenate([vel, np.zeros(3)])
            state_0.joint_q.assign(jq)
            state_0.joint_qd.assign(jqd)
            newton.eval_fk(
                model, state_0.joint_q, state_0.joint_qd, state_0, body_flag_filter=newton.BodyFlags.KINEMATIC
            )
            state_0.clear_forces()
            if push.any():
                bf = state_0.body_f.numpy()
                bf[obj_body, :3] = push
                state_0.body_f.assign(bf)
            solver.step(state_0, state_1, control, contacts, dt, observables=observables)
            state_0, state_1 = state_1, state_0
        trace.add(state_0, lay, sensors, contacts, observables)
        palm_err = max(palm_err, float(np.linalg.norm(trace.palm[-1] - pe)))
        sc.score(n, trace.obj[-1], trace.palm[-1])
        if not np.isfinite(trace.obj[-1]).all():
            log(f"    {variant}: non-finite state at step {n}")
            break
    info["palm_tracking_err_mm"] = 1000.0 * palm_err
    info["wall_s"] = time.perf_counter() - t0
    log(f"    {variant}: {info['wall_s']:.0f} s, palm tracking error {info['palm_tracking_err_mm']:.2f} mm")
    return trace.to_arrays(), info


def collide_mask(model, shapes: np.ndarray) -> np.ndarray:
    import newton

    flags = model.shape_flags.numpy()[shapes]
    return (flags & int(newton.ShapeFlags.COLLIDE_SHAPES)) != 0


# ----------------------------------------------------------------------------------------------
# Driver and report
# ----------------------------------------------------------------------------------------------


def run(
    objects: list[str],
    seeds: list[int],
    variants: list[str],
    out: Path,
    log=print,
    max_steps: int | None = None,
    vbd_iterations: tuple[int, ...] = (),
) -> dict[str, Any]:
    import warp as wp

    wp.config.quiet = True
    wp.init()
    results: dict[str, Any] = {"variants": variants, "runs": []}
    if out.is_file():
        results = json.loads(out.read_text())
    done = {(r["object"], r["seed"]) for r in results["runs"]}
    for oid in objects:
        for seed in seeds:
            if (oid, seed) in done:
                continue
            log(f"[{oid} seed {seed}]")
            rec = record_episode(oid, seed, log, max_steps)
            env_trace = rec.env_run["trace"].to_arrays()
            # The object body index is the same in the fresh single-world model (built the same way).
            model, lay = fresh_scene(rec)
            obj_body = int(lay.object_body[0])
            obj_start = rec.state0["body_q"][obj_body, :3].copy()
            mu = model.shape_material_mu.numpy()
            row: dict[str, Any] = {
                "object": oid,
                "seed": seed,
                "mass": float(rec.model_arrays["body_mass"][obj_body]),
                "object_hull_mu": float(
                    mu[lay.object_shapes[0]][collide_mask(model, lay.object_shapes[0])][0]
                ),
                "object_first_shape_mu": float(mu[lay.object_shapes[0][0]]),
                "hand_mu": float(np.unique(mu[lay.hand_shapes[0]])[0]),
                "drive_ke": sorted(
                    {float(x) for x in rec.model_arrays["joint_target_ke"][lay.finger_dof[0]]}
                ),
                "drive_kd": sorted(
                    {float(x) for x in rec.model_arrays["joint_target_kd"][lay.finger_dof[0]]}
                ),
                "effort_limit": sorted(
                    {float(x) for x in model.joint_effort_limit.numpy()[lay.finger_dof[0]]}
                ),
                "env_episode": rec.env_run["episode"],
                "solvers": {},
            }
            row["solvers"]["env_vbd"] = summarise(rec.cfg, env_trace, obj_start)
            vbd = replay_vbd(rec, log)
            row["solvers"]["vbd_replay"] = summarise(rec.cfg, vbd, obj_start)
            d0 = rec.env_run["disturb_start"]
            dev = np.linalg.norm(vbd["obj"] - env_trace["obj"], axis=1)
            row["vbd_replay_max_obj_dev_mm"] = 1000.0 * float(dev.max())
            row["vbd_replay_obj_dev_before_push_mm"] = 1000.0 * float(dev[:d0].max())
            for it in vbd_iterations:
                row["solvers"][f"vbd_replay_{it}it"] = summarise(rec.cfg, replay_vbd(rec, log, it), obj_start)
            for v in variants:
                try:
                    tr, info = replay_mujoco(rec, v, log)
                    row["solvers"][v] = summarise(rec.cfg, tr, obj_start) | {"info": info}
                except Exception as exc:  # a failed conversion or step must name itself in the results
                    import traceback

                    traceback.print_exc()
                    row["solvers"][v] = {"error": f"{type(exc).__name__}: {exc}"}
            results["runs"].append(row)
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(results, indent=1, default=_json_default))
            report(results, log)
    return results


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def report(results: dict[str, Any], log=print) -> None:
    log("")
    log(
        "| object | seed | solver | lifted (rise at push) | held | lost | grip at push: pads / hand (N) "
        "| push motion mm (+x -x +y -y +z -z) |"
    )
    log("|---|---|---|---|---|---|---|---|")
    for r in results["runs"]:
        for name, s in r["solvers"].items():
            if "error" in s:
                log(f"| {r['object']} | {r['seed']} | {name} | error: {s['error']} | | | | |")
                continue
            motion = " ".join(f"{p['motion_mm']:.0f}" for p in s["pushes"])
            pads = s["pad_normal_at_push"] if s["pad_normal_at_push"] is not None else float("nan")
            hand = s["hand_normal_at_push"] if s["hand_normal_at_push"] is not None else float("nan")
            lifted = f"{'yes' if s['s_lift'] else 'no'} ({s['rise_at_push_mm']:.0f} mm)"
            log(
                f"| {r['object']} | {r['seed']} | {name} | {lifted} "
                f"| {'yes' if s['s_disturb'] else 'no'} | {s['failure'] or '-'} "
                f"| {pads:.1f} / {hand:.1f} | {motion} |"
            )
        log(
            f"  ({r['object']}: mass {r['mass']:.3f} kg, hull mu {r['object_hull_mu']:.2f}, "
            f"hand mu {r['hand_mu']:.2f}, VBD replay vs env: object deviation "
            f"{r['vbd_replay_obj_dev_before_push_mm']:.2f} mm before the pushes, "
            f"{r['vbd_replay_max_obj_dev_mm']:.2f} mm in all; "
            f"env record: {r['env_episode']})"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", nargs="+", default=["frustum_09", "frustum_04"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0])
    ap.add_argument("--variants", nargs="+", default=list(DEFAULT_VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--out", type=Path, default=Path("/tmp/mjstudy/replay.json"))
    ap.add_argument("--report", nargs="+", type=Path, help="print the tables of saved runs")
    ap.add_argument(
        "--vbd-iterations", nargs="*", type=int, default=[20], help="VBD replays at these iterations too"
    )
    ap.add_argument("--max-steps", type=int, default=None, help="stop each episode early (a smoke test)")
    args = ap.parse_args(argv)
    if args.report:
        for p in args.report:
            report(json.loads(p.read_text()))
        return 0
    require_mujoco()
    run(
        args.objects,
        args.seeds,
        args.variants,
        args.out,
        max_steps=args.max_steps,
        vbd_iterations=tuple(args.vbd_iterations),
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
