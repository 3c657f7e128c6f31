"""Localisation error of the camera perception over the shipped objects, with and without sensor noise,
and the ray-tracing time per image.

    python -m d3grasp.vision.measure [--kinds rigid deformable] [--split all] [--seeds 2] [--batch 40]

Each object is placed as in evaluation (random position within 1 cm, random yaw) in ``--seeds``
environments; the table lists mean and 95th percentile of the centre error (3-D and horizontal)
and of the largest extent error, per object kind.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence

import numpy as np


def measure(ids: list[str], noise: bool, seeds: int, batch: int, log=print) -> tuple[list[dict], float]:
    """Localisation records of every object and seed; and the mean render time (s) of one depth image."""
    import d3grasp

    records: list[dict] = []
    render_s, renders = 0.0, 0
    for seed in range(seeds):
        for start in range(0, len(ids), batch):
            chunk = tuple(ids[start : start + batch])
            env = d3grasp.make_env(
                num_envs=len(chunk),
                seed=seed,
                eval_mode=True,
                perception="camera",
                camera={"noise": noise},
                objects={"ids": chunk},
            )
            for w, rec in enumerate(env.record.localisation):
                records.append({"object": chunk[w], "kind": env.world_entries[w].kind, "seed": seed, **rec})
            # Render time of one world's 320x240 depth image (the BVH refit included).
            perception = env.planning.estimator.perception
            t0 = time.perf_counter()
            for w in range(len(chunk)):
                perception.camera.render(env.state_0, [perception.pose], [w])
            render_s += time.perf_counter() - t0
            renders += len(chunk)
            env.close()
            log(f"  noise={noise} seed={seed}: {start + len(chunk)}/{len(ids)} objects")
    return records, render_s / max(renders, 1)


def summary_line(label: str, rows: list[dict]) -> str:
    def stats(key: str) -> str:
        v = 1000.0 * np.asarray([r[key] for r in rows])
        return f"{v.mean():5.1f} / {np.percentile(v, 95.0):5.1f}"

    failed = sum(not r["loc_ok"] for r in rows)
    return (
        f"| {label:<22} | {len(rows):>4} | {stats('loc_error')} | {stats('loc_error_xy')} | "
        f"{stats('loc_extent_error')} | {failed} |"
    )


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m d3grasp.vision.measure", description=__doc__.split("\n")[0])
    p.add_argument("--kinds", nargs="+", default=["rigid", "deformable"])
    p.add_argument("--split", default="all", choices=("train", "test", "all"))
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--batch", type=int, default=40, help="worlds per environment")
    args = p.parse_args(argv)

    from d3grasp.authoring.manifest import read_manifest
    from d3grasp.console import quiet_warp
    from d3grasp.paths import default_manifest

    quiet_warp()
    entries = [
        e
        for e in read_manifest(default_manifest())
        if e.kind in args.kinds and (args.split == "all" or e.split == args.split)
    ]
    ids = [e.id for e in entries]
    lines = [
        "| perception             | eps. | centre mean / p95 (mm) | xy mean / p95 (mm) "
        "| extent mean / p95 (mm) | not found |",
        "|---|---|---|---|---|---|",
    ]
    times = []
    for noise in (False, True):
        rows, per_image = measure(ids, noise, args.seeds, args.batch)
        times.append(per_image)
        tag = "camera, noisy" if noise else "camera, no noise"
        lines.append(summary_line(f"{tag}", rows))
        for kind in args.kinds:
            sub = [r for r in rows if r["kind"] == kind]
            if sub:
                lines.append(summary_line(f"  {kind}", sub))
        worst = sorted(rows, key=lambda r: -r["loc_error"])[:3]
        lines.append(
            "|   worst: "
            + ", ".join(f"{r['object']} {1000 * r['loc_error']:.1f}" for r in worst)
            + " | | | | | |"
        )
    print("\n".join(lines))
    print(f"depth render, one world at 320x240 on CPU: {1000 * float(np.mean(times)):.1f} ms per image")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
