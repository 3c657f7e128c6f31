"""Plate test of soft objects' tet meshes: how far a load compresses each object, to compare meshes
of the same objects at different tet budgets against a fine one.

Each object rests on the table, and a rigid plate on a vertical slider (a prismatic joint: it
cannot tilt) is lowered onto it under its own weight. The weight is chosen so that a linear-elastic
block of the object's footprint and height would shorten by ``--nominal-strain``:
F = strain * E * A, with A the product of the extents' two horizontal sides, capped at
``--max-load``. The run uses the environment's SolverVBD settings (control rate, substeps, soft
iterations, contact stiffness, the closed-form tet kernel) for ``--seconds`` of simulation. The
test then reports two figures at that load:
- the compression: the nodes' height span, unloaded against loaded, over the unloaded one. Contact
  radii and gaps drop out of it.
- eps_bar: the volume-weighted mean of the nodes' largest principal Green strain, the environment's
  strain sensor (``kernels/strain.py``).

Linear tets are stiffer than the continuum (they lock in bending and near incompressibility), so a
coarser mesh can compress less under the same load. The ratio of a mesh's compression to the fine
mesh's is the error its budget adds. ``--reference-iterations`` solves the first (fine) library to
convergence, because a fixed number of Gauss-Seidel sweeps can leave a mesh unconverged:
- A structured 4 cm block under Hooke's 5% load shortens by 4.8, 4.3 and 3.7% at 20 iterations
  with 2, 3 and 4 cells a side, and by 4.8 and 4.9% at 80.
- The library's large, stiff rubber duck compresses twice as much at 20 as at 80.
(docs/design.md, Where a soft step's time goes.)

Run: ``python tools/soft_plate_test.py FINE/manifest.json [OTHER/manifest.json ...] [--ids a,b]
[--reference-iterations 80]``. It prints the objects the libraries share, row by row, with each
later library's compression and eps_bar also given as a ratio to the first's.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from a checkout without installing
    sys.path.insert(0, str(REPO))

import newton  # noqa: E402
import warp as wp  # noqa: E402

from d3grasp.authoring.manifest import AssetEntry, read_manifest, resolve_asset_path  # noqa: E402
from d3grasp.authoring.usd_soft import read_soft_usd  # noqa: E402
from d3grasp.cli.args import run_command  # noqa: E402
from d3grasp.console import quiet_warp  # noqa: E402
from d3grasp.envs.config import SimConfig  # noqa: E402
from d3grasp.envs.physics import capture_graph, use_soft_solve_kernels  # noqa: E402
from d3grasp.envs.scene import set_tet_damping  # noqa: E402
from kernels import strain as strain_k  # noqa: E402

GRAVITY = 9.81
PLATE_HALF_THICKNESS = 0.005  # m
PLATE_CLEARANCE = 0.002  # m between the object's top and the plate's face at the start


def plate_test(
    entry: AssetEntry,
    usd_path: Path,
    nominal_strain: float,
    seconds: float,
    sim: SimConfig,
    max_load: float = 20.0,
    iterations: int | None = None,
) -> dict[str, float]:
    """Compression and eps_bar of one object under its plate load (module docstring)."""
    ext = np.asarray(entry.extents, dtype=float)
    footprint = float(ext[0] * ext[1])
    load = min(nominal_strain * float(entry.material["youngs_modulus"]) * footprint, max_load)
    builder = newton.ModelBuilder()
    builder.default_shape_cfg.mu = sim.shape_mu
    # Newton takes no contact radius from USD and defaults to 0.1 m (d3grasp.envs.scene.build_scene).
    builder.default_particle_radius = float(entry.stats.get("particle_radius", 0.003))
    builder.add_ground_plane()
    rest = np.asarray(read_soft_usd(usd_path)["points"], dtype=float)  # the nodes, object frame
    lift = -rest[:, 2].min() + sim.soft_contact_gap * 0.5
    builder.add_usd(str(usd_path), xform=wp.transform(wp.vec3(0.0, 0.0, lift), wp.quat_identity()))
    top = rest[:, 2].max() + lift
    half = 0.6 * float(max(ext[0], ext[1])) + 0.02
    z0 = top + PLATE_CLEARANCE + PLATE_HALF_THICKNESS
    mass = load / GRAVITY
    side = mass * (2.0 * half) ** 2 / 12.0  # a thin square plate's inertia (it only slides)
    plate = builder.add_link(
        xform=wp.transform(wp.vec3(0.0, 0.0, z0), wp.quat_identity()),
        mass=mass,
        inertia=wp.mat33(side, 0.0, 0.0, 0.0, side, 0.0, 0.0, 0.0, 2.0 * side),
        lock_inertia=True,
    )
    builder.add_shape_box(
        plate,
        hx=half,
        hy=half,
        hz=PLATE_HALF_THICKNESS,
        cfg=newton.ModelBuilder.ShapeConfig(density=0.0, mu=sim.shape_mu),
    )
    joint = builder.add_joint_prismatic(
        parent=-1,
        child=plate,
        axis=newton.Axis.Z,
        parent_xform=wp.transform(wp.vec3(0.0, 0.0, z0), wp.quat_identity()),
    )
    builder.add_articulation([joint])
    builder.color()
    model = builder.finalize()
    model.soft_contact_ke = sim.soft_contact_ke
    model.soft_contact_kd = sim.soft_contact_kd
    model.soft_contact_mu = sim.soft_contact_mu
    set_tet_damping(model, [(0, model.tet_count, float(entry.material.get("damping", 0.0)))])
    solver = newton.solvers.SolverVBD(
        model,
        iterations=iterations or sim.soft_iterations,
        friction_epsilon=sim.friction_epsilon,
        rigid_contact_history=True,
        particle_enable_self_contact=False,
    )
    pipeline = newton.CollisionPipeline(
        model, contact_matching="sticky", soft_contact_gap=sim.soft_contact_gap
    )
    use_soft_solve_kernels(solver, pipeline, sim)
    contacts = pipeline.contacts()
    states = [model.state(), model.state()]
    control = model.control()
    dt = 1.0 / sim.control_hz / sim.substeps

    def control_step() -> None:  # an even number of substeps leaves the result in states[0]
        for k in range(sim.substeps):
            s_in, s_out = states[k % 2], states[(k + 1) % 2]
            s_in.clear_forces()
            pipeline.collide(s_in, contacts)
            solver.step(s_in, s_out, control, contacts, dt)

    if sim.substeps % 2:
        raise ValueError("sim.substeps must be even: the captured step alternates two states")
    control_step()  # sizes the solver's lazy buffers before the capture
    graph = capture_graph(control_step, model.device)
    for _ in range(max(1, round(seconds * sim.control_hz)) - 1):
        wp.capture_launch(graph)
    q = states[0].particle_q.numpy()
    layout = strain_k.StrainLayout.from_model(model)
    buf = strain_k.StrainBuffers.allocate(layout)
    strain_k.compute_strain(layout, states[0].particle_q, buf)
    # The object's height between its lowest and highest node, before and under the load: the
    # contact radius and gap of the plate and table drop out.
    rest_height = float(np.ptp(rest[:, 2]))
    return {
        "load_n": load,
        "compression": (rest_height - float(np.ptp(q[:, 2]))) / rest_height,
        "eps_bar": float(buf.object_eps.numpy()[0]),
        "finite": bool(np.isfinite(q).all()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("manifests", type=Path, nargs="+", help="library manifests, the reference first")
    ap.add_argument("--ids", default=None, help="comma-separated asset ids (default: every soft object)")
    ap.add_argument("--nominal-strain", type=float, default=0.2)
    ap.add_argument("--seconds", type=float, default=1.0, help="simulated time under the load")
    ap.add_argument("--max-load", type=float, default=20.0, help="N, the most a plate weighs")
    ap.add_argument(
        "--iterations", type=int, default=None, help="SolverVBD iterations (default: the environment's)"
    )
    ap.add_argument(
        "--reference-iterations",
        type=int,
        default=None,
        help="iterations of the first library's runs (e.g. 80: the fine mesh solved to convergence)",
    )
    args = ap.parse_args(argv)
    quiet_warp()
    return run_command("soft_plate_test", lambda: _compare(args))


def _compare(args: argparse.Namespace) -> int:
    libs = [{e.id: e for e in read_manifest(m) if e.kind == "deformable"} for m in args.manifests]
    ids = [i for i in libs[0] if all(i in lib for lib in libs)]
    if args.ids:
        wanted = args.ids.split(",")
        ids = [i for i in ids if i in wanted]
    if not ids:
        raise ValueError("no soft object is in every library given (and in --ids)")
    sim = SimConfig()
    head = f"{'object':18s} {'load N':>7s}" + "".join(
        f" {'tets ' + str(k):>8s} {'compr ' + str(k):>8s} {'eps ' + str(k):>7s}" for k in range(len(libs))
    )
    head += "".join(f"  compr {k}/0  eps {k}/0" for k in range(1, len(libs)))
    print(head, flush=True)
    for i in ids:
        t0 = time.perf_counter()
        rows = [
            plate_test(
                lib[i],
                resolve_asset_path(m, lib[i]),
                args.nominal_strain,
                args.seconds,
                sim,
                args.max_load,
                (args.reference_iterations or args.iterations) if k == 0 else args.iterations,
            )
            for k, (lib, m) in enumerate(zip(libs, args.manifests, strict=True))
        ]
        line = f"{i:18s} {rows[0]['load_n']:7.2f}"
        for lib, r in zip(libs, rows, strict=True):
            line += f" {lib[i].stats['num_tets']:8d} {r['compression']:8.3f} {r['eps_bar']:7.3f}"
        ref = rows[0]
        for r in rows[1:]:
            line += f"  {r['compression'] / ref['compression']:9.2f} {r['eps_bar'] / ref['eps_bar']:8.2f}"
        if not all(r["finite"] for r in rows):
            line += "  NON-FINITE"
        print(f"{line}  ({time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
