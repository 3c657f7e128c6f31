"""The FEM soft-object library and its authoring functions (tet meshing, TetMesh USD writer).

References are independent of the code under test: tet volumes and orientation by NumPy
determinants, boundary faces by usd-core's ``UsdGeom.TetMesh.ComputeSurfaceFaces``, Lamé
parameters from the manifest's E and nu by the textbook formulas, masses from density x the
NumPy volume, the sphere volume analytically.
"""

from __future__ import annotations

import importlib.util
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from d3grasp.authoring.manifest import SIZE_BINS, read_manifest, resolve_asset_path, size_bin_of
from d3grasp.paths import default_manifest

REPO = Path(__file__).resolve().parents[2]
CLASSES = ("sponge", "bread", "plush", "rubber")


def _soft_entries():
    return [e for e in read_manifest(default_manifest()) if e.kind == "deformable"]


def _det_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    a, b, c, d = (points[tets[:, i]] for i in range(4))
    return np.linalg.det(np.stack([b - a, c - a, d - a], axis=-1)) / 6.0


def _read_usd(path: Path) -> dict:
    """Raw read with usd-core only (not through d3grasp's reader)."""
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(path))
    root = stage.GetDefaultPrim()
    sim = UsdGeom.TetMesh(stage.GetPrimAtPath(root.GetPath().AppendChild("sim")))
    mat, _ = UsdShade.MaterialBindingAPI(sim.GetPrim()).ComputeBoundMaterial("physics")
    return {
        "stage": stage,  # keeps the prims below alive
        "root": root,
        "sim": sim,
        "mat": mat.GetPrim(),
        "points": np.asarray(sim.GetPointsAttr().Get(), dtype=np.float64),
        "tets": np.asarray(sim.GetTetVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 4),
        "surface": np.asarray(sim.GetSurfaceFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3),
    }


def _canon_tris(tris: np.ndarray) -> set[tuple[int, int, int]]:
    """Triangles up to rotation (winding kept): rotate the smallest index first."""
    out = set()
    for t in np.asarray(tris).tolist():
        k = t.index(min(t))
        out.add(tuple(t[k:] + t[:k]))
    return out


# ------------------------------------------------------------------------------ the library


def test_library_covers_classes_bins_stiffness_and_splits():
    entries = _soft_entries()
    assert len(entries) >= 20
    for cls in CLASSES:
        es = [e for e in entries if e.family == cls]
        assert {e.size_bin for e in es} == set(SIZE_BINS), cls
        assert sum(e.split == "test" for e in es) / len(es) >= 0.15, cls
        assert all(e.material["class"] == cls for e in es)
    stiff = [e.material["youngs_modulus"] for e in entries]
    assert max(stiff) / min(stiff) >= 10.0
    for e in entries:
        assert 200 <= e.stats["num_tets"] <= 2000, e.id
        assert size_bin_of(max(e.extents)) == e.size_bin, e.id
        assert e.mass <= 0.5 + 1e-9, e.id
        assert e.material["damping"] > 0 and 0 < e.material["poissons_ratio"] < 0.5


