"""Study: the anatomy of every episode the rule-based baseline does not hold (issue 60, part 1).

Runs the evaluation itself (``d3grasp.eval.evaluate.evaluate``: the same batches, seeds and episodes
as ``d3grasp-eval --checkpoint baseline``), with an environment that, at the step the first push
starts (the state after the hold), reads for every world:

- the grip: each pad's force from the object in the pad's frame (true values, no noise), the sum of
  the normal components (pad +z) and the number of pads touching;
- the finger drives' torques, ke (q_target - q) - kd qd per joint (SolverVBD applies no
  ``joint_effort_limit``: this is what a hold asks of the motors), against the spec's effort limit;
- the episode's friction coefficient of the object's shapes and its mass (the evaluation draws no
  dynamics: they are the nominal ones, recorded to show it);
- the friction reserve ``mu * grip - |m g + F|``: the tangential force the pads' normal forces could
  resist at the object's friction against the load of the push that lost it (the weight and the
  2.5 N push together; for a held episode the worst push, -z, where the two add). The palm's contact
  is not a pad, so a power grasp's reserve is a lower bound.

and joins each episode with what the planner's trials had said of its grasp (``grasps.json``: the
score and trials of the type the episode used).

    python tools/grasp_anatomy_study.py --perception oracle --split test --seeds 0 1 2 3 4 5 \\
        --out /tmp/anatomy/test_oracle.json

One process (the instrumented environment runs in it); run perceptions or seeds side by side in
two processes on two cores. ``--report A.json B.json ...`` prints the tables of saved runs.
docs/studies/grasp_anatomy.md reports them.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter, defaultdict
from pathlib import Path
from typing import Any

import numpy as np

GRAVITY = 9.81


def _spec_effort() -> np.ndarray:
    """(16,) effort limits of the finger joints in the policy's order, from the hand's spec."""
    from d3grasp.authoring.hand_spec import load_spec
    from d3grasp.dexhand13 import FINGER_JOINT_NAMES

    spec = load_spec()
    return np.array([spec.joint(n).effort for n in FINGER_JOINT_NAMES])


def instrumented_env(*args: Any, **kwargs: Any) -> Any:
    """``make_env`` whose episode records carry the grip, torques and dynamics at the first push."""
    from d3grasp.envs import make_env
    from d3grasp.envs.scene import pad_object_friction

    env = make_env(*args, **kwargs)
    inner_step = env.step
    push_start = env.script.phase_start["disturb"]
    lay, model = env.layout, env.model
    ke, kd = model.joint_target_ke.numpy(), model.joint_target_kd.numpy()
    particle_mass = model.particle_mass.numpy() if model.particle_count else None
    snapshots: dict[int, dict[str, Any]] = {}

    def snapshot(worlds: np.ndarray) -> None:
        forces = env.sensors.pad_force_object.numpy()  # (W, 11, 3), pad frames, true
        q = env.view.joint_q.detach().cpu().numpy()
        qd = env.view.joint_qd.detach().cpu().numpy()
        target = env.view.target.detach().cpu().numpy()
        # Mass and friction are written at reset; read them once per snapshot (the model's arrays).
        body_mass = model.body_mass.numpy()
        friction_of = pad_object_friction(model, lay)  # NaN for soft: the particle law, not a coefficient
        for w in worlds:
            qi, di = lay.finger_q[w], lay.finger_dof[w]
            torque = ke[di] * (target[qi] - q[qi]) - kd[di] * qd[di]  # targets in joint_q layout
            normal = np.abs(forces[w, :, 2])
            if lay.object_shapes[w].size:
                mass = float(body_mass[lay.object_body[w]])
            else:
                p0, n = int(lay.particle_start[w]), int(lay.particle_count[w])
                mass = float(particle_mass[p0 : p0 + n].sum()) if particle_mass is not None else float("nan")
            snapshots[int(w)] = {
                "pad_forces": np.round(forces[w], 4).tolist(),
                "grip_n": float(normal.sum()),
                "pads_touching": int((np.linalg.norm(forces[w], axis=1) > 0.1).sum()),
                "torques": np.round(torque, 4).tolist(),
                "max_torque": float(np.abs(torque).max()),
                "mass": mass,
                "mu": float(friction_of[w]),
            }

    def step(actions: Any) -> Any:
        obs, rew, dones, extras = inner_step(actions)
        t = env.episode_length_buf.detach().cpu().numpy()
        at_push = np.flatnonzero(t == push_start)
        if at_push.size:
            snapshot(at_push)
        for ep in extras.get("episodes", ()):
            ep.update(snapshots.pop(int(ep["env"]), {"grip_n": None}))
        return obs, rew, dones, extras

    env.step = step
    return env


def planner_record(manifest: Path | None) -> dict[str, Any]:
    from d3grasp.envs.grasp_file import grasp_file_path, read_grasp_file
    from d3grasp.paths import default_manifest

    path = grasp_file_path(manifest or default_manifest())
    return read_grasp_file(path)["objects"] if path.is_file() else {}


def run(args: argparse.Namespace) -> dict[str, Any]:
    from d3grasp.console import quiet_warp
    from d3grasp.eval.evaluate import EvalSettings, evaluate, select_objects
    from d3grasp.policies import BASELINE

    quiet_warp()
    manifest, _ = select_objects(args.objects, args.split)
    plans = planner_record(manifest)
    episodes = []
    for seed in args.seeds:
        settings = EvalSettings(
            checkpoint=BASELINE,
            objects=args.objects,
            split=args.split,
            seed=seed,
            num_envs=args.num_envs,
            perception=args.perception,
        )
        result = evaluate(settings, progress=not args.no_progress, env_factory=instrumented_env)
        for label, eps in result.runs.items():
            for ep in eps:
                grasp = (plans.get(ep["object"]) or {}).get("grasps", {}).get(ep["grasp_type"], {})
                episodes.append(
                    {
                        **ep,
                        "run": label,
                        "planned_score": grasp.get("score"),
                        "planned_trials": grasp.get("trials"),
                    }
                )
        print(f"[anatomy] seed {seed} done", flush=True)
    return {
        "perception": args.perception,
        "split": args.split,
        "objects": args.objects,
        "seeds": list(args.seeds),
        "effort_limit": _spec_effort().tolist(),
        "push_n": 2.5,
        "episodes": episodes,
    }


PUSHES = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
}


def reserve(ep: dict[str, Any], push: float) -> float | None:
    """``mu * grip - |m g + F|`` (N) of an episode (module docstring); None without a snapshot."""
    if ep.get("grip_n") is None or np.isnan(ep.get("mu", np.nan)):
        return None
    failure = str(ep.get("failure") or "")
    direction = next((d for d in PUSHES if failure.endswith(f"({d})")), "-z")
    load = np.array([0.0, 0.0, -GRAVITY * ep["mass"]]) + push * np.array(PUSHES[direction])
    return float(ep["mu"] * ep["grip_n"] - np.linalg.norm(load))


def where(ep: dict[str, Any]) -> str:
    """Where an episode was lost: held, or its failure cause."""
    return "held" if ep["s_disturb"] else str(ep["failure"])


def report(data: dict[str, Any]) -> str:
    eps = data["episodes"]
    effort = np.asarray(data["effort_limit"])
    push = float(data["push_n"])
    lines = [
        f"## {data['perception']}, {data['split']} split, seeds {data['seeds']}: {len(eps)} episodes",
        "",
        "| where | episodes | mean grip N (pads) | reserve mu grip - abs(m g + F) > 0 | max torque N m | "
        "planned trials held (mean) |",
        "|---|---|---|---|---|---|",
    ]
    groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for ep in eps:
        groups[where(ep)].append(ep)
    for name, rows in sorted(groups.items(), key=lambda kv: (kv[0] != "held", -len(kv[1]))):
        grips = [r["grip_n"] for r in rows if r.get("grip_n") is not None]
        reserves = [v for v in (reserve(r, push) for r in rows) if v is not None]
        spare = sum(1 for v in reserves if v > 0.0)
        torques = [r["max_torque"] for r in rows if r.get("max_torque") is not None]
        planned = [
            r["planned_trials"]["disturb"] / max(1, r["planned_trials"]["of"])
            for r in rows
            if r.get("planned_trials")
        ]
        lines.append(
            f"| {name} | {len(rows)} | {np.mean(grips) if grips else float('nan'):.2f} | "
            f"{spare} of {len(reserves)} | {max(torques) if torques else float('nan'):.2f} | "
            f"{np.mean(planned) if planned else float('nan'):.2f} |"
        )
    over = [ep for ep in eps if ep.get("torques") and np.any(np.abs(ep["torques"]) > effort)]
    lines += [
        "",
        f"Holds asking more torque than the spec's effort limit ({effort.max():g} N m): {len(over)}.",
        f"Friction and mass: mu {sorted({ep['mu'] for ep in eps if ep.get('mu') is not None})[:5]}, "
        "mass as authored (no dynamics drawn in evaluation).",
        "",
        "Lost episodes by grasp type and size bin:",
    ]
    lost = [ep for ep in eps if not ep["s_disturb"]]
    by = Counter((ep["grasp_type"], ep["size_bin"]) for ep in lost)
    total = Counter((ep["grasp_type"], ep["size_bin"]) for ep in eps)
    lines += [f"- {g} / {b}: {by[(g, b)]} of {total[(g, b)]}" for g, b in sorted(total)]
    lines += ["", "By object (those with a loss): held, how the others were lost, the planner's trials:"]
    lines += ["", "| object | mass g | type | held | lost as | planned lift/held of |"]
    lines += ["|---|---|---|---|---|---|"]
    by_object: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for ep in eps:
        by_object[ep["object"]].append(ep)
    for obj, rows in sorted(by_object.items(), key=lambda kv: sum(r["s_disturb"] for r in kv[1])):
        if all(r["s_disturb"] for r in rows):
            continue
        how = Counter(where(r) for r in rows if not r["s_disturb"])
        trials = rows[0].get("planned_trials") or {}
        types = "/".join(sorted({r["grasp_type"] for r in rows}))
        lines.append(
            f"| {obj} | {1e3 * rows[0].get('mass', float('nan')):.0f} | {types} | "
            f"{sum(r['s_disturb'] for r in rows)} of {len(rows)} | "
            + ", ".join(f"{k} {v}" for k, v in how.most_common())
            + f" | {trials.get('lift', '')}/{trials.get('disturb', '')} of {trials.get('of', '')} |"
        )
    lines += ["", "| object | seed | type | where | grip N | reserve N | mass g | planned |"]
    lines += ["|---|---|---|---|---|---|---|---|"]
    for ep in sorted(lost, key=lambda e: (e["object"], e["seed"])):
        grip = ep.get("grip_n")
        spare = reserve(ep, push)
        trials = ep.get("planned_trials") or {}
        grams = 1e3 * ep.get("mass", float("nan"))
        lines.append(
            f"| {ep['object']} | {ep['seed']} | {ep['grasp_type']} | {where(ep)} | "
            f"{'' if grip is None else f'{grip:.2f}'} | {'' if spare is None else f'{spare:+.2f}'} | "
            f"{grams:.0f} | "
            f"{trials.get('lift', '')}/{trials.get('disturb', '')} of {trials.get('of', '')} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--perception", choices=("oracle", "camera"), default="oracle")
    p.add_argument("--split", choices=("test", "train", "all"), default="test")
    p.add_argument("--objects", default="diverse", help="diverse | deformable | all")
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--num_envs", type=int, default=16, help="worlds per batch (the main command's 16)")
    p.add_argument("--out", type=Path, default=None, help="write the episodes here (JSON)")
    p.add_argument("--report", type=Path, nargs="+", default=None, help="print the tables of saved runs")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.report:
        for path in args.report:
            print(report(json.loads(path.read_text())) + "\n")
        return 0
    data = run(args)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(data) + "\n")
        print(f"[anatomy] wrote {args.out}")
    print(report(data))
    return 0


if __name__ == "__main__":
    sys.exit(main())
