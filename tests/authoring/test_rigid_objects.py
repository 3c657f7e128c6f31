"""The shipped rigid object library: coverage, mass properties, Newton loading, physics, rebuild.

Independent references: analytic volumes (box, faceted cylinder), a NumPy volume/inertia
integration of the USD render mesh (not trimesh, which the authoring code uses), and Newton's own
USD importer for read-back.
"""

from __future__ import annotations

import importlib.util
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from d3grasp.authoring.manifest import SIZE_BINS, read_manifest, resolve_asset_path, size_bin_of
from d3grasp.paths import default_manifest

REPO = Path(__file__).resolve().parents[2]
MANIFEST = default_manifest()
RIGID = [e for e in read_manifest(MANIFEST) if e.kind == "rigid"] if MANIFEST.exists() else []
BY_ID = {e.id: e for e in RIGID}
CONVEX_FAMILIES = {"box", "cylinder", "ellipsoid", "capsule", "frustum", "superquadric"}
HOLLOW_FAMILIES = {"torus", "mug", "bowl"}

pytestmark = pytest.mark.skipif(not RIGID, reason="rigid library not built")


def _usd(entry):
    """Render mesh (points, triangles), hull point sets and MassAPI values read with pxr."""
    from pxr import Usd, UsdGeom, UsdPhysics, UsdShade

    stage = Usd.Stage.Open(str(resolve_asset_path(MANIFEST, entry)))
    root = stage.GetDefaultPrim()
    vis = UsdGeom.Mesh(stage.GetPrimAtPath(f"{root.GetPath()}/visual"))
    pts = np.array(vis.GetPointsAttr().Get(), dtype=np.float64)
    tris = np.array(vis.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
    hulls, frictions = [], []
    for p in Usd.PrimRange(root):
        if p.HasAPI(UsdPhysics.CollisionAPI):
            hulls.append(np.array(UsdGeom.Mesh(p).GetPointsAttr().Get(), dtype=np.float64))
            assert UsdPhysics.MeshCollisionAPI(p).GetApproximationAttr().Get() == "convexHull"
            mat, _ = UsdShade.MaterialBindingAPI(p).ComputeBoundMaterial("physics")
            frictions.append(UsdPhysics.MaterialAPI(mat.GetPrim()).GetDynamicFrictionAttr().Get())
    mass = UsdPhysics.MassAPI(root).GetMassAttr().Get()
    return pts, tris, hulls, frictions, mass, root.HasAPI(UsdPhysics.RigidBodyAPI)


def _volume_and_inertia(pts: np.ndarray, tris: np.ndarray, density: float):
    """Volume, centre of mass and inertia about it of a closed triangle mesh (NumPy only).

    Each triangle with the origin spans a signed tet; for a tet with edge matrix A (columns
    a, b, c), the integral of x x^T is det(A) * A K A^T with K = [[2,1,1],[1,2,1],[1,1,2]] / 120.
    """
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    det = np.einsum("ij,ij->i", a, np.cross(b, c))
    vol = det.sum() / 6.0
    com = (det[:, None] * (a + b + c)).sum(axis=0) / 24.0 / vol
    A = np.stack([a, b, c], axis=2)  # (T, 3, 3), columns a, b, c
    K = (np.ones((3, 3)) + np.eye(3)) / 120.0
    cov = np.einsum("t,tij,jk,tlk->il", det, A, K, A) * density
    mass = density * vol
    inertia_o = np.trace(cov) * np.eye(3) - cov
    inertia = inertia_o - mass * (com @ com * np.eye(3) - np.outer(com, com))
    return vol, com, inertia


def test_library_coverage() -> None:
    assert len(RIGID) >= 100
    bins = Counter(e.size_bin for e in RIGID)
    assert set(bins) == set(SIZE_BINS) and min(bins.values()) >= 25, bins
    fams = Counter(e.family for e in RIGID)
    assert len(fams) >= 10
    for fam, n in fams.items():
        held = sum(e.split == "test" for e in RIGID if e.family == fam)
        assert held >= 0.15 * n and held < n, (fam, held, n)
    assert len(BY_ID) == len(RIGID)
    for e in RIGID:
        assert resolve_asset_path(MANIFEST, e).is_file(), e.path
        assert size_bin_of(max(e.extents)) == e.size_bin
        assert 0.5 <= e.material["friction"] <= 1.0
        assert 0.0 < e.mass <= 0.5  # liftable by the ~1 kg hand (documented cap)
        assert 1 <= e.stats["num_hulls"] <= 16 and max(e.stats["num_hull_vertices"]) <= 64
        assert (e.stats["num_hulls"] == 1) == (e.family in CONVEX_FAMILIES) or e.family == "blob"
    size = sum(resolve_asset_path(MANIFEST, e).stat().st_size for e in RIGID)
    assert size < 8e6, f"rigid library is {size / 1e6:.1f} MB"


@pytest.mark.parametrize("asset_id", sorted(BY_ID))
def test_mass_is_density_times_volume(asset_id: str) -> None:
    e = BY_ID[asset_id]
    pts, tris, hulls, frictions, usd_mass, is_body = _usd(e)
    assert is_body
    rho = e.material["density"]
    vol, com, inertia = _volume_and_inertia(pts, tris, rho)
    # USD coordinates are rounded to 10 um: relative volume error stays well under 1%.
    assert vol == pytest.approx(e.volume, rel=5e-3)
    assert e.mass == pytest.approx(rho * e.volume, rel=2e-8)  # both written at 9 digits
    assert usd_mass == pytest.approx(e.mass, rel=1e-6)
    assert np.ptp(pts, axis=0) == pytest.approx(e.extents, abs=2e-5)
    assert len(hulls) == e.stats["num_hulls"]
    assert frictions == pytest.approx([e.material["friction"]] * len(hulls), rel=1e-6)
    if e.family == "box":
        assert e.volume == pytest.approx(float(np.prod(e.extents)), rel=1e-3)
    if e.family == "cylinder":  # 24-sided prism along z, a vertex on +x
        r, h = e.extents[0] / 2, e.extents[2]
        assert e.volume == pytest.approx(12 * r * r * np.sin(2 * np.pi / 24) * h, rel=2e-3)
    if e.family in HOLLOW_FAMILIES:  # shells: much less solid than their hull
        hull_vol = sum(_hull_volume(h) for h in hulls)
        assert e.volume < 0.8 * float(np.prod(e.extents)) and hull_vol > 0.9 * e.volume


def _hull_volume(points: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points).volume)


