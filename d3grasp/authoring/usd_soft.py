"""USD writer for FEM soft bodies: a ``UsdGeom.TetMesh`` that Newton 1.8's ``add_usd`` simulates.

Layout of a written file (``defaultPrim`` is the object, so it can be referenced or loaded with
``ModelBuilder.add_usd(path, xform=...)``)::

    /<name>                      Xform, PhysicsDeformableBodyAPI
    /<name>/sim                  TetMesh: points, tetVertexIndices, surfaceFaceVertexIndices,
                                 PhysicsVolumeDeformableSimAPI, PhysicsCollisionAPI,
                                 rel material:binding:physics -> /<name>/Materials/PhysicsMaterial
    /<name>/Materials/PhysicsMaterial
                                 Material, PhysicsMaterialAPI + PhysicsVolumeDeformableMaterialAPI:
                                 physics:youngsModulus (Pa), physics:poissonsRatio,
                                 physics:density (kg/m^3), physics:static/dynamicFriction,
                                 d3grasp:damping (Pa s), d3grasp:class

What Newton reads (``newton/_src/utils/import_usd_deformable_volume.py``, checked on 1.8.0): the
TetMesh with the applied ``PhysicsVolumeDeformableSimAPI`` token; the bound material's
``PhysicsVolumeDeformableMaterialAPI`` attributes, turned into per-tet Lamé parameters
``k_mu = E / (2 (1 + nu))`` and ``k_lambda = E nu / ((1 + nu)(1 - 2 nu))`` (``model.tet_materials``
columns 0 and 1); ``physics:density``, lumped as ``density * V_tet / 4`` per tet node. The deformable
API schemas are not registered with usd-core, so they are written as plain ``apiSchemas`` tokens,
which is how Newton checks them. Newton does **not** read a tet damping from USD (and not the
friction: soft contact friction is the model's ``soft_contact_mu``); they are recorded here as
custom attributes and the environment applies ``d3grasp:damping`` to ``model.tet_materials[:, 2]``
after loading. Newton also takes no particle radius from a TetMesh: set
``builder.default_particle_radius`` before ``add_usd`` (its 0.1 m default is larger than our objects).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .precision import export_layer
from .tetmesh import check_tet_mesh, rest_volume_and_mass, surface_faces

# Keys of the manifest's deformable material dict that this writer needs.
REQUIRED_MATERIAL_KEYS = ("youngs_modulus", "poissons_ratio", "density")


def lame_parameters(youngs_modulus: float, poissons_ratio: float) -> tuple[float, float]:
    """``(k_mu, k_lambda)`` in Pa from Young's modulus (Pa) and Poisson's ratio."""
    e, nu = youngs_modulus, poissons_ratio
    return e / (2.0 * (1.0 + nu)), e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))


def validate_material(material: dict[str, Any]) -> None:
    """Raise ``ValueError`` for a material Newton would reject, clamp or misread."""
    missing = [k for k in REQUIRED_MATERIAL_KEYS if k not in material]
    if missing:
        raise ValueError(f"deformable material is missing {missing}")
    e = float(material["youngs_modulus"])
    nu = float(material["poissons_ratio"])
    rho = float(material["density"])
    damping = float(material.get("damping", 0.0))
    if not (math.isfinite(e) and e > 0.0):
        raise ValueError(f"youngs_modulus must be positive, got {e}")
    # Newton replaces nu >= 0.5 by 0.499 with a warning; we refuse instead so the manifest and
    # the simulated material never disagree.
    if not (-1.0 < nu < 0.5):
        raise ValueError(f"poissons_ratio must be in (-1, 0.5), got {nu}")
    if not (math.isfinite(rho) and rho > 0.0):
        raise ValueError(f"density must be positive, got {rho}")
    if not (math.isfinite(damping) and damping >= 0.0):
        raise ValueError(f"damping must be >= 0, got {damping}")


def write_soft_usd(
    path: str | Path,
    points: np.ndarray,
    tets: np.ndarray,
    material: dict[str, Any],
    *,
    name: str,
    color: tuple[float, float, float] | None = None,
    doc: str = "",
    custom_data: dict[str, Any] | None = None,
) -> None:
    """Write a soft body as a USD TetMesh with a bound deformable physics material.

    ``points`` (N, 3) in metres, object frame (z up); ``tets`` (T, 4), positively oriented;
    ``material`` is the manifest's deformable material dict (``youngs_modulus`` Pa,
    ``poissons_ratio``, ``density`` kg/m^3, optional ``damping`` Pa s, ``friction``, ``class``);
    ``name`` is the root prim name (a valid USD identifier). The file format follows the suffix
    (``.usda`` text, ``.usd``/``.usdc`` crate). ``custom_data`` goes into the root prim's
    ``customData`` (``:`` in a key nests dictionaries), next to the ``d3grasp:num_tets``,
    ``num_nodes``, ``rest_volume`` and ``mass`` this writer records. Raises ``ValueError`` for
    invalid geometry or material before anything is written.
    """
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdPhysics, UsdShade, Vt

    if not Tf.IsValidIdentifier(name):
        raise ValueError(f"{name!r} is not a valid USD prim name")
    validate_material(material)
    points = np.asarray(points, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    check_tet_mesh(points, tets)
    # Newton reads points as float32: make sure no tet flips or collapses at that precision.
    check_tet_mesh(points.astype(np.float32).astype(np.float64), tets)
    tris = surface_faces(tets)

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)

    root = UsdGeom.Xform.Define(stage, f"/{name}")
    stage.SetDefaultPrim(root.GetPrim())
    root.GetPrim().AddAppliedSchema("PhysicsDeformableBodyAPI")
    if doc:
        stage.GetRootLayer().documentation = doc

    sim = UsdGeom.TetMesh.Define(stage, f"/{name}/sim")
    sim.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    sim.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    sim.CreateTetVertexIndicesAttr(Vt.Vec4iArray.FromNumpy(tets.astype(np.int32)))
    sim.CreateSurfaceFaceVertexIndicesAttr(Vt.Vec3iArray.FromNumpy(tris.astype(np.int32)))
    lo, hi = points.min(axis=0), points.max(axis=0)
    sim.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    if color is not None:
        sim.CreateDisplayColorAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, color))]))
    sim_prim = sim.GetPrim()
    sim_prim.AddAppliedSchema("PhysicsVolumeDeformableSimAPI")
    UsdPhysics.CollisionAPI.Apply(sim_prim)

    UsdGeom.Scope.Define(stage, f"/{name}/Materials")
    mat = UsdShade.Material.Define(stage, f"/{name}/Materials/PhysicsMaterial")
    mat_prim = mat.GetPrim()
    phys = UsdPhysics.MaterialAPI.Apply(mat_prim)
    mat_prim.AddAppliedSchema("PhysicsVolumeDeformableMaterialAPI")
    mat_prim.CreateAttribute("physics:youngsModulus", Sdf.ValueTypeNames.Float).Set(
        float(material["youngs_modulus"])
    )
    mat_prim.CreateAttribute("physics:poissonsRatio", Sdf.ValueTypeNames.Float).Set(
        float(material["poissons_ratio"])
    )
    phys.CreateDensityAttr(float(material["density"]))
    if "friction" in material:
        phys.CreateStaticFrictionAttr(float(material["friction"]))
        phys.CreateDynamicFrictionAttr(float(material["friction"]))
    damp = mat_prim.CreateAttribute("d3grasp:damping", Sdf.ValueTypeNames.Float, custom=True)
    damp.Set(float(material.get("damping", 0.0)))
    damp.SetDocumentation(
        "Tet viscous damping [Pa s] for SolverVBD (model.tet_materials[:, 2]); not read by "
        "Newton's USD importer, applied by the d3grasp environment after loading."
    )
    if "class" in material:
        mat_prim.CreateAttribute("d3grasp:class", Sdf.ValueTypeNames.Token, custom=True).Set(
            str(material["class"])
        )
    UsdShade.MaterialBindingAPI.Apply(sim_prim).Bind(
        mat, UsdShade.Tokens.weakerThanDescendants, materialPurpose="physics"
    )

    volume, mass = rest_volume_and_mass(points, tets, float(material["density"]))
    root.GetPrim().SetCustomDataByKey("d3grasp:num_tets", int(len(tets)))
    root.GetPrim().SetCustomDataByKey("d3grasp:num_nodes", int(len(points)))
    root.GetPrim().SetCustomDataByKey("d3grasp:rest_volume", float(volume))
    root.GetPrim().SetCustomDataByKey("d3grasp:mass", float(mass))
    for key, value in (custom_data or {}).items():
        root.GetPrim().SetCustomDataByKey(key, value)
    export_layer(stage.GetRootLayer(), str(path))


def read_soft_usd(path: str | Path) -> dict[str, Any]:
    """Read back what :func:`write_soft_usd` wrote, without Newton: points, tets, surface, material.

    For checks and tools; the simulator reads the file with ``ModelBuilder.add_usd``.
    """
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(path))
    if stage is None:
        raise ValueError(f"{path}: cannot open USD stage")
    root = stage.GetDefaultPrim()
    if not root:
        raise ValueError(f"{path}: no default prim")
    sim_prim = stage.GetPrimAtPath(root.GetPath().AppendChild("sim"))
    if not sim_prim or not sim_prim.IsA(UsdGeom.TetMesh):
        raise ValueError(f"{path}: no TetMesh at {root.GetPath()}/sim")
    sim = UsdGeom.TetMesh(sim_prim)
    mat, _ = UsdShade.MaterialBindingAPI(sim_prim).ComputeBoundMaterial("physics")
    if not mat:
        raise ValueError(f"{path}: no physics material bound to {sim_prim.GetPath()}")
    mp = mat.GetPrim()

    def _get(attr: str) -> Any:
        a = mp.GetAttribute(attr)
        return a.Get() if a and a.HasAuthoredValue() else None

    material = {
        "youngs_modulus": _get("physics:youngsModulus"),
        "poissons_ratio": _get("physics:poissonsRatio"),
        "density": _get("physics:density"),
        "damping": _get("d3grasp:damping"),
        "class": _get("d3grasp:class"),
    }
    return {
        "name": root.GetName(),
        "points": np.asarray(sim.GetPointsAttr().Get(), dtype=np.float64),
        "tets": np.asarray(sim.GetTetVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 4),
        "surface": np.asarray(sim.GetSurfaceFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3),
        "api_schemas": _authored_api_schemas(sim_prim),
        "material_api_schemas": _authored_api_schemas(mp),
        "material": material,
    }


def _authored_api_schemas(prim: Any) -> list[str]:
    """API schema tokens as authored, including ones usd-core does not know (the deformable ones)."""
    op = prim.GetMetadata("apiSchemas")
    return [str(t) for t in op.ApplyOperations([])] if op is not None else []
