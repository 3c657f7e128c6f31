"""How hard can the DexHand13 hold the 500 g objects no planned grasp held? (issue 60's last target)

    python tools/holding_force_study.py [--objects blob_04 ellipsoid_09 ...] [--ramp 1.0] [--seconds 8]

Each object is placed twice in one environment (Mixed task, eval mode, no randomisation, the
library's planned grasp): world ``i`` runs the rule-based baseline (zero residual), world ``n + i``
the hand's strongest closure: every flexion joint's target ramps at the rule's ``close_speed`` from
the grasp phase on up to its upper limit and never stops (abduction stays at the grasp pre-shape),
world ``2n + i`` the rule until its touch-timed lift starts, then the same ramp to the upper limits
from the rule's targets (the rule's contacts, squeezed as hard as the drives go).
The scripted approach, touch-timed lift and hold are the env's own. In the disturb phase the
evaluation's six pushes are replaced by a downward force ramped at ``--ramp`` N/s on the object's
centre of mass: the extra load at which the object has moved 2 cm relative to the palm (the
evaluation's ``DISTURB_TOLERANCE``) measures the grip's vertical holding capacity,
``weight + ramp force at slip``.

Per world it prints: the grasp type, the pads' summed normal force (|z| in the pad frames,
``sensors.pad_force_object``) and pads touching (> 0.5 N) at the lift's start and over the hold, the
friction budget ``mu_pair * grip`` with ``mu_pair = sqrt(mu_pad * mu_object_hull)``
(``model.shape_material_mu``, the object's colliding shape), the largest drive torque
``ke * (target - q)`` of a flexion joint against the spec's effort limit, the object's rise, and
the slip load. The hand's opening: the open hand's thumb-tip-pad to middle/index-tip-pad distance
at the first step. Writes nothing; the study is docs/studies/holding_force.md.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

import d3grasp
from d3grasp.authoring.hand_spec import load_spec
from d3grasp.console import quiet_warp
from d3grasp.dexhand13 import FINGER_JOINT_NAMES, FLEXION_JOINTS
from d3grasp.vocabulary import GRASP_TYPES, PHASES

DEFAULT_OBJECTS = ("blob_04", "ellipsoid_09", "frustum_04", "blob_01", "bottle_02", "box_02", "cylinder_04")
TOUCH_N = 0.5  # N: a pad "in contact" (the rule's force threshold)
SLIP_M = 0.02  # m of motion relative to the palm (the evaluation's DISTURB_TOLERANCE)


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate v (..., 3) by quaternions q (..., 4) xyzw."""
    xyz, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(xyz, v)
    return v + w * t + np.cross(xyz, t)