def test_every_entry_loads_in_newton_with_its_mass_and_inertia() -> None:
    from d3grasp.authoring.validate import _load, validate_library

    report = validate_library(MANIFEST, hand=False)
    rigid = [a for a in report.assets if a.kind == "rigid"]
    assert len(rigid) == len(RIGID)
    assert all(a.ok for a in rigid), [f for a in rigid for f in a.errors][:5]
    # Inertia and centre of mass as Newton reads them vs the NumPy integration of the surface.
    for aid in ("lshape_03", "mug_02", "bottle_05", "blob_07"):
        e = BY_ID[aid]
        pts, tris, *_ = _usd(e)
        _, com, inertia = _volume_and_inertia(pts, tris, e.material["density"])
        b = _load(resolve_asset_path(MANIFEST, e))
        got = np.array(b.body_inertia[0], dtype=np.float64).reshape(3, 3)
        assert np.abs(got - inertia).max() <= 5e-3 * np.abs(inertia).max(), aid
        assert np.array(b.body_com[0], dtype=np.float64) == pytest.approx(com, abs=5e-5)


@pytest.mark.parametrize("asset_id", ["box_01", "mug_02"])
def test_rigid_object_rests_on_plane(asset_id: str) -> None:
    """Dropped 1 cm onto the ground with the project's VBD settings: settles, no sinking."""
    import newton
    import warp as wp

    e = BY_ID[asset_id]
    half_z = e.extents[2] / 2  # body origin = bounding-box centre; rest frame z is up
    b = newton.ModelBuilder()
    b.add_ground_plane()
    b.add_usd(
        str(resolve_asset_path(MANIFEST, e)),
        xform=wp.transform(wp.vec3(0.0, 0.0, half_z + 0.01), wp.quat_identity()),
    )
    b.color()
    model = b.finalize()
    pipe = newton.CollisionPipeline(model, contact_matching="sticky")
    contacts = pipe.contacts()
    solver = newton.solvers.SolverVBD(model, iterations=5, rigid_contact_history=True)
    s0, s1, ctrl = model.state(), model.state(), model.control()
    fps, substeps = 60, 10
    dt = 1.0 / fps / substeps
    for _ in range(fps):  # 1 s
        for _ in range(substeps):
            s0.clear_forces()
            pipe.collide(s0, contacts)
            solver.step(s0, s1, ctrl, contacts, dt)
            s0, s1 = s1, s0
    q, qd = s0.body_q.numpy()[0], s0.body_qd.numpy()[0]
    assert np.all(np.isfinite(q)) and np.all(np.isfinite(qd))
    assert np.linalg.norm(qd[:3]) < 0.01  # at rest (< 1 cm/s)
    assert q[2] == pytest.approx(half_z, abs=0.003)  # neither sunk nor floating by > 3 mm
    assert np.linalg.norm(q[:2]) < 0.005  # no sliding away on a flat drop
    # still upright: body z axis stays vertical
    quat = q[3:7]  # x, y, z, w
    x, y = quat[0], quat[1]
    assert 1.0 - 2.0 * (x * x + y * y) > 0.999


def _load_builder_module():
    spec = importlib.util.spec_from_file_location(
        "build_rigid_objects", REPO / "tools" / "build_rigid_objects.py"
    )
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up by name
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("asset_id", ["box_00", "torus_02"])
def test_rebuild_reproduces_committed_files(tmp_path: Path, asset_id: str, assert_usda_matches) -> None:
    """Authoring is deterministic: rebuilding an instance gives the committed file (up to round-off)."""
    if not (REPO / "tools" / "build_rigid_objects.py").is_file():
        pytest.skip("not a source checkout")
    mod = _load_builder_module()
    spec = next(s for s in mod.plan() if s.asset_id == asset_id)
    entry = mod.build_one(spec, tmp_path)
    committed = resolve_asset_path(MANIFEST, BY_ID[asset_id])
    assert_usda_matches((tmp_path / entry.path).read_text(), committed.read_text(), asset_id)
    assert entry.mass == pytest.approx(BY_ID[asset_id].mass, rel=1e-8)  # the manifest holds 9 digits
