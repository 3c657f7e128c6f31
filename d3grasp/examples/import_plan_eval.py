"""A mesh of your own: imported as a rigid object, its grasps planned in simulation, the rule-based
controller evaluated on it under the camera and at the true pose.

    python -m d3grasp.examples.import_plan_eval [MESH ...] [--out DIR] [--episodes 4] [--budget 12]

Without a mesh it makes one: a 7 x 4.5 x 4.5 cm capsule (trimesh), written as STL. The three steps
are ``d3grasp-assets import`` (USD with its collision hulls, a manifest), ``d3grasp-assets
plan-grasps`` (the evaluation schedule; ``--budget`` is its last round's trials per kept grasp) and
``d3grasp-eval --objects DIR/manifest.json`` (docs/own_objects.md walks through the same).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import Any

import trimesh

from d3grasp.authoring.importer import import_meshes
from d3grasp.console import quiet_warp
from d3grasp.envs.grasp_file import read_grasp_file
from d3grasp.eval.evaluate import EvalSettings, evaluate
from d3grasp.eval.metrics import summary_rows
from d3grasp.parallel import default_workers
from d3grasp.planner.plan import PlannerConfig, evaluation_planner, plan_grasps


def example_mesh(folder: Path) -> Path:
    """A capsule lying on its side, 7 cm long and 4.5 cm across, as an STL file."""
    capsule = trimesh.creation.capsule(height=0.025, radius=0.0225)  # the axis is z: 2.5 + 2 x 2.25 cm
    capsule.apply_transform(trimesh.transformations.rotation_matrix(1.5707963, [0.0, 1.0, 0.0]))
    folder.mkdir(parents=True, exist_ok=True)
    capsule.export(folder / "capsule.stl")
    return folder / "capsule.stl"


def run(
    meshes: list[Path] | None = None,
    out: str | Path = "logs/example_import",
    episodes: int = 4,
    planner: PlannerConfig | None = None,
    workers: int | None = None,
) -> dict[str, Any]:
    """Import, plan and evaluate; returns the evaluation's ``results.json`` content."""
    quiet_warp()
    out = Path(out)
    meshes = meshes or [example_mesh(out / "meshes")]
    workers = workers or default_workers()
    imported = import_meshes(meshes, out / "library", workers=workers)
    for e in imported.entries:
        print(f"imported {e.id}: {e.kind}, {e.size_bin}, {e.mass * 1e3:.0f} g -> {e.path}")
    manifest = out / "library" / "manifest.json"
    path = plan_grasps(manifest, cfg=planner or evaluation_planner(seed=0), workers=workers)
    for oid, rec in read_grasp_file(path)["objects"].items():
        for grasp, g in rec["grasps"].items():
            t = g["trials"]
            held = f"lifted {t['lift']} and held {t['disturb']} of {t['of']} trials"
            print(f"{oid} {grasp:5s} score {g['score']:.2f}: {held}")
    settings = EvalSettings(
        objects=str(manifest), episodes_per_object=episodes, perception="both", num_envs=4
    )
    result = evaluate(settings, progress=False, workers=workers)
    for label, eps in result.runs.items():
        rows = {r["metric"]: r for r in summary_rows(eps) if r["column"] == "Average"}
        rates = ", ".join(f"{m} {r['successes']}/{r['trials']}" for m, r in rows.items())
        print(f"{label}: {rates}")
    return result.to_json()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "meshes", nargs="*", type=Path, help="mesh files (STL, OBJ, PLY, ...); default: a capsule"
    )
    ap.add_argument("--out", default="logs/example_import", help="folder for the library and meshes")
    ap.add_argument("--episodes", type=int, default=4, help="evaluation episodes per object and perception")
    ap.add_argument("--budget", type=int, default=12, help="the planner's last-round trials per kept grasp")
    args = ap.parse_args(argv)
    run(args.meshes, args.out, args.episodes, replace(evaluation_planner(seed=0), final_trials=args.budget))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
