"""Import a dozen ordinary shapes as soft bodies, several times each, and count what succeeds.

    python tools/soft_import_study.py --runs 5 [--out DIR]

Each shape is made with trimesh at the size of an everyday soft object (bars, plates, rings,
L-shapes, thin cylinders ...), exported as STL and imported through the same code as
``d3grasp-assets import MESH --deformable --no-plan-grasps`` (``import_meshes``), one mesh per
import, so that one failure cannot hide another. Prints one row per shape: successes out of runs,
the tet count and the tet volume against the surface's, and the first error seen. fTetWild ran in
the importing process before issue 45, where a crash on a flat bar took the whole import down.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh


def _l_shape() -> trimesh.Trimesh:
    """An L-shaped block, 10 x 8 cm, 3 cm thick (a bracket, a corner sponge): the L outline extruded."""
    outline = np.array([[0, 0], [0.10, 0], [0.10, 0.03], [0.03, 0.03], [0.03, 0.08], [0, 0.08]])
    n, h = len(outline), 0.03
    vertices = np.vstack([np.c_[outline, np.zeros(n)], np.c_[outline, np.full(n, h)]])
    cap = [(0, 1, 2), (0, 2, 3), (0, 3, 4), (0, 4, 5)]  # a fan from the corner sees the whole L
    faces = [(a, c, b) for a, b, c in cap] + [(a + n, b + n, c + n) for a, b, c in cap]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, j + n), (i, j + n, i + n)]
    mesh = trimesh.Trimesh(vertices, np.array(faces))
    assert mesh.is_watertight and mesh.volume > 0
    return mesh


def _ring() -> trimesh.Trimesh:
    return trimesh.creation.torus(0.04, 0.012, major_sections=32, minor_sections=12)


def _cylinder(radius: float, height: float) -> Callable[[], trimesh.Trimesh]:
    return lambda: trimesh.creation.cylinder(radius=radius, height=height, sections=24)


def _box(*extents: float) -> Callable[[], trimesh.Trimesh]:
    return lambda: trimesh.creation.box(extents=list(extents))


SHAPES: dict[str, Callable[[], trimesh.Trimesh]] = {
    "bar 15 x 4.5 x 2 cm (remote control)": _box(0.15, 0.045, 0.02),
    "ruler 19 x 3 x 0.5 cm": _box(0.19, 0.03, 0.005),
    "plate 12 x 12 x 1 cm": _box(0.12, 0.12, 0.01),
    "phone-sized sponge 14 x 7 x 1.5 cm": _box(0.14, 0.07, 0.015),
    "thin plate 10 x 10 x 0.3 cm": _box(0.10, 0.10, 0.003),
    "stick 18 x 1.5 x 1.5 cm": _box(0.18, 0.015, 0.015),
    "ring (torus 4 / 1.2 cm)": _ring,
    "L-shape 10 x 8 x 3 cm": _l_shape,
    "thin cylinder r 0.6 cm, 15 cm": _cylinder(0.006, 0.15),
    "cylinder r 3 cm, 10 cm (bottle)": _cylinder(0.03, 0.10),
    "disc r 5 cm, 1 cm (coaster)": _cylinder(0.05, 0.01),
    "capsule r 2 cm, 12 cm (bread roll)": lambda: trimesh.creation.capsule(height=0.08, radius=0.02),
}


def study(runs: int, out: Path) -> list[dict[str, object]]:
    from d3grasp.authoring.importer import import_meshes

    rows = []
    for n, (name, make) in enumerate(SHAPES.items()):
        mesh = make()
        src = out / f"shape_{n:02d}.stl"
        mesh.export(src)
        ok, tets, ratio, error, seconds = 0, [], [], "", []
        for r in range(runs):
            t0 = time.perf_counter()
            try:
                (entry,) = import_meshes(
                    [src], out / f"lib_{n:02d}_{r}", deformable=True, youngs_modulus=3e4, poissons_ratio=0.3
                ).entries
            except Exception as exc:  # noqa: BLE001 -- a study counts every failure, whatever its type
                error = error or f"{type(exc).__name__}: {exc}"[:140]
            else:
                ok += 1
                tets.append(int(entry.stats["num_tets"]))
                ratio.append(float(entry.volume) / float(mesh.volume))
            seconds.append(time.perf_counter() - t0)
        rows.append(
            {
                "shape": name,
                "ok": ok,
                "tets": tets,
                "ratio": ratio,
                "error": error,
                "s": float(np.median(seconds)),
            }
        )
        print(f"{name}: {ok}/{runs}", flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--out", type=Path, default=None, help="keep the imports here (default: a temp folder)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory(prefix="d3grasp_soft_study_") as tmp:
        rows = study(args.runs, args.out or Path(tmp))
    print("\n| shape | imported | tets | tet volume / surface volume | s per import | first error |")
    print("|---|---|---|---|---|---|")
    for row in rows:
        tets, ratio = row["tets"], row["ratio"]
        t = f"{min(tets)}-{max(tets)}" if tets else ""
        v = f"{min(ratio):.3f}-{max(ratio):.3f}" if ratio else ""
        print(f"| {row['shape']} | {row['ok']}/{args.runs} | {t} | {v} | {row['s']:.1f} | {row['error']} |")
    total = sum(int(row["ok"]) for row in rows)
    print(f"\n{total} of {args.runs * len(rows)} imports succeeded")


if __name__ == "__main__":
    main()
