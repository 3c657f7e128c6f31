"""USD writer for rigid objects.

Layout of one object file (``.usda``, default prim = the object)::

    /<id>                     Xform, RigidBodyAPI + MassAPI (mass, centerOfMass,
                              diagonalInertia, principalAxes), customData d3grasp:{...}
    /<id>/visual              Mesh, render surface only (no CollisionAPI)
    /<id>/collision/hull_000  Mesh, CollisionAPI + MeshCollisionAPI approximation "convexHull",
    ...                       bound to the physics material
    /<id>/physics_material    Material with PhysicsMaterialAPI (friction, restitution 0, density)

The body origin is the centre of the object's bounding box; the mass properties are authored
explicitly (computed from the closed surface at the chosen density) so the simulator does not
integrate them from the overlapping hulls, which would count the overlap twice.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from d3grasp.authoring.convex import Hull
from d3grasp.authoring.precision import export_layer

# Coordinates are written rounded to 10 micrometres: far below any contact tolerance, and it
# keeps the text files small (float32 shortest representations).
COORD_DECIMALS = 5


@dataclass
class MassProperties:
    """Rigid-body mass properties in the body frame (SI units)."""

    mass: float
    volume: float
    center_of_mass: np.ndarray  # (3,)
    inertia: np.ndarray  # (3, 3) about the centre of mass, body axes
    principal_moments: np.ndarray  # (3,)
    principal_axes_quat: np.ndarray  # (w, x, y, z): rotates principal axes into the body frame


def mass_properties(mesh: trimesh.Trimesh, density: float) -> MassProperties:
    """Mass, centre of mass and inertia of a closed mesh of uniform ``density`` (kg/m^3)."""
    from scipy.spatial.transform import Rotation

    props = trimesh.triangles.mass_properties(mesh.triangles, density=density)
    inertia = np.asarray(props["inertia"], dtype=np.float64)
    inertia = 0.5 * (inertia + inertia.T)
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:  # a reflection is not a rotation: flip one axis
        axes[:, 2] *= -1.0
    x, y, z, w = Rotation.from_matrix(axes).as_quat()
    return MassProperties(
        mass=float(props["mass"]),
        volume=float(props["volume"]),
        center_of_mass=np.asarray(props["center_mass"], dtype=np.float64),
        inertia=inertia,
        principal_moments=np.asarray(moments, dtype=np.float64),
        principal_axes_quat=np.array([w, x, y, z]),
    )


def _vec3f_array(points: np.ndarray):
    from pxr import Vt

    pts = np.round(np.asarray(points, dtype=np.float64), COORD_DECIMALS).astype(np.float32)
    return Vt.Vec3fArray.FromNumpy(pts)


def _define_mesh(stage, path: str, vertices: np.ndarray, faces: np.ndarray):
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(_vec3f_array(vertices))
    faces = np.asarray(faces, dtype=np.int32)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr("none")
    lo, hi = np.min(vertices, axis=0), np.max(vertices, axis=0)
    mesh.CreateExtentAttr([tuple(float(v) for v in lo), tuple(float(v) for v in hi)])
    return mesh


def write_rigid_usd(
    path: str | Path,
    name: str,
    visual: trimesh.Trimesh,
    hulls: list[Hull],
    mass_props: MassProperties,
    *,
    density: float,
    friction: float,
    restitution: float = 0.0,
    color: tuple[float, float, float] = (0.7, 0.6, 0.5),
    custom_data: dict[str, Any] | None = None,
) -> Path:
    """Write one rigid object to ``path`` (``.usda`` or ``.usdc``) and return the path.

    ``name`` must be a valid USD prim name (letters, digits, underscores; not starting with a
    digit). All geometry is in the body frame, metres.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade

    if not Sdf.Path.IsValidIdentifier(name):
        raise ValueError(f"'{name}' is not a valid USD prim name")
    if not hulls:
        raise ValueError(f"{name}: a rigid object needs at least one collision hull")
    path = Path(path)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)

    root_path = f"/{name}"
    root = UsdGeom.Xform.Define(stage, root_path)
    stage.SetDefaultPrim(root.GetPrim())
    UsdPhysics.RigidBodyAPI.Apply(root.GetPrim())
    mass_api = UsdPhysics.MassAPI.Apply(root.GetPrim())
    mass_api.CreateMassAttr(float(mass_props.mass))
    mass_api.CreateCenterOfMassAttr(Gf.Vec3f(*(float(c) for c in mass_props.center_of_mass)))
    mass_api.CreateDiagonalInertiaAttr(Gf.Vec3f(*(float(v) for v in mass_props.principal_moments)))
    w, x, y, z = (float(v) for v in mass_props.principal_axes_quat)
    mass_api.CreatePrincipalAxesAttr(Gf.Quatf(w, x, y, z))
    if custom_data:
        root.GetPrim().SetCustomDataByKey("d3grasp", custom_data)

    visual_mesh = _define_mesh(stage, f"{root_path}/visual", visual.vertices, visual.faces)
    visual_mesh.CreateDisplayColorAttr([Gf.Vec3f(*color)])

    material = UsdShade.Material.Define(stage, f"{root_path}/physics_material")
    mat_api = UsdPhysics.MaterialAPI.Apply(material.GetPrim())
    mat_api.CreateStaticFrictionAttr(float(friction))
    mat_api.CreateDynamicFrictionAttr(float(friction))
    mat_api.CreateRestitutionAttr(float(restitution))
    mat_api.CreateDensityAttr(float(density))

    UsdGeom.Scope.Define(stage, f"{root_path}/collision")
    for i, hull in enumerate(hulls):
        hm = _define_mesh(stage, f"{root_path}/collision/hull_{i:03d}", hull.vertices, hull.faces)
        hm.CreatePurposeAttr(UsdGeom.Tokens.guide)  # colliders are not part of the render
        prim = hm.GetPrim()
        UsdPhysics.CollisionAPI.Apply(prim)
        UsdPhysics.MeshCollisionAPI.Apply(prim).CreateApproximationAttr(UsdPhysics.Tokens.convexHull)
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(
            material, UsdShade.Tokens.weakerThanDescendants, materialPurpose="physics"
        )

    path.parent.mkdir(parents=True, exist_ok=True)
    export_layer(stage.GetRootLayer(), str(path))
    return path