def test_usd_files_geometry_schemas_and_mass():
    """Every shipped file: positive tets, outward closed surface, schemas, volume and mass."""
    from pxr import Usd, UsdGeom

    for e in _soft_entries():
        path = resolve_asset_path(default_manifest(), e)
        r = _read_usd(path)
        pts, tets = r["points"], r["tets"]
        vols = _det_volumes(pts, tets)
        assert vols.min() > 0.0, f"{e.id}: inverted tet"
        assert len(tets) == e.stats["num_tets"] and len(pts) == e.stats["num_nodes"]
        assert len(np.unique(tets)) == len(pts), f"{e.id}: unreferenced nodes"
        np.testing.assert_allclose(pts.max(0) - pts.min(0), e.extents, rtol=1e-5)
        np.testing.assert_allclose(vols.sum(), e.volume, rtol=1e-5)
        np.testing.assert_allclose(e.mass, e.material["density"] * vols.sum(), rtol=1e-5)
        # Surface: as usd-core computes it, and closed and outward by the divergence theorem.
        ref = UsdGeom.TetMesh.ComputeSurfaceFaces(r["sim"], Usd.TimeCode.Default())
        assert _canon_tris(r["surface"]) == _canon_tris(np.asarray(ref)), e.id
        tri = pts[r["surface"]]
        div_volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6.0
        np.testing.assert_allclose(div_volume, vols.sum(), rtol=1e-6)
        # Schemas and material, exactly the tokens Newton 1.8 checks.
        api = list(r["sim"].GetPrim().GetMetadata("apiSchemas").ApplyOperations([]))
        assert "PhysicsVolumeDeformableSimAPI" in api and "PhysicsCollisionAPI" in api
        mapi = list(r["mat"].GetMetadata("apiSchemas").ApplyOperations([]))
        assert "PhysicsVolumeDeformableMaterialAPI" in mapi
        mat = r["mat"]
        assert mat.GetAttribute("physics:youngsModulus").Get() == pytest.approx(
            e.material["youngs_modulus"], rel=1e-6
        )
        assert mat.GetAttribute("physics:poissonsRatio").Get() == pytest.approx(
            e.material["poissons_ratio"], rel=1e-6
        )
        assert mat.GetAttribute("physics:density").Get() == pytest.approx(e.material["density"], rel=1e-6)
        assert mat.GetAttribute("d3grasp:damping").Get() == pytest.approx(e.material["damping"], rel=1e-6)


def test_newton_reads_every_soft_object():
    """``add_usd`` on each file: counts, per-tet Lamé parameters and lumped masses."""
    import newton

    for e in _soft_entries():
        b = newton.ModelBuilder()
        b.default_particle_radius = 0.003
        b.add_usd(str(resolve_asset_path(default_manifest(), e)))
        assert b.particle_count == e.stats["num_nodes"], e.id
        assert b.tet_count == e.stats["num_tets"], e.id
        young, nu = e.material["youngs_modulus"], e.material["poissons_ratio"]
        k_mu = young / (2.0 * (1.0 + nu))
        k_lambda = young * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
        mats = np.asarray(b.tet_materials, dtype=np.float64)
        np.testing.assert_allclose(mats[:, 0], k_mu, rtol=1e-5, err_msg=e.id)
        np.testing.assert_allclose(mats[:, 1], k_lambda, rtol=1e-5, err_msg=e.id)
        pts = np.asarray(b.particle_q, dtype=np.float64)
        tets = np.asarray(b.tet_indices, dtype=np.int64)
        volume = _det_volumes(pts, tets).sum()
        np.testing.assert_allclose(
            sum(b.particle_mass), e.material["density"] * volume, rtol=1e-4, err_msg=e.id
        )
        np.testing.assert_allclose(volume, e.volume, rtol=1e-4, err_msg=e.id)
        assert np.allclose(b.particle_radius, 0.003)


def test_finalized_model_tet_materials():
    """One object through ``finalize``: ``model.tet_materials`` and ``model.particle_mass``."""
    import newton

    e = next(x for x in _soft_entries() if x.id == "sponge_kitchen_m")
    b = newton.ModelBuilder()
    b.add_usd(str(resolve_asset_path(default_manifest(), e)))
    m = b.finalize(device="cpu")
    young, nu = e.material["youngs_modulus"], e.material["poissons_ratio"]
    tm = m.tet_materials.numpy()
    np.testing.assert_allclose(tm[:, 0], young / (2 * (1 + nu)), rtol=1e-5)
    np.testing.assert_allclose(tm[:, 1], young * nu / ((1 + nu) * (1 - 2 * nu)), rtol=1e-5)
    np.testing.assert_allclose(m.particle_mass.numpy().sum(), e.mass, rtol=1e-4)


def test_rebuild_reuses_committed_tets(tmp_path, monkeypatch, assert_usda_matches):
    """Without --regenerate-tets the build is deterministic: it rewrites the committed files (up to
    round-off in the last digits, which the stated precision of authored numbers removes)."""
    spec = importlib.util.spec_from_file_location(
        "build_soft_objects", REPO / "tools" / "build_soft_objects.py"
    )
    mod = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "build_soft_objects", mod)  # dataclasses look their module up
    spec.loader.exec_module(mod)
    src = Path(default_manifest()).parent / "objects" / "soft"
    shutil.copytree(src, tmp_path / "objects" / "soft")
    entries = mod.build(tmp_path, progress=False)
    assert len(entries) == len(list(src.glob("*.usda")))
    for f in src.glob("*.usda"):
        assert_usda_matches((tmp_path / "objects" / "soft" / f.name).read_text(), f.read_text(), f.name)
    rebuilt = {e.id: e for e in read_manifest(tmp_path / "manifest.json")}
    for e in _soft_entries():
        assert rebuilt[e.id].material == e.material and rebuilt[e.id].stats == e.stats


