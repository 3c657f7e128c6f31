"""``d3grasp-assets``: build, import, validate and list simulation assets.

    d3grasp-assets build [--tools-dir DIR] [--out DIR] [--only hand,rigid,soft]
    d3grasp-assets import MESH... --out DIR [--deformable --youngs-modulus E --poisson P --target-tets N]
                          [--density RHO] [--friction MU] [--scale S] [--family NAME]
                          [--skip-invalid] [--no-plan-grasps] [--workers N]
    d3grasp-assets validate [DIR|MANIFEST] [--no-hand]
    d3grasp-assets list [DIR|MANIFEST]
    d3grasp-assets plan-grasps DIR|MANIFEST [--ids A,B] [--seed S] [--workers N] [--per-type K]
                               [--schedule legacy|evaluation] [--final-trials N]
    d3grasp-assets plan-grasps DIR|MANIFEST --ids A,B --adopt OTHER/grasps.json

Exit status: 0 success, 1 validation failure, 2 bad input (one line ``error: <file>: <reason>``;
nothing written), 3 ``import --skip-invalid`` wrote some meshes and refused others (one line
``skipped <file>: <reason>`` each on stderr).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from types import ModuleType
from typing import Any

EXIT_FAIL = 1
EXIT_BAD_INPUT = 2
EXIT_PARTIAL = 3


def _progress(desc: str, unit: str = "asset"):
    """A tqdm wrapper for the library functions' ``progress`` hooks (bars go to stderr)."""
    from tqdm import tqdm

    def wrap(items: Iterable[Any]) -> Iterable[Any]:
        return tqdm(list(items), desc=desc, unit=unit, leave=False, file=sys.stderr)

    return wrap


