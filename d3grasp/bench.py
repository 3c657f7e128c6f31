"""Benchmarks: ``python -m d3grasp.bench kernels``, ``env`` and ``train``; ``soak`` (see d3grasp.soak);
``shift``, the share of grasp outcomes a 1 mm whole-scene shift flips (see d3grasp.eval.shift).

``kernels`` times one launch of each batched kernel group for 1, 16 and 256 worlds with realistic
sizes per world: 11 pads on a 20-shape hand+object, 2000 contact rows (1000 rigid + 1000 soft, half
active), one soft object of 512 nodes / 2058 tets (an 8x8x8 grid), 16 joints, 16 links, 16
hand-to-table distances. Figures are medians over repeats after a warm-up, in ms per launch, plain
launches (no graph capture) so the Python launch overhead is included. The ratio column compares
tactile + strain + rewards with one physics substep of the grasp scene (the design target is <= 10%
of one environment step); it prints "n/a" until the scene exists, unless ``--substep-ms`` is given.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from types import SimpleNamespace

import numpy as np

__all__ = ["main", "physics_substep_ms"]


def physics_substep_ms(num_worlds: int) -> float | None:
    """Time of one captured physics substep of the grasp scene with ``num_worlds`` worlds, in ms.

    Builds the default (mixed rigid/soft) task with that many worlds, captures one substep
    (clear forces, disturbance, collide, SolverVBD step) and returns its median replay time.
    """
    import torch
    import warp as wp

    from d3grasp.envs import make_env

    env = make_env(num_envs=num_worlds, sim__use_graph=False)
    for _ in range(2):
        env.step(torch.zeros(num_worlds, env.num_actions))
    substeps = env.cfg.sim.substeps
    env.cfg.sim.substeps = 2  # two substeps keep the state swap even; time per substep = half
    with wp.ScopedDevice(env.wp_device), wp.ScopedCapture() as cap:
        env.physics.substeps()
    env.cfg.sim.substeps = substeps
    graph = cap.graph
    return 0.5 * _median_ms(lambda: wp.capture_launch(graph), repeats=10)


def _median_ms(fn: Callable[[], None], repeats: int, warmup: int = 2) -> float:
    import warp as wp

    for _ in range(warmup):
        fn()
    wp.synchronize()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        wp.synchronize()
        samples.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(samples)


def _kernel_fixtures(num_worlds: int, rng: np.random.Generator) -> dict[str, Callable[[], None]]:
    """Device data for every kernel group at realistic per-world sizes; returns one closure per group."""
    import warp as wp

    from d3grasp.kernels import rewards, rotation, strain, strain_numpy, tactile

    w = num_worlds
    # --- tactile: 20 shapes per world (11 pads), one ground shape, 2000 rows per world
    shapes_per_world, rows = 20, 1000
    n_shapes = 1 + w * shapes_per_world
    shape_pad = np.full(n_shapes, -1)
    shape_world = np.full(n_shapes, -1)
    for i in range(w):
        base = 1 + i * shapes_per_world
        shape_world[base : base + shapes_per_world] = i
        shape_pad[base : base + tactile.NUM_PADS] = np.arange(tactile.NUM_PADS)
    shape_body = np.maximum(np.arange(n_shapes) - 1, -1)
    layout = tactile.TactileLayout.from_arrays(
        shape_pad, shape_world, shape_body, np.tile([0.0, 0.0, 0.0, 1.0], (n_shapes, 1)), w
    )
    rmax = smax = rows * w

    def i32(a: np.ndarray) -> wp.array:
        return wp.array(np.asarray(a, dtype=np.int32), dtype=wp.int32)

    contacts = SimpleNamespace(
        rigid_contact_max=rmax,
        rigid_contact_count=i32([rmax // 2]),
        rigid_contact_shape0=i32(rng.integers(0, n_shapes, rmax)),
        rigid_contact_shape1=i32(rng.integers(0, n_shapes, rmax)),
        soft_contact_count=i32([smax // 2]),
        soft_contact_shape=i32(rng.integers(0, n_shapes, smax)),
    )
    contact_f = wp.array(rng.normal(size=(rmax + smax, 6)).astype(np.float32), dtype=wp.spatial_vector)
    body_q = wp.array(
        np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (n_shapes, 1)).astype(np.float32), dtype=wp.transform
    )
    world_f = wp.zeros((w, tactile.NUM_PADS), dtype=wp.vec3)
    pad_f = wp.zeros((w, tactile.NUM_PADS), dtype=wp.vec3)
    pad_c = wp.zeros((w, tactile.NUM_PADS), dtype=float)
    tcfg = tactile.TactileConfig(noise_std=0.05)

    def run_tactile() -> None:
        tactile.accumulate_pad_forces(layout, contacts, contact_f, world_f)
        tactile.pad_frame_forces(layout, world_f, body_q, tcfg, pad_f, pad_c)

    # --- strain and pose: one 512-node, 2058-tet object per world
    rest1, tets1 = strain_numpy.grid_tet_mesh(8, 8, 8, spacing=0.008)
    n1 = len(rest1)
    rest = np.concatenate([rest1 + [0.5 * i, 0.0, 0.0] for i in range(w)])
    tets = np.concatenate([tets1 + i * n1 for i in range(w)])
    tet_obj = np.repeat(np.arange(w), len(tets1))
    slayout = strain.StrainLayout.from_arrays(rest, tets, tet_obj, object_world=np.arange(w))
    sbuf = strain.StrainBuffers.allocate(slayout)
    points = wp.array((rest + 0.001 * rng.normal(size=rest.shape)).astype(np.float32), dtype=wp.vec3)
    pose = rotation.ObjectPoseBuffers.allocate(slayout)

    def run_strain() -> None:
        strain.compute_strain(slayout, points, sbuf)
        strain.compute_sigma(slayout, points, sbuf)

    def run_pose() -> None:
        rotation.compute_object_pose(slayout, points, sbuf.sigma, pose)
        rotation.update_object_velocity(pose, 1.0 / 60.0)

    # --- rewards: 16 joints, 16 links, 11 pads, 16 hand-to-table distances
    j = 16
    inp = rewards.make_inputs(
        alive=np.ones(w),
        joint_q=rng.uniform(0, 1.5, (w, j)),
        joint_q_ref=np.zeros((w, j)),
        joint_qd=rng.normal(size=(w, j)),
        link_pos=rng.normal(size=(w, j, 3)) * 0.1,
        object_com=rng.normal(size=(w, 3)) * 0.1,
        pad_force=rng.normal(size=(w, tactile.NUM_PADS, 3)),
        pad_contact=np.ones((w, tactile.NUM_PADS)),
        obj_lin_vel=rng.normal(size=(w, 3)),
        obj_ang_vel=rng.normal(size=(w, 3)),
        env_dist=rng.uniform(0.0, 0.05, (w, j)),
        eps_bar=rng.uniform(0, 0.2, w),
        node_count=np.full(w, float(n1)),
        is_deformable=np.ones(w, dtype=np.int32),
        object_rise=rng.uniform(0.0, 0.1, w),
    )
    rbuf = rewards.RewardBuffers.allocate(rewards.RewardConfig(), w, j, tactile.NUM_PADS)

    def run_rewards() -> None:
        rewards.compute_rewards(inp, rbuf)

    return {"tactile": run_tactile, "strain": run_strain, "pose": run_pose, "rewards": run_rewards}


def _cmd_kernels(args: argparse.Namespace) -> int:
    import warp as wp

    from d3grasp.console import quiet_warp

    quiet_warp()  # initialises Warp
    rng = np.random.default_rng(0)
    with wp.ScopedDevice(args.device):
        print(f"d3grasp kernel benchmark on {wp.get_device()} (Warp {wp.__version__}); ms per launch, median")
        cols = ("tactile", "strain", "pose", "rewards", "t+s+r", "us/world")
        print(f"{'worlds':>7} " + " ".join(f"{c:>9}" for c in cols) + "  ratio (t+s+r) / physics substep")
        for w in args.worlds:
            fns = _kernel_fixtures(w, rng)
            ms = {name: _median_ms(fn, args.repeats) for name, fn in fns.items()}
            tsr = ms["tactile"] + ms["strain"] + ms["rewards"]
            substep = args.substep_ms if args.substep_ms is not None else physics_substep_ms(w)
            ratio = "n/a" if substep is None else f"{tsr / substep:.3f} (substep {substep:.1f} ms)"
            print(
                f"{w:>7} {ms['tactile']:>9.3f} {ms['strain']:>9.3f} {ms['pose']:>9.3f} {ms['rewards']:>9.3f}"
                f" {tsr:>9.3f} {1e3 * tsr / w:>9.1f}  {ratio}"
            )
    return 0


def _add_kernels_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("kernels", help="time tactile, strain, pose and reward kernels per launch")
    p.add_argument("--worlds", type=int, nargs="+", default=[1, 16, 256], help="world counts")
    p.add_argument("--repeats", type=int, default=20, help="timed repeats per kernel group (median reported)")
    p.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    p.add_argument("--substep-ms", type=float, default=None, help="physics substep time [ms] to compare with")
    p.set_defaults(func=_cmd_kernels)


def _cmd_train(args: argparse.Namespace) -> int:
    # The training stack lives in d3grasp.train (which imports d3grasp): import it only when asked.
    from d3grasp.train.benchmark import run_train_benchmark

    run_train_benchmark(
        args.task,
        args.worlds,
        args.procs,
        args.iterations,
        args.steps,
        args.env_factory,
        args.device,
        torch_threads=args.torch_threads,
        rank_layouts=args.rank_worlds,
        overrides=args.set,
        rank_overrides=args.rank_set,
    )
    return 0


def _add_train_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="end-to-end training throughput (env-steps/s incl. PPO update), 1..P procs"
    )
    p.add_argument("--task", default="D3Grasp-DexHand13-Mixed-v0", help="registered task")
    p.add_argument("--worlds", type=int, nargs="+", default=[8, 16, 32], help="total world counts")
    p.add_argument("--procs", type=int, nargs="+", default=[1, 2], help="process counts (torchrun for > 1)")
    p.add_argument("--iterations", type=int, default=4, help="PPO iterations per run (the first is dropped)")
    p.add_argument("--steps", type=int, default=24, help="rollout steps per world and iteration")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--torch_threads", type=int, default=1, help="torch threads per process (default 1)")
    p.add_argument("--env_factory", default=None, help="advanced: 'module:function' building the VecEnv")
    p.add_argument(
        "--rank_worlds",
        type=int,
        nargs="+",
        action="append",
        default=[],
        metavar="N",
        help="worlds per rank, one count per rank (repeat the flag for more layouts; replaces --worlds "
        "and --procs), e.g. 96 4 with --rank_set for the shipped recipe's rigid and soft ranks",
    )
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="passed on to training")
    p.add_argument("--rank_set", action="append", default=[], metavar="RANK:KEY=VALUE", help="passed on too")
    p.set_defaults(func=_cmd_train)


def _cmd_env(args: argparse.Namespace) -> int:
    from d3grasp.console import quiet_warp
    from d3grasp.envs.benchmark import run_env_benchmark

    quiet_warp()

    run_env_benchmark(
        args.worlds,
        args.kinds,
        episodes=args.episodes,
        device=args.device,
        overrides=dict(args.overrides),
        procs=args.procs,
    )
    return 0


def _add_env_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("env", help="env-steps/s and physics steps/s, rigid and soft, vs world count")
    p.add_argument("--worlds", type=int, nargs="+", default=[1, 8, 32], help="world counts")
    p.add_argument("--kinds", nargs="+", default=["rigid", "soft"], choices=["rigid", "soft"])
    from d3grasp.cli.args import add_env_override_arg, positive_float, positive_int

    p.add_argument(
        "--procs",
        type=positive_int,
        nargs="+",
        default=[1],
        help="process counts, each row run in that many at once",
    )

    p.add_argument("--episodes", type=positive_float, default=1.0, help="timed episodes per row (0.5: half)")
    p.add_argument("--device", default="cpu", help="cpu or cuda:N")
    add_env_override_arg(p, "env config override, e.g. sim.substeps=8 (a faster profile to compare)")
    p.set_defaults(func=_cmd_env)


def _cmd_soak(args: argparse.Namespace) -> int:
    from d3grasp.soak import run_soak

    report = run_soak(
        args.steps,
        task=args.task,
        num_envs=args.num_envs,
        seed=args.seed,
        rebuild_every=args.rebuild_every,
        soft_fraction=args.soft_fraction,
        overrides=dict(args.overrides),
        state=args.state,
        resume=args.resume,
        device=args.device,
        progress=not args.no_progress,
    )
    print(report.summary())
    return 1 if report.crashes else 0


def _add_soak_parser(sub: argparse._SubParsersAction) -> None:
    from d3grasp.cli.args import add_env_override_arg, positive_int

    p = sub.add_parser(
        "soak",
        help="random actions on mixed rigid and soft worlds for N env-steps: resets, blow-ups, crashes",
    )
    p.add_argument("--steps", type=positive_int, default=100_000, help="env-steps in all (default 1e5)")
    p.add_argument("--task", default=None, help="registered task (default: the mixed task)")
    p.add_argument("--num_envs", type=positive_int, default=16, help="worlds per build (default 16)")
    p.add_argument(
        "--rebuild_every", type=positive_int, default=20_000, help="env-steps between object redraws"
    )
    p.add_argument(
        "--soft_fraction",
        type=float,
        default=0.25,
        help="share of soft worlds (default 0.25, as in training)",
    )
    add_env_override_arg(p, "env config override, e.g. sim.iterations=10")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--state", default=None, help="JSON file the progress is saved to after each build")
    p.add_argument("--resume", action="store_true", help="continue the soak saved in --state")
    p.add_argument("--device", default="cpu", help="cpu or cuda:N")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_soak)


def _cmd_shift(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from d3grasp.console import quiet_warp
    from d3grasp.eval.shift import run_shift_benchmark

    quiet_warp()
    report = run_shift_benchmark(
        shift_m=args.mm * 1e-3,
        seeds=args.seeds,
        split=args.split,
        objects=args.objects,
        num_envs=args.num_envs,
        workers=args.workers,
        overrides=dict(args.overrides),
        progress=not args.no_progress,
    )
    print(report.summary())
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(report.to_json(), indent=1) + "\n", encoding="utf-8")
        print(f"[bench shift] wrote {args.out}")
    return 0


def _add_shift_parser(sub: argparse._SubParsersAction) -> None:
    from d3grasp.cli.args import add_env_override_arg, positive_float, positive_int

    p = sub.add_parser(
        "shift",
        help="brittleness: the share of objects whose rule outcome a 1 mm whole-scene shift changes",
    )
    p.add_argument("--mm", type=positive_float, default=1.0, help="shift of the scene in mm (default 1)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="evaluation seeds (default 0)")
    p.add_argument("--split", choices=("test", "train", "all"), default="test")
    p.add_argument("--objects", default="diverse", help="diverse | deformable | all (default diverse)")
    p.add_argument("--num_envs", type=positive_int, default=16, help="worlds per batch (default 16)")
    p.add_argument("--workers", type=positive_int, default=None, help="processes (default: the cores)")
    add_env_override_arg(p, "env config override for every run (not scene_shift)")
    p.add_argument("--out", default=None, help="write the outcomes as JSON here")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_shift)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m d3grasp.bench", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    _add_kernels_parser(sub)
    _add_train_parser(sub)
    _add_env_parser(sub)
    _add_soak_parser(sub)
    _add_shift_parser(sub)
    args = parser.parse_args(argv)
    if any(w < 1 for w in getattr(args, "worlds", [1])):
        parser.error("--worlds must be positive")
    return int(args.func(args))


if __name__ == "__main__":
    raise SystemExit(main())