# ------------------------------------------------------------------------------ authoring functions


def test_tetrahedralize_sphere_volume_orientation_and_count(tmp_path, monkeypatch):
    from d3grasp.authoring.tetmesh import surface_faces, tetrahedralize

    r = 0.03
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=r)
    monkeypatch.chdir(tmp_path)
    pts, tets = tetrahedralize(sphere, 400)
    # fTetWild's scratch surface stays out of the caller's folder, which stays current.
    assert list(tmp_path.iterdir()) == [] and Path.cwd() == tmp_path
    assert pts.dtype == np.float64 and tets.dtype == np.int32
    assert 200 <= len(tets) <= 2000
    vols = _det_volumes(pts, tets.astype(np.int64))
    assert vols.min() > 0
    # Within a few % of both the input surface and the analytic ball.
    assert vols.sum() == pytest.approx(sphere.volume, rel=0.05)
    assert vols.sum() == pytest.approx(4.0 / 3.0 * math.pi * r**3, rel=0.06)
    tris = surface_faces(tets)
    tri = pts[tris]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    outward = np.einsum("ij,ij->i", normals, tri.mean(axis=1))  # centre at the origin: all > 0
    assert (outward > 0).all()


def test_tetrahedralize_refuses_open_mesh():
    from d3grasp.authoring.tetmesh import tetrahedralize

    box = trimesh.creation.box([0.05, 0.05, 0.05])
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    with pytest.raises(ValueError, match="watertight"):
        tetrahedralize(open_box)
    with pytest.raises(ValueError, match="target_tets"):
        tetrahedralize(box, target_tets=5000)


def test_a_mesher_crash_is_a_failed_attempt(monkeypatch):
    from d3grasp.authoring import tetmesh

    # A run that crashes fTetWild (pytetwild 0.4.2: a flat bar at an edge of 0.03 diagonals and an
    # envelope of 0.01, SIGSEGV) ends in MesherCrash, not in the death of this process.
    bar = trimesh.creation.box([0.12, 0.02, 0.004])
    try:
        tetmesh._run_ftetwild(bar.vertices, bar.faces, 0.03, 0.01)
    except tetmesh.MesherCrash as exc:
        assert str(exc).startswith("fTetWild crashed (")
    # And the meshing goes on after one: the first attempt crashes, the next ones mesh.
    real, calls = tetmesh._run_ftetwild, []

    def crashing_once(*args):
        calls.append(args)
        if len(calls) == 1:
            raise tetmesh.MesherCrash("fTetWild crashed (signal SIGSEGV)")
        return real(*args)

    monkeypatch.setattr(tetmesh, "_run_ftetwild", crashing_once)
    logs = []
    _, tets = tetmesh.tetrahedralize(trimesh.creation.box([0.05, 0.05, 0.05]), 400, log=logs.append)
    assert "fTetWild crashed (signal SIGSEGV) -> 0 tets" in logs[0]
    assert len(calls) >= 2 and 200 <= len(tets) <= 2000


def test_surface_faces_two_tets_and_orientation_fix():
    from d3grasp.authoring.tetmesh import orient_positive, surface_faces

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])  # the second one is inverted
    fixed = orient_positive(pts, tets)
    assert (_det_volumes(pts, fixed) > 0).all()
    tris = surface_faces(fixed)
    assert len(tris) == 6  # two tets glued on one face
    assert (0, 1, 2) not in _canon_tris(tris) and (0, 2, 1) not in _canon_tris(tris)
    centre = pts.mean(axis=0)
    tri = pts[tris]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert (np.einsum("ij,ij->i", n, tri.mean(axis=1) - centre) > 0).all()