def pad_positions(env, body_q: np.ndarray) -> np.ndarray:
    """(W, 11, 3) world positions of the pads' collider frames."""
    model, lay = env.model, env.layout
    sb = model.shape_body.numpy()
    st = model.shape_transform.numpy()
    pads = lay.pad_shapes  # (W, 11)
    bq = body_q[sb[pads]]  # (W, 11, 7)
    local = st[pads]
    return bq[..., :3] + quat_rotate(bq[..., 3:7], local[..., :3])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="+", default=list(DEFAULT_OBJECTS))
    ap.add_argument("--ramp", type=float, default=1.0, help="N/s of downward force in the disturb phase")
    ap.add_argument("--seconds", type=float, default=8.0, help="seconds of the ramp (then stop)")
    ap.add_argument("--squeeze", type=float, default=None, help="the rule's squeeze (rad; default the env's)")
    args = ap.parse_args(argv)
    quiet_warp()
    import newton

    from d3grasp.envs.scene import pad_object_friction

    ids = tuple(args.objects)
    n = len(ids)
    W = 3 * n
    t0 = time.time()
    env = d3grasp.make_env(
        "D3Grasp-DexHand13-Mixed-v0",
        num_envs=W,
        objects={"ids": ids},
        seed=0,
        eval_mode=True,
        randomization__enabled=False,
        **({"rule__squeeze": args.squeeze} if args.squeeze is not None else {}),
    )
    print(f"rule squeeze {env.cfg.rule.squeeze} rad, close_speed {env.cfg.rule.close_speed} rad/s")
    print(f"env built in {time.time() - t0:.1f} s; max_episode_length {env.max_episode_length}")
    model, lay, dev = env.model, env.layout, env.torch_device
    names = [e.id for e in env.world_entries]
    mass = [e.mass for e in env.world_entries]
    extents = [e.extents for e in env.world_entries]
    g = 9.81
    widx = torch.arange(W, device=dev)
    max_world = (widx >= n) & (widx < 2 * n)  # strongest closure from the grasp phase on
    late_world = widx >= 2 * n  # the rule until the lift starts, then the strongest closure
    MODES = ("rule", "max", "rule+max")

    # Friction: pad vs the object's colliding shape(s), each side's coefficient and the pair's.
    mu = model.shape_material_mu.numpy()
    colliding = (model.shape_flags.numpy() & int(newton.ShapeFlags.COLLIDE_SHAPES)) != 0
    mu_pad = np.array([mu[lay.pad_shapes[w]].mean() for w in range(W)])
    mu_obj = np.array([mu[[s for s in lay.object_shapes[w] if colliding[s]]].mean() for w in range(W)])
    mu_pair = pad_object_friction(model, lay)

    # Drives and effort limits of the finger joints.
    ke = torch.as_tensor(model.joint_target_ke.numpy()[lay.finger_dof], dtype=torch.float32)
    kd = torch.as_tensor(model.joint_target_kd.numpy()[lay.finger_dof], dtype=torch.float32)
    spec = {j.name: j for j in load_spec().joints}
    effort = torch.tensor([spec[nm].effort for nm in FINGER_JOINT_NAMES])
    flex = list(FLEXION_JOINTS)
    print(
        f"flexion ke {sorted(set(ke[0, flex].tolist()))} kd {sorted(set(kd[0, flex].tolist()))} "
        f"effort {sorted(set(effort[flex].tolist()))} N m; upper {env.joints.upper[flex].tolist()}"
    )

    # The strongest closure: wrap the rule so the max worlds' flexion targets ramp to the upper limit.
    rule = env.residual_base
    orig_act = rule.act
    ramp_target = env.joints.open_pose.expand(W, -1).clone()
    upper = env.joints.upper

    def act(obs=None):
        out = orig_act(obs)
        t = env.episode_length_buf
        closing = env.phase_of(t) >= PHASES.index("grasp")
        fresh = t == 0
        ramp_target[fresh] = rule.state.target[fresh]
        lifting = t >= env.scoring.now.lift_start
        begin = late_world & (t == env.scoring.now.lift_start)
        ramp_target[begin] = rule.state.target[begin]
        adv = (closing & max_world) | (lifting & late_world)
        step = env.cfg.rule.close_speed * env.dt
        nxt = torch.minimum(ramp_target + step, upper)
        ramp_target[:, flex] = torch.where(adv[:, None], nxt[:, flex], ramp_target[:, flex])
        sel = (max_world & ~fresh) | (late_world & lifting & ~fresh)
        rule.state.target[sel] = torch.where(
            torch.zeros(16, dtype=torch.bool).index_fill_(0, torch.tensor(flex), True)[None],
            ramp_target[sel],
            rule.state.target[sel],
        )
        return out

    rule.act = act

    # The ramped downward push in the disturb phase (the step gates it by lift_ok & disturb_ok).
    d0 = env.script.phase_start["disturb"]
    steps_ramp = int(round(args.seconds / env.dt))

    def disturbance(t, order):
        f = torch.zeros(W, 3, device=dev)
        f[:, 2] = -args.ramp * ((t - d0).clamp(min=0).float() * env.dt) * (t >= d0)
        return f

    env.script.disturbance = disturbance

    zero = torch.zeros(W, env.num_actions)
    obj0 = env.object_state()[0][:, 2].clone()
    palm0 = env.view.body_q[env.index.palm, 2].clone()
    rec = {k: [None] * W for k in ("grip_lift", "pads_lift", "tau_lift", "aperture_lift")}
    peak_grip, peak_pads, peak_tau, max_rise = [0.0] * W, [0] * W, [0.0] * W, [-1.0] * W
    hold_grip, hold_pads, hold_tau, hold_rise = (
        [[] for _ in range(W)],
        [[] for _ in range(W)],
        [[] for _ in range(W)],
        [[] for _ in range(W)],
    )
    span_open = None
    ref_rel = None
    slip_force = [None] * W
    pushed_to = [0.0] * W
    t_start = time.time()
    last_phase = None
    grasp_type = [GRASP_TYPES[int(i)] for i in env.grasp.type_id]
    for _k in range(d0 + steps_ramp):
        env.step(zero)
        t = env.episode_length_buf
        phase = env.phase_of(t)
        body_q = (
            env.view.body_q.numpy() if hasattr(env.view.body_q, "numpy") else env.view.body_q.cpu().numpy()
        )
        if span_open is None:
            p = pad_positions(env, body_q)
            span_open = [
                (float(np.linalg.norm(p[w, 10] - p[w, 5])), float(np.linalg.norm(p[w, 10] - p[w, 2])))
                for w in range(W)
            ]
        pf = env.view.pad_force_object  # (W, 11, 3)
        normal = pf[:, :, 2].abs()
        grip = normal.sum(-1)
        pads = (pf.norm(dim=-1) > TOUCH_N).sum(-1)
        q = env.view.joint_q[env.index.finger_q]
        tgt = env.view.target[env.index.finger_q]
        tau = (ke * (tgt - q))[:, flex]
        tau_max = tau.max(-1).values
        lift_start = env.scoring.now.lift_start
        rise = env.object_state()[0][:, 2] - obj0
        env.view.body_q[env.index.palm, 2] - palm0
        p_now = None
        for w in range(W):
            if int(t[w]) == int(lift_start[w]) and rec["grip_lift"][w] is None:
                rec["grip_lift"][w], rec["pads_lift"][w], rec["tau_lift"][w] = (
                    float(grip[w]),
                    int(pads[w]),
                    float(tau_max[w]),
                )
                p_now = pad_positions(env, body_q) if p_now is None else p_now
                rec["aperture_lift"][w] = float(np.linalg.norm(p_now[w, 10] - p_now[w, 5]))
            ph_w = int(phase[w])
            if PHASES.index("grasp") <= ph_w <= PHASES.index("hold"):
                if float(grip[w]) > peak_grip[w]:
                    peak_grip[w], peak_pads[w] = float(grip[w]), int(pads[w])
                peak_tau[w] = max(peak_tau[w], float(tau_max[w]))
                max_rise[w] = max(max_rise[w], float(rise[w]))
            if int(phase[w]) == PHASES.index("hold"):
                hold_grip[w].append(float(grip[w]))
                hold_pads[w].append(int(pads[w]))
                hold_tau[w].append(float(tau_max[w]))
                hold_rise[w].append(float(rise[w]))
        # Slip under the ramp: motion relative to the palm since the disturb phase began.
        rel = env.object_state()[0] - env.view.body_q[env.index.palm, :3]
        if int(t[0]) == d0:
            ref_rel = rel.clone()
        if ref_rel is not None:
            moved = (rel - ref_rel).norm(dim=-1)
            f_now = args.ramp * max(0, int(t[0]) - d0) * env.dt
            ok = env.scoring.now.lift_ok & env.scoring.now.disturb_ok
            for w in range(W):
                if slip_force[w] is None and (moved[w] > SLIP_M or not bool(ok[w])):
                    slip_force[w] = f_now
                if slip_force[w] is None:
                    pushed_to[w] = f_now
        ph = PHASES[int(phase[0])]
        if ph != last_phase:
            print(f"step {int(t[0])} world0 phase {ph} ({time.time() - t_start:.0f} s)", flush=True)
            last_phase = ph
        if ref_rel is not None and all(s is not None for s in slip_force):
            break
    lifted = env.scoring.now.lift_ok.tolist()
    print(f"stepped in {time.time() - t_start:.0f} s")
    print()
    hdr = (
        "world object mode grasp mass_kg extents_cm open_span_thumb-mid/idx_cm mu_pad mu_obj mu_pair "
        "grip@lift_N pads@lift grip_hold_N pads_hold fric_budget_N load_N tau_max_Nm effort_Nm "
        "rise_cm lift_ok slip_extra_N capacity_N | peak_grip_N peak_pads budget@lift_N budget@peak_N "
        "peak_tau_Nm max_rise_cm aperture@lift_cm"
    )
    print(hdr)
    for w in range(W):
        mode = MODES[w // n]
        gh = float(np.mean(hold_grip[w])) if hold_grip[w] else float("nan")
        ph_ = float(np.mean(hold_pads[w])) if hold_pads[w] else float("nan")
        th = float(np.max(hold_tau[w])) if hold_tau[w] else float("nan")
        rz = float(np.mean(hold_rise[w])) * 100 if hold_rise[w] else float("nan")
        weight = mass[w] * g
        sf = slip_force[w]
        slip = f"{sf:.2f}" if sf is not None else f">{pushed_to[w]:.2f}"
        cap = (
            (weight + sf)
            if (sf is not None and lifted[w])
            else (weight + pushed_to[w] if lifted[w] else float("nan"))
        )
        if not lifted[w]:
            slip, cap_s = "-", f"<{weight:.2f}"
        else:
            cap_s = f"{cap:.2f}" if sf is not None else f">{cap:.2f}"
        ext = "x".join(f"{100 * e:.1f}" for e in extents[w])
        gl = rec["grip_lift"][w]
        aperture_lift = rec["aperture_lift"][w] or float("nan")
        columns = [
            f"{w} {names[w]} {mode} {grasp_type[w]} {mass[w]:.3f} {ext}",
            f"{100 * span_open[w][0]:.1f}/{100 * span_open[w][1]:.1f}",
            f"{mu_pad[w]:.2f} {mu_obj[w]:.2f} {mu_pair[w]:.2f}",
            f"{gl if gl is None else round(gl, 2)} {rec['pads_lift'][w]}",
            f"{gh:.2f} {ph_:.1f} {mu_pair[w] * gh:.2f}",
            f"{weight:.2f}-{weight + 2.5:.2f} {th:.3f} {float(effort[flex].max()):.1f}",
            f"{rz:.1f} {lifted[w]} {slip} {cap_s}",
            "|",
            f"{peak_grip[w]:.2f} {peak_pads[w]}",
            f"{mu_pair[w] * (gl or 0.0):.2f} {mu_pair[w] * peak_grip[w]:.2f}",
            f"{peak_tau[w]:.2f} {100 * max_rise[w]:.1f} {100 * aperture_lift:.1f}",
        ]
        print(" ".join(columns))
    env.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
