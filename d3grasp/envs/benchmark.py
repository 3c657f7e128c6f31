"""Environment throughput: env-steps/s and physics steps/s for rigid and soft objects (``bench env``).

For each object kind and world count: the time to make the environment (cold when the Warp
kernel cache is empty, warm otherwise), the median wall time of a full ``env.step`` (captured
physics + sensors + kernels + observations + rewards + scoring) and of the bare captured physics
(``substeps`` x collide + SolverVBD step), and their ratio.
"""

from __future__ import annotations

import statistics
import time

import torch
import warp as wp

from d3grasp.envs import make_env

TASK_BY_KIND = {"rigid": "D3Grasp-DexHand13-Diverse-v0", "soft": "D3Grasp-DexHand13-Deformable-v0"}


def _median_s(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_one(kind: str, worlds: int, steps: int, device: str) -> dict[str, float]:
    t0 = time.perf_counter()
    env = make_env(TASK_BY_KIND[kind], num_envs=worlds, device=device)
    make_s = time.perf_counter() - t0
    actions = torch.zeros(worlds, env.num_actions)
    for _ in range(3):
        env.step(actions)
    step_s = _median_s(lambda: env.step(actions), steps)
    with wp.ScopedDevice(env.wp_device), wp.ScopedCapture() as cap:
        env._physics()
    graph = cap.graph
    wp.capture_launch(graph)
    phys_s = _median_s(lambda: (wp.capture_launch(graph), wp.synchronize_device(env.wp_device)), steps)
    return {
        "make_s": make_s,
        "env_steps_per_s": worlds / step_s,
        "physics_steps_per_s": worlds / phys_s,
        "ratio": step_s / phys_s,
    }


def run_env_benchmark(worlds: list[int], kinds: list[str], steps: int = 30, device: str = "cpu") -> None:
    print(f"env benchmark on {device}: median of {steps} control steps (60 Hz, substeps from SimConfig)")
    header = ("kind", "worlds", "make env s", "env-steps/s", "physics/s", "step/physics")
    print(f"{header[0]:6s} " + " ".join(f"{h:>12s}" for h in header[1:]))
    for kind in kinds:
        for w in worlds:
            r = bench_one(kind, w, steps, device)
            print(
                f"{kind:6s} {w:12d} {r['make_s']:12.1f} {r['env_steps_per_s']:12.0f} "
                f"{r['physics_steps_per_s']:12.0f} {r['ratio']:12.2f}"
            )
    print(
        "targets (2-core CPU, one process): >= 500 env-steps/s rigid and >= 100 soft at 8+ worlds; "
        "step/physics <= 1.25"
    )
