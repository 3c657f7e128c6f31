"""Environment throughput: env-steps/s and physics steps/s for rigid and soft objects (``bench env``).

For each object kind and world count: the time to make the environment (cold when the Warp kernel
cache is empty, warm otherwise) and, over whole episodes from reset (approach, grasp, lift, hold,
push: the zero action is the rule-based grasp in the residual action modes, so the hands close and
lift), the mean wall time of a full ``env.step`` (captured physics + sensors + kernels +
observations + rewards + scoring) and of the bare captured physics inside it (``substeps`` x
collide + SolverVBD step), and their ratio.

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


def _timed_physics_launch(env, physics_s: list[float]) -> Callable[[], None]:
    """The env's captured control step as two graphs, physics then sensors, the physics timed.

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
        physics_s.append(time.perf_counter() - t0)
        wp.capture_launch(sensors_graph)

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
    env._launch_step = _timed_physics_launch(env, physics_s)
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
    }


def run_env_benchmark(
    worlds: list[int],
    kinds: list[str],
    episodes: float = 1.0,
    device: str = "cpu",
    overrides: dict[str, Any] | None = None,
) -> None:
    print(
        f"env benchmark on {device}: {episodes:g} episode(s) from reset per row, all phases, the rule-based "
        "grasp acting (60 Hz control, substeps from SimConfig)"
        + (f"; overrides {overrides}" if overrides else "")
    )
    header = ("kind", "worlds", "steps", "make env s", "env-steps/s", "physics/s", "step/physics")
    print(f"{header[0]:6s} " + " ".join(f"{h:>12s}" for h in header[1:]), flush=True)
    for kind in kinds:
        for w in worlds:
            r = bench_one(kind, w, episodes, device, overrides)
            print(
                f"{kind:6s} {w:12d} {r['steps']:12d} {r['make_s']:12.1f} {r['env_steps_per_s']:12.0f} "
                f"{r['physics_steps_per_s']:12.0f} {r['ratio']:12.2f}",
                flush=True,
            )
    print(
        "targets (2-core CPU, one process): >= 500 env-steps/s rigid and >= 100 soft at 8+ worlds; "
        "step/physics <= 1.25"
    )