def test_rest_volume_and_mass_unit_tet():
    from d3grasp.authoring.tetmesh import rest_volume_and_mass

    pts = np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]])
    vol, mass = rest_volume_and_mass(pts, np.array([[0, 1, 2, 3]]), 500.0)
    assert vol == pytest.approx(0.1**3 / 6)
    assert mass == pytest.approx(500.0 * 0.1**3 / 6)


def test_write_soft_usd_rejects_bad_input(tmp_path):
    from d3grasp.authoring.usd_soft import write_soft_usd

    pts = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05]], dtype=np.float64)
    good = {"youngs_modulus": 1e5, "poissons_ratio": 0.3, "density": 100.0}
    with pytest.raises(ValueError, match="poissons_ratio"):
        write_soft_usd(tmp_path / "a.usda", pts, [[0, 1, 2, 3]], {**good, "poissons_ratio": 0.5}, name="a")
    with pytest.raises(ValueError, match="youngs_modulus"):
        write_soft_usd(tmp_path / "a.usda", pts, [[0, 1, 2, 3]], {**good, "youngs_modulus": -1.0}, name="a")
    with pytest.raises(ValueError, match="inverted"):
        write_soft_usd(tmp_path / "a.usda", pts, [[0, 2, 1, 3]], good, name="a")
    with pytest.raises(ValueError, match="prim name"):
        write_soft_usd(tmp_path / "a.usda", pts, [[0, 1, 2, 3]], good, name="1 bad")
    assert not (tmp_path / "a.usda").exists()


# ------------------------------------------------------------------------------ simulation


@pytest.mark.slow
def test_soft_objects_rest_stably_on_ground():
    """Softest, stiffest, a medium sponge and a ball dropped 1 cm onto a plane with SolverVBD at
    the project's settings (60 Hz x 10 substeps, 5 iterations, soft contact ke 1e4 / kd 1e-2 /
    mu 1, gap 5 mm, no self-contact, particle radius 3 mm, damping from the manifest)."""
    import newton
    import warp as wp

    from d3grasp.envs.scene import set_tet_damping

    ids = ["sponge_kitchen_m", "rubber_ball_m", "rubber_duck_l", "plush_blob_s"]
    byid = {e.id: e for e in _soft_entries()}
    radius = 0.003
    b = newton.ModelBuilder()
    b.default_shape_cfg.ke, b.default_shape_cfg.kd, b.default_shape_cfg.mu = 1e4, 1e-2, 1.0
    b.add_ground_plane()
    b.default_particle_radius = radius
    ranges = []
    for i, aid in enumerate(ids):
        e = byid[aid]
        p0, t0 = b.particle_count, b.tet_count
        z0 = 0.5 * e.extents[2] + radius + 0.01
        b.add_usd(
            str(resolve_asset_path(default_manifest(), e)),
            xform=wp.transform((0.3 * i, 0.0, z0), wp.quat_identity()),
        )
        ranges.append((p0, b.particle_count, t0, b.tet_count))
    b.color()
    model = b.finalize(device="cpu")
    model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = 1e4, 1e-2, 1.0
    damping = [byid[aid].material["damping"] for aid in ids]
    set_tet_damping(model, [(t0, t1, d) for d, (_, _, t0, t1) in zip(damping, ranges, strict=True)])
    solver = newton.solvers.SolverVBD(model, iterations=5, particle_enable_self_contact=False)
    pipe = newton.CollisionPipeline(model, soft_contact_gap=0.005)
    contacts = pipe.contacts()
    s0, s1, ctrl = model.state(), model.state(), model.control()

    def frame():
        nonlocal s0, s1
        for _ in range(10):
            s0.clear_forces()
            pipe.collide(s0, contacts)
            solver.step(s0, s1, ctrl, contacts, 1.0 / 600.0)
            s0, s1 = s1, s0

    with wp.ScopedCapture(device="cpu") as cap:
        frame()  # 10 substeps, an even count: s0 is again the current state after a replay
    mass = model.particle_mass.numpy()
    coms = []
    # 5 s: a faceted ball dropped 1 cm rolls until it settles on a facet (rubber_ball_m, 112 nodes:
    # 55, 30, 9, 3 and 1.4 mm in the half-seconds after landing, under 0.3 mm from 3.5 s on).
    for f in range(1, 300):
        wp.capture_launch(cap.graph)
        if f in (270, 299):
            x = s0.particle_q.numpy()
            coms.append([(x[a:b_] * mass[a:b_, None]).sum(0) / mass[a:b_].sum() for a, b_, _, _ in ranges])
    x, v = s0.particle_q.numpy(), s0.particle_qd.numpy()
    assert np.isfinite(x).all() and np.isfinite(v).all()
    for k, (aid, (a, b_, _, _)) in enumerate(zip(ids, ranges, strict=True)):
        e = byid[aid]
        xs, ms = x[a:b_], mass[a:b_]
        height = xs[:, 2].max() - xs[:, 2].min()
        assert xs[:, 2].min() > -radius, f"{aid}: sank into the ground ({xs[:, 2].min():.4f} m)"
        assert height > 0.75 * e.extents[2], f"{aid}: collapsed to {height / e.extents[2]:.2f} of its height"
        kinetic = 0.5 * (ms * (v[a:b_] ** 2).sum(1)).sum()
        assert kinetic < 0.01 * ms.sum() * 9.81 * 1e-3, f"{aid}: still moving (KE {kinetic:.2e} J)"
        drift = np.linalg.norm(coms[1][k] - coms[0][k])
        assert drift < 2e-3, f"{aid}: centre of mass drifted {drift * 1e3:.1f} mm in the last 0.5 s"


