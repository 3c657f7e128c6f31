"""Environment throughput: env-steps/s and physics steps/s for rigid and soft objects (``bench env``).

For each object kind and world count: the time to make the environment (cold when the Warp kernel
cache is empty, warm otherwise) and, over whole episodes from reset (approach, grasp, lift, hold,
push: the zero action is the rule-based grasp in the residual action modes, so the hands close and
lift), the mean wall time of a full ``env.step`` (captured physics + sensors + kernels +
observations + rewards + scoring) and of the bare captured physics inside it (``substeps`` x
collide + SolverVBD step), and their ratio; the step's cost split into physics, sensors (tactile,
strain, object pose) and the task's terms (everything else: actions, observations, rewards,
terminations, resets). With ``procs`` > 1 the same row runs in that many processes at once
(d3grasp.parallel) and the figures are given per process and for all of them together: Warp's CPU
backend runs a process on one core, so processes are how a machine's cores add up.

Why whole episodes: the cost of a step follows the contacts. The first half second (approach, no
touch) runs ~1.2-1.7x faster than the grasp and lift (30-60 contacts per world, objects of many
hulls up to 200), so timing only the first steps after reset overstates the throughput.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import torch
import warp as wp

from d3grasp.envs import close_env, make_env

TASK_BY_KIND = {"rigid": "D3Grasp-DexHand13-Diverse-v0", "soft": "D3Grasp-DexHand13-Deformable-v0"}


def _timed_physics_launch(env, physics_s: list[float], sensors_s: list[float]) -> Callable[[], None]:
    """The env's captured control step as two graphs, physics then sensors, each timed.

    The same kernels in the same order as the env's own graph (``_control_step`` = the physics
    substeps then the sensors' update): only the split is new, so the episode is the one the env
    would run.
    """
    device = env.wp_device
    with wp.ScopedDevice(device), wp.ScopedCapture() as cap:
        env.physics.substeps()
    physics_graph = cap.graph
    with wp.ScopedDevice(device), wp.ScopedCapture() as cap:
        env.sensors.update(env.state_0, env.contacts, env.observables)
    sensors_graph = cap.graph

    def launch() -> None:
        t0 = time.perf_counter()
        wp.capture_launch(physics_graph)
        wp.synchronize_device(device)
        t1 = time.perf_counter()
        physics_s.append(t1 - t0)
        wp.capture_launch(sensors_graph)
        wp.synchronize_device(device)
        sensors_s.append(time.perf_counter() - t1)

    return launch


def bench_one(
    kind: str, worlds: int, episodes: float, device: str, overrides: dict[str, Any] | None = None
) -> dict[str, float]:
    t0 = time.perf_counter()
    env = make_env(TASK_BY_KIND[kind], num_envs=worlds, device=device, **(overrides or {}))
    make_s = time.perf_counter() - t0
    if env.graph is None:
        raise RuntimeError("the env benchmark times the captured step: sim.use_graph must be on")
    physics_s: list[float] = []
    sensors_s: list[float] = []
    env.step_launcher = _timed_physics_launch(env, physics_s, sensors_s)
    actions = torch.zeros(worlds, env.num_actions, device=env.torch_device)
    steps = max(1, round(episodes * (int(env.max_episode_length) - 1)))
    step_s = 0.0
    for _ in range(steps):
        t0 = time.perf_counter()
        env.step(actions)
        wp.synchronize_device(env.wp_device)
        step_s += time.perf_counter() - t0
    close_env(env)
    return {
        "make_s": make_s,
        "steps": steps,
        "env_steps_per_s": worlds * steps / step_s,
        "physics_steps_per_s": worlds * steps / sum(physics_s),
        "ratio": step_s / sum(physics_s),
        "physics_share": sum(physics_s) / step_s,
        "sensors_share": sum(sensors_s) / step_s,
        "task_share": 1.0 - (sum(physics_s) + sum(sensors_s)) / step_s,
    }


def run_env_benchmark(
    worlds: list[int],
    kinds: list[str],
    episodes: float = 1.0,
    device: str = "cpu",
    overrides: dict[str, Any] | None = None,
    procs: list[int] | None = None,
) -> list[dict[str, Any]]:
    """Print (and return) one row per kind, world count and process count."""
    from d3grasp.parallel import run_units

    procs = procs or [1]
    print(
        f"env benchmark on {device}: {episodes:g} episode(s) from reset per row, all phases, the rule-based "
        "grasp acting (60 Hz control, substeps from SimConfig)"
        + (f"; overrides {overrides}" if overrides else "")
    )
    header = (
        "kind", "worlds", "procs", "steps", "make env s", "env-steps/s", "all procs/s", "x 1 proc",
        "physics/s", "step/physics", "physics %", "sensors %", "task %",
    )  # fmt: skip
    print(f"{header[0]:6s} " + " ".join(f"{h:>12s}" for h in header[1:]), flush=True)
    rows: list[dict[str, Any]] = []
    for kind in kinds:
        for w in worlds:
            single = None
            for p in procs:
                results: list[dict[str, float]] = [{} for _ in range(p)]

                def keep(k: int, r: dict[str, float], results: list[dict[str, float]] = results) -> None:
                    results[k] = r

                # p copies of the row at once, in p processes (the row itself here when p = 1).
                run_units(bench_one, [(kind, w, episodes, device, overrides)] * p, p, keep)
                per = {key: sum(r[key] for r in results) / p for key in results[0]}
                total = sum(r["env_steps_per_s"] for r in results)
                single = total if p == 1 else single
                row = {"kind": kind, "worlds": w, "procs": p, **per, "all_env_steps_per_s": total}
                row["speedup"] = total / single if single else float("nan")
                rows.append(row)
                print(
                    f"{kind:6s} {w:12d} {p:12d} {int(per['steps']):12d} {per['make_s']:12.1f} "
                    f"{per['env_steps_per_s']:12.0f} {total:12.0f} {row['speedup']:12.2f} "
                    f"{per['physics_steps_per_s']:12.0f} {per['ratio']:12.2f} "
                    + " ".join(
                        f"{100 * per[k]:12.1f}" for k in ("physics_share", "sensors_share", "task_share")
                    ),
                    flush=True,
                )
    print(
        "targets (2-core CPU): >= 500 env-steps/s rigid and >= 100 soft at 8+ worlds in one process; "
        "step/physics <= 1.25; two processes >= 1.8x one"
    )
    return rows