def _error(msg: str) -> int:
    print(f"error: {msg}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _resolve_manifest(arg: str | None) -> Path:
    from d3grasp.paths import default_manifest

    if arg is None:
        return default_manifest()
    p = Path(arg)
    return p / "manifest.json" if p.is_dir() else p


# ---------------------------------------------------------------------------------- build


def find_tools_dir(explicit: str | None = None) -> Path:
    """The checkout's ``tools/`` directory: ``--tools-dir``, else next to the installed package.

    Raises ``FileNotFoundError`` with a clear message when this is not a source checkout.
    """
    if explicit:
        d = Path(explicit).resolve()
        if not (d / "build_rigid_objects.py").is_file():
            raise FileNotFoundError(f"{d}: not a d3grasp tools/ directory (no build_rigid_objects.py)")
        return d
    import d3grasp

    d = Path(d3grasp.__file__).resolve().parents[1] / "tools"
    if not (d / "build_rigid_objects.py").is_file():
        raise FileNotFoundError(
            "the build command needs a source checkout of d3grasp (tools/ not found next to the "
            f"installed package at {d.parent}); clone the repository and run it there, or pass --tools-dir"
        )
    return d


def _load_tool(tools_dir: Path, name: str) -> ModuleType:
    path = tools_dir / f"{name}.py"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: builder not found")
    spec = importlib.util.spec_from_file_location(f"d3grasp_tools_{name}", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses (and pickling) look the module up by name
    spec.loader.exec_module(mod)
    return mod


def cmd_build(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    try:
        tools = find_tools_dir(args.tools_dir)
    except FileNotFoundError as exc:
        return _error(str(exc))
    out = Path(args.out) if args.out else tools.parent / "assets_usd"
    steps = [s.strip() for s in args.only.split(",")] if args.only else ["hand", "rigid", "soft"]
    unknown = set(steps) - {"hand", "rigid", "soft"}
    if unknown:
        return _error(f"--only: unknown builders {sorted(unknown)} (choose from hand, rigid, soft)")
    for step in tqdm(steps, desc="build", unit="builder", file=sys.stderr):
        t0 = time.perf_counter()
        if step == "hand":
            mod = _load_tool(tools, "build_hand")
            result = mod.build(out / "hands" / "dexhand13.usda")
            print(f"hand: {result} ({time.perf_counter() - t0:.1f} s)")
        else:
            mod = _load_tool(tools, "build_rigid_objects" if step == "rigid" else "build_soft_objects")
            entries = mod.build(out)
            print(f"{step}: {len(entries)} assets ({time.perf_counter() - t0:.1f} s)")
    print(f"library written to {out}")
    return 0


# ---------------------------------------------------------------------------------- import


def cmd_import(args: argparse.Namespace) -> int:
    from d3grasp.authoring.importer import import_meshes
    from d3grasp.authoring.meshcheck import MeshError
    from d3grasp.parallel import default_workers

    kw: dict[str, Any] = {}
    if args.youngs_modulus is not None:
        kw["youngs_modulus"] = args.youngs_modulus
    if args.poisson is not None:
        kw["poissons_ratio"] = args.poisson
    if args.target_tets is not None:
        kw["target_tets"] = args.target_tets
    if not args.deformable and kw:
        return _error("--youngs-modulus/--poisson/--target-tets only apply with --deformable")
    try:
        result = import_meshes(
            args.meshes,
            args.out,
            deformable=args.deformable,
            scale=args.scale,
            density=args.density,
            friction=args.friction,
            family=args.family,
            skip_invalid=args.skip_invalid,
            progress=_progress("import", "mesh"),
            workers=args.workers or default_workers(),
            **kw,
        )
    except (MeshError, ValueError, FileNotFoundError, ImportError) as exc:
        return _error(str(exc))
    replaced = {e.id: e for e in result.replaced}
    for e in result.entries:
        extra = (
            f"{e.stats['num_hulls']} hulls"
            if e.kind == "rigid"
            else f"{e.stats['num_tets']} tets, {e.stats['num_nodes']} nodes"
        )
        dims = " x ".join(f"{x * 100:.1f}" for x in e.extents)
        print(f"{e.id}: {e.kind}, {e.size_bin}, {dims} cm, {e.mass * 1e3:.1f} g, {extra} -> {e.path}")
        if e.id in replaced:
            old = replaced[e.id]
            print(f"  replaced the {old.kind} asset {old.id} ({old.path}, from {old.source or 'unknown'})")
    print(f"{len(result.entries)} assets written; manifest {Path(args.out) / 'manifest.json'}")
    if args.plan_grasps and result.entries:
        # The same treatment as a shipped object: candidate grasps scored in simulation.
        code = _plan_grasps(
            Path(args.out) / "manifest.json",
            [e.id for e in result.entries],
            workers=args.workers,
            schedule=args.schedule,
            final_trials=args.final_trials,
        )
        if code:
            return code
    for path, why in result.skipped:
        print(f"skipped {path}: {why}", file=sys.stderr)
    if result.skipped:
        print(f"{len(result.skipped)} of {len(args.meshes)} meshes refused (listed above)", file=sys.stderr)
        return EXIT_PARTIAL
    return 0


# ---------------------------------------------------------------------------------- plan-grasps


def _add_schedule_args(p: argparse.ArgumentParser) -> None:
    from d3grasp.cli.args import positive_int
    from d3grasp.planner.plan import SCHEDULES

    p.add_argument(
        "--schedule",
        choices=SCHEDULES,
        default="evaluation",
        help="evaluation (default; the shipped library's rigid objects): successive halving under "
        "the evaluation's draws, the camera's and the true pose's placements and its 2 s pushes, "
        "each kept grasp with 16 trials and a measured rate; legacy: 3 trials per finalist without "
        "the evaluation's draws (the plan before 2026-12-08, ~3x cheaper)",
    )
    p.add_argument(
        "--final-trials",
        type=positive_int,
        default=None,
        help="evaluation schedule: the last round's trials per kept grasp, the planning budget "
        "(default 12: 16 trials in all; each costs ~3 screening trials)",
    )


def cmd_plan_grasps(args: argparse.Namespace) -> int:
    if args.path is None:
        # The plan is written next to the manifest it plans: with no library named that would be the
        # installed package's own folder, which a system-wide install cannot write (and a user's
        # plan does not belong in). The shipped library is replanned by naming it, in a checkout.
        return _error(
            "plan-grasps writes grasps.json next to the library's manifest.json: name the library "
            "folder (d3grasp-assets plan-grasps DIR), e.g. the --out folder of your import, or "
            "assets_usd/ of a source checkout to replan the shipped library"
        )
    ids = [i for i in args.ids.split(",") if i] if args.ids else None
    if args.adopt is not None:
        return _adopt_plans(_resolve_manifest(args.path), Path(args.adopt), ids)
    return _plan_grasps(
        _resolve_manifest(args.path),
        ids,
        args.seed,
        args.workers,
        args.per_type,
        schedule=args.schedule,
        final_trials=args.final_trials,
    )


def _adopt_plans(manifest: Path, source: Path, ids: list[str] | None) -> int:
    """Copy the plans of ``ids`` from another grasp file, each with its own planner settings."""
    from d3grasp.envs.grasp_file import GraspFileError
    from d3grasp.planner.plan import adopt_plans

    if not ids:
        return _error("--adopt takes the plans of the objects named by --ids: give --ids")
    try:
        path = adopt_plans(manifest, source, ids)
    except (GraspFileError, ValueError) as exc:
        return _error(str(exc))
    print(f"{len(ids)} plans adopted from {source} into {path}, each with the planner settings it records")
    return 0


def _plan_grasps(
    manifest: Path,
    ids: list[str] | None,
    seed: int = 0,
    workers: int | None = None,
    per_type: int | None = None,
    schedule: str = "evaluation",
    final_trials: int | None = None,
) -> int:
    """Plan ``ids`` (None: every object) of a library and print how many lifted and held."""
    from dataclasses import replace

    from d3grasp.console import quiet_warp
    from d3grasp.envs.grasp_file import GraspFileError, read_grasp_file
    from d3grasp.parallel import default_workers
    from d3grasp.planner.plan import PlannerConfig, evaluation_planner, plan_grasps

    quiet_warp()
    if not manifest.is_file():
        return _error(f"{manifest}: manifest not found")
    if not os.access(manifest.parent, os.W_OK):
        # Refused before any trial runs: the plan is written (atomically, so into this folder) as
        # each group of objects finishes, and an hour of planning would end in a PermissionError.
        return _error(
            f"{manifest.parent}: not writable, and grasps.json is written there; copy the library to a "
            "folder you can write and plan that copy (d3grasp-assets plan-grasps COPY)"
        )
    cfg = evaluation_planner(seed) if schedule == "evaluation" else PlannerConfig(seed=seed)
    if final_trials is not None:
        if schedule != "evaluation":
            return _error(
                "--final-trials sets the evaluation schedule's last round: give --schedule evaluation"
            )
        cfg = replace(cfg, final_trials=final_trials)
    if per_type is not None:
        cfg = replace(cfg, candidates=replace(cfg.candidates, per_type=per_type))
    t0 = time.perf_counter()
    try:
        path = plan_grasps(manifest, ids, cfg, workers=workers or default_workers(), progress=True)
    except (GraspFileError, ValueError, FileNotFoundError) as exc:
        return _error(str(exc))
    objects = read_grasp_file(path)["objects"]
    held = sum(1 for rec in objects.values() if any(g["trials"]["disturb"] for g in rec["grasps"].values()))
    lifted = sum(1 for rec in objects.values() if any(g["trials"]["lift"] for g in rec["grasps"].values()))
    print(
        f"{len(objects)} objects planned in {path}: {lifted} with a grasp that lifted in simulation, "
        f"{held} with one that held through the pushes ({time.perf_counter() - t0:.0f} s)"
    )
    return 0


# ---------------------------------------------------------------------------------- validate


def cmd_validate(args: argparse.Namespace) -> int:
    from d3grasp.console import quiet_warp

    quiet_warp()  # keep the summary table readable: no Warp banner or module-load lines on stdout
    from d3grasp.authoring.validate import validate_library

    mpath = _resolve_manifest(args.path)
    t0 = time.perf_counter()
    try:
        report = validate_library(mpath, hand=not args.no_hand, progress=_progress("validate"))
    except (FileNotFoundError, ValueError) as exc:
        return _error(str(exc))
    print(report.table())
    print(f"validated {len(report.assets)} assets in {time.perf_counter() - t0:.1f} s")
    if not report.ok:
        for f in report.failures()[:50]:
            print(f"FAIL {f}", file=sys.stderr)
        return EXIT_FAIL
    return 0


# ---------------------------------------------------------------------------------- list


def cmd_list(args: argparse.Namespace) -> int:
    from d3grasp.authoring.manifest import SIZE_BINS, read_manifest

    mpath = _resolve_manifest(args.path)
    try:
        entries = read_manifest(mpath)
    except (FileNotFoundError, ValueError) as exc:
        return _error(str(exc))
    print(f"manifest: {mpath.resolve()} ({len(entries)} assets)")
    for kind in sorted({e.kind for e in entries}):
        for b in SIZE_BINS:
            es = sorted((e for e in entries if e.kind == kind and e.size_bin == b), key=lambda e: e.id)
            if not es:
                continue
            lo, hi = SIZE_BINS[b]
            print(f"\n{kind} / {b} ({lo * 100:g}-{hi * 100:g} cm): {len(es)}")
            for e in es:
                dims = "x".join(f"{x * 100:.1f}" for x in e.extents)
                print(
                    f"  {e.id:<20} {e.family:<13} {dims:>17} cm {e.mass * 1e3:7.1f} g  "
                    f"{e.material.get('friction', '-')!s:>5}  {e.split}"
                )
    return 0


# ---------------------------------------------------------------------------------- main


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="d3grasp-assets", description="Build, import, validate and list d3grasp assets."
    )
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("build", help="regenerate the hand and object library from tools/ (slow)")
    p.add_argument("--tools-dir", help="the checkout's tools/ directory (default: found next to the package)")
    p.add_argument("--out", help="library root to write (default: assets_usd/ of the checkout)")
    p.add_argument("--only", help="comma-separated subset of hand,rigid,soft")
    p.set_defaults(func=cmd_build)

    p = sub.add_parser("import", help="turn OBJ/STL/PLY/GLB meshes into USD assets + manifest")
    p.add_argument("meshes", nargs="+", metavar="MESH")
    p.add_argument("--out", required=True, help="output library directory (manifest.json is written there)")
    p.add_argument(
        "--deformable", action="store_true", help="make FEM tet soft bodies instead of rigid objects"
    )
    p.add_argument("--youngs-modulus", type=float, help="Young's modulus E in Pa (deformable; default 5e4)")
    p.add_argument("--poisson", type=float, help="Poisson's ratio (deformable; default 0.3)")
    p.add_argument("--target-tets", type=int, help="tets to aim for, 200-2000 (deformable; default 800)")
    p.add_argument("--density", type=float, help="kg/m^3 (default 1000 rigid, 200 deformable)")
    p.add_argument("--friction", type=float, help="friction coefficient (default 0.8 rigid, 1.0 deformable)")
    p.add_argument(
        "--scale", type=float, default=1.0, help="uniform scale to metres (e.g. 0.001 for mm files)"
    )
    p.add_argument("--family", default="imported", help="family name recorded in the manifest")
    p.add_argument(
        "--skip-invalid",
        action="store_true",
        help="import the meshes that pass and list the others with their reasons (exit 3); by "
        "default one invalid mesh imports nothing (exit 2)",
    )
    p.add_argument(
        "--no-plan-grasps",
        dest="plan_grasps",
        action="store_false",
        help="skip planning the new objects' grasps (plan-grasps; about a minute a rigid object on 2 cores, "
        "minutes a soft one, docs/grasp_planning.md#cost): "
        "until planned they get the geometric rule's grasp",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=None,
        help="processes for authoring and grasp planning (default: the machine's cores)",
    )
    _add_schedule_args(p)
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("validate", help="load every asset in Newton and check it against the manifest")
    p.add_argument(
        "path", nargs="?", help="library directory or manifest.json (default: the shipped library)"
    )
    p.add_argument("--no-hand", action="store_true", help="skip the hand USD")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("list", help="print the library by kind and size bin")
    p.add_argument(
        "path", nargs="?", help="library directory or manifest.json (default: the shipped library)"
    )
    p.set_defaults(func=cmd_list)

    p = sub.add_parser(
        "plan-grasps",
        help="score candidate grasps of every object in simulation; write the best per type to grasps.json",
    )
    p.add_argument(
        "path",
        nargs="?",  # checked by the command: its one-line error says what to give
        help="library directory or manifest.json; grasps.json is written next to the manifest",
    )
    p.add_argument("--ids", help="comma-separated asset ids (default: every object of the manifest)")
    p.add_argument("--seed", type=int, default=0, help="candidate seed (same seed, same plan)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: the machine's cores)")
    p.add_argument("--per-type", type=int, default=None, help="candidates per grasp type (default 10)")
    _add_schedule_args(p)
    p.add_argument(
        "--adopt",
        metavar="GRASPS_JSON",
        help="instead of planning, copy the plans of --ids from this other grasp file, each keeping "
        "the planner settings it was measured under (a later plan-grasps under the file's settings "
        "replans them)",
    )
    p.set_defaults(func=cmd_plan_grasps)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    raise SystemExit(main())