def _bent_capsule(length: float, radius: float, bend_radius: float) -> trimesh.Trimesh:
    """A banana: a capsule along x whose centre line is bent onto a circle of ``bend_radius``."""
    m = trimesh.creation.capsule(height=length - 2 * radius, radius=radius, count=[24, 24])
    m.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=0.006)  # bendable sides
    th = v[:, 0] / bend_radius
    rad = bend_radius - v[:, 1]
    bent = np.stack([rad * np.sin(th), bend_radius - rad * np.cos(th), v[:, 2]], axis=1)
    return trimesh.Trimesh(bent, f, process=True)


# Ordinary watertight shapes of graspable size that a user imports as soft bodies: elongated and
# curved (a 17 x 5 x 3 cm banana of 12,768 faces, which the tet pipeline once refused for a 6-13%
# volume loss), long and slender, thin and flat, and one with a hole. Reference volumes are
# analytic where the shape has a closed form, else the input surface's own.
SOFT_IMPORT_FAMILY = {
    "banana": (lambda: _bent_capsule(0.176, 0.016, 0.13), None),
    "rod": (
        lambda: trimesh.creation.capsule(height=0.16, radius=0.011, count=[32, 32]),
        math.pi * 0.011**2 * 0.16 + 4 / 3 * math.pi * 0.011**3,
    ),
    "plate": (lambda: trimesh.creation.box(extents=[0.12, 0.08, 0.008]), 0.12 * 0.08 * 0.008),
    "ring": (
        lambda: trimesh.creation.torus(0.045, 0.01, major_sections=64, minor_sections=24),
        2 * math.pi**2 * 0.045 * 0.01**2,
    ),
}


def test_soft_import_of_ordinary_shapes(tmp_path):
    from d3grasp.authoring.importer import import_meshes

    paths, reference = [], {}
    for name, (make, volume) in SOFT_IMPORT_FAMILY.items():
        mesh = make()
        assert mesh.is_watertight
        reference[name] = volume if volume is not None else mesh.volume
        paths.append(tmp_path / f"{name}.stl")
        mesh.export(paths[-1])
    result = import_meshes(paths, tmp_path / "lib", deformable=True)
    assert not result.skipped
    by_id = {e.id: e for e in result.entries}
    assert set(by_id) == set(SOFT_IMPORT_FAMILY)
    for name, e in by_id.items():
        assert 200 <= e.stats["num_tets"] <= 2000, name
        # The tet mesh keeps the shape's volume (faceting alone costs the torus ~1%).
        assert e.volume == pytest.approx(reference[name], rel=0.06), name
    with pytest.raises(ValueError, match=r"--target-tets must be in \[200, 2000\]"):
        import_meshes(paths[:1], tmp_path / "lib", deformable=True, target_tets=5000)
