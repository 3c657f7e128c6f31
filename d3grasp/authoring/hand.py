"""The DexHand13 right hand: kinematic spec, physical choices, USD writer and a Newton loader.

Conventions (see ``assets_usd/hands/README.md`` for the long version):

* Palm frame (``right_palm_link``): origin at the wrist end of the palm, fingers along +x, thumb on
  the -y side, **palmar side along +z** (finger flexion turns +x towards +z).
* Every link prim's frame is its joint (child) frame of the spec, so Newton's ``body_q`` of a link
  is exactly the URDF-convention forward kinematics of the spec.
* The hand is moved in space by a driven 6-DoF root chain, world -> ``root_x`` -> ``root_y`` ->
  ``root_z`` (prismatic) -> ``root_rz`` -> ``root_ry`` -> ``root_rx`` (revolute) -> palm, so the
  palm pose relative to the hand's import frame is ``Trans(x, y, z) · Rz(rz) · Ry(ry) · Rx(rx)``
  (URDF rpy order; see :func:`palm_pose_to_root_q`).
* Tactile pads: one box collider per pad, a child of the pad frame prim; the pad frame's +z axis
  (:data:`PAD_NORMAL_AXIS`) is the outward sensing normal (points away from the finger, towards
  the grasped object), so a pressing object pushes the pad along -z.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from d3grasp.authoring.precision import export_layer
from d3grasp.dexhand13 import (  # noqa: F401  (re-exported: the authoring API names them too)
    FINGER_JOINT_NAMES,
    FINGERS,
    LINK_NAMES,
    PAD_NAMES,
    PALM_LINK,
    ROOT_JOINT_NAMES,
    ROOT_LINK_NAMES,
    pad_finger,
    pad_groups,
)
from d3grasp.geometry import homogeneous, matrix_to_quat_xyzw_nonneg_w, quat_xyzw_to_matrix, rpy_matrix

# --------------------------------------------------------------------------------------------
# Names and fixed orders live in d3grasp.dexhand13 (the environment, the tactile kernel and the
# rewards index with them); the USD writer's own names follow.
# --------------------------------------------------------------------------------------------

HAND_PRIM = "/dexhand13"
"""Path of the hand's root Xform (default prim, carries ``ArticulationRootAPI``)."""

PAD_NORMAL_AXIS = 2
"""Axis of the pad frame that is the sensing normal: +z points out of the finger towards the object."""

PAD_NORMAL_SIGN = 1.0
"""Sign of :data:`PAD_NORMAL_AXIS` that faces outward (a pressing object pushes the pad along -z)."""

PALM_NORMAL = (0.0, 0.0, 1.0)
"""Palmar direction in the palm frame (the side the fingers close towards)."""

PAD_COLLIDER = "pad"
"""Name of the box collider prim below each pad frame prim: ``.../<link>/<pad name>/pad``."""

LINK_COLLIDER = "collision"
"""Name of the box collider prim below each link prim that has one."""


# --------------------------------------------------------------------------------------------
# The kinematic spec.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class JointSpec:
    """One joint of the spec (URDF convention: child frame = parent · Trans(xyz) · Rot(rpy))."""

    name: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    lower: float = 0.0
    upper: float = 0.0
    effort: float = 0.0


@dataclass(frozen=True)
class LinkSpec:
    """Bounding box of a link's geometry in its own frame, and its (shell) CAD mass."""

    name: str
    box_min: tuple[float, float, float]
    box_max: tuple[float, float, float]
    cad_mass: float


@dataclass(frozen=True)
class HandSpec:
    """The DexHand13 figures: 16 revolute joints, 11 fixed pad frames, link boxes."""

    root: str
    joints: tuple[JointSpec, ...]
    pads: tuple[JointSpec, ...]
    links: dict[str, LinkSpec]

    def joint(self, name: str) -> JointSpec:
        for j in self.joints:
            if j.name == name:
                return j
        raise KeyError(f"no joint {name!r} in the hand spec")

    def pad(self, name: str) -> JointSpec:
        """The fixed joint placing pad ``name`` (its ``child``) on its finger link."""
        for p in self.pads:
            if p.child == name:
                return p
        raise KeyError(f"no pad {name!r} in the hand spec")


def default_spec_path() -> Path:
    """The spec in a source checkout (``tools/specs/dexhand13_kinematics.json``); authoring only."""
    return Path(__file__).resolve().parents[2] / "tools" / "specs" / "dexhand13_kinematics.json"


def load_spec(path: str | Path | None = None) -> HandSpec:
    """Read the kinematic spec JSON and check it names exactly the links, joints and pads we expect."""
    path = Path(path) if path is not None else default_spec_path()
    if not path.is_file():
        raise FileNotFoundError(f"hand spec not found: {path} (pass the path to dexhand13_kinematics.json)")
    raw = json.loads(path.read_text())

    def _joint(d: dict[str, Any]) -> JointSpec:
        return JointSpec(
            name=d["name"],
            parent=d["parent"],
            child=d["child"],
            xyz=tuple(float(v) for v in d["xyz"]),
            rpy=tuple(float(v) for v in d["rpy"]),
            lower=float(d.get("lower", 0.0)),
            upper=float(d.get("upper", 0.0)),
            effort=float(d.get("effort", 0.0)),
        )

    joints = tuple(_joint(d) for d in raw["joints"])
    pads = tuple(_joint(d) for d in raw["tactile_pads"])
    links = {
        name: LinkSpec(name, tuple(v["box_min"]), tuple(v["box_max"]), float(v["mass"]))
        for name, v in raw["links"].items()
    }
    for j in joints:
        if tuple(float(a) for a in raw["joints"][joints.index(j)]["axis"]) != (0.0, 0.0, 1.0):
            raise ValueError(f"{path}: joint {j.name} axis is not local z; the USD writer assumes it is")
    spec = HandSpec(root=raw["root"], joints=joints, pads=pads, links=links)
    if spec.root != PALM_LINK:
        raise ValueError(f"{path}: root link is {spec.root!r}, expected {PALM_LINK!r}")
    if sorted(j.name for j in joints) != sorted(FINGER_JOINT_NAMES):
        raise ValueError(f"{path}: joints differ from the 16 expected finger joints")
    if sorted(p.child for p in pads) != sorted(PAD_NAMES):
        raise ValueError(f"{path}: tactile pads differ from the 11 expected pads")
    missing = [n for n in (*LINK_NAMES, *PAD_NAMES) if n not in links]
    if missing:
        raise ValueError(f"{path}: no link box for {missing}")
    return spec


# --------------------------------------------------------------------------------------------
# Physical choices.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HandPhysics:
    """Masses, drives and contact material of the simulated hand (the spec only has shell masses).

    Masses: the real DexH13 weighs roughly 1 kg; its CAD shells sum to 0.19 kg because motors,
    boards and fasteners are missing. We put 0.55 kg in the palm (it houses the actuators), 130 g
    in each long finger and 155 g in the thumb: 1.10 kg in all. Each body's inertia is that of a
    solid box of its mass filling the spec's link box, centred on the box (principal axes = link axes).

    Drives: finger ke 20 N·m/rad, kd 0.5. The first prototype's value (ke 2, kd 0.05) let the thumb base
    (joints 0 and 1 share a pivot through the light abduction carrier) lag 0.4 rad, overshoot its
    limit and drift at ~1 Hz under SolverVBD at 5 iterations, with or without gravity; at ke 20 every
    finger joint holds its target within ~0.01 rad. Root gains make the palm a stiff positioner:
    5e4 N/m keeps the drive's sag under hand plus a 0.5 kg object below 0.4 mm (measured palm error
    after a 0.1 m lift: 1.3 mm, the rest is the chain's joint compliance in VBD).
    ``max_force`` values are authored for solvers that honour them (SolverVBD ignores effort limits).
    """

    palm_mass: float = 0.55
    finger_link_masses: tuple[float, float, float, float] = (0.010, 0.060, 0.035, 0.025)
    thumb_link_masses: tuple[float, float, float, float] = (0.010, 0.050, 0.060, 0.035)
    root_link_mass: float = 0.1
    root_link_inertia: float = 1.0e-4

    finger_stiffness: float = 20.0  # N·m/rad
    finger_damping: float = 0.5  # N·m·s/rad
    finger_max_force: float = 10.0  # N·m, the spec's effort

    root_linear_stiffness: float = 5.0e4  # N/m
    root_linear_damping: float = 5.0e2  # N·s/m
    root_linear_max_force: float = 500.0  # N
    root_angular_stiffness: float = 2.0e3  # N·m/rad
    root_angular_damping: float = 40.0  # N·m·s/rad
    root_angular_max_force: float = 100.0  # N·m

    friction: float = 1.0
    restitution: float = 0.0

    def link_mass(self, link: str) -> float:
        """Mass [kg] of a spec link under these choices."""
        if link == PALM_LINK:
            return self.palm_mass
        for finger in FINGERS:
            prefix = f"right_{finger}_link_"
            if link.startswith(prefix):
                masses = self.thumb_link_masses if finger == "thumb" else self.finger_link_masses
                return masses[int(link[len(prefix) :])]
        raise KeyError(f"no mass choice for link {link!r}")

    def total_mass(self) -> float:
        """Mass of the hand proper (palm and fingers, without the root chain's helper bodies)."""
        return sum(self.link_mass(n) for n in LINK_NAMES)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------------------------
# The root chain's coordinates (the rotation helpers are in d3grasp.geometry).
# --------------------------------------------------------------------------------------------


def palm_pose_to_root_q(pos: Sequence[float], quat_xyzw: Sequence[float]) -> np.ndarray:
    """Root joint coordinates ``(x, y, z, rz, ry, rx)`` that put the palm at ``pos``/``quat_xyzw``.

    The pose is relative to the hand's import frame (the ``xform`` given to :func:`add_hand`).
    The rotation is decomposed as ``Rz(rz) · Ry(ry) · Rx(rx)``; it is singular at ``ry = ±pi/2``
    (palm x axis vertical), where ``rx`` is set to 0.
    """
    r = quat_xyzw_to_matrix(quat_xyzw)
    ry = math.asin(max(-1.0, min(1.0, -r[2, 0])))
    if abs(r[2, 0]) < 1.0 - 1e-9:
        rz = math.atan2(r[1, 0], r[0, 0])
        rx = math.atan2(r[2, 1], r[2, 2])
    else:
        rx = 0.0
        rz = math.atan2(-r[0, 1], r[1, 1])
    return np.array([pos[0], pos[1], pos[2], rz, ry, rx], dtype=np.float64)


def root_q_to_palm_pose(root_q: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`palm_pose_to_root_q`: palm position and quaternion (x, y, z, w)."""
    x, y, z, rz, ry, rx = (float(v) for v in root_q)
    return np.array([x, y, z]), matrix_to_quat_xyzw_nonneg_w(rpy_matrix((rx, ry, rz)))


def spec_link_frames(spec: HandSpec, joint_q: dict[str, float] | None = None) -> dict[str, np.ndarray]:
    """4x4 frames of every link and pad in the palm frame at joint positions ``joint_q`` (default 0)."""
    joint_q = joint_q or {}
    frames = {spec.root: np.eye(4)}
    pending = list(spec.joints)
    while pending:
        j = next(j for j in pending if j.parent in frames)
        pending.remove(j)
        q = float(joint_q.get(j.name, 0.0))
        frames[j.child] = (
            frames[j.parent]
            @ homogeneous(j.xyz, rpy_matrix(j.rpy))
            @ homogeneous((0, 0, 0), rpy_matrix((0, 0, q)))
        )
    for p in spec.pads:
        frames[p.child] = frames[p.parent] @ homogeneous(p.xyz, rpy_matrix(p.rpy))
    return frames


def box_inertia(mass: float, extents: Sequence[float]) -> tuple[float, float, float]:
    """Principal moments [kg·m²] of a solid box of ``mass`` and full side lengths ``extents``."""
    a, b, c = (float(e) for e in extents)
    return (mass * (b * b + c * c) / 12.0, mass * (a * a + c * c) / 12.0, mass * (a * a + b * b) / 12.0)


# --------------------------------------------------------------------------------------------
# USD writer.
# --------------------------------------------------------------------------------------------


def _links_with_collider() -> set[str]:
    # The abduction carriers (link_0) are 3 mm plates buried between the palm and link_1: they
    # keep their mass but get no collider (they could only make spurious contacts).
    return {n for n in LINK_NAMES if not n.endswith("_link_0")}


def write_hand_usd(
    out_path: str | Path, spec: HandSpec | None = None, physics: HandPhysics | None = None
) -> Path:
    """Author the DexHand13 (16 finger joints, 11 pad colliders, 6-DoF driven root) as a USDA file.

    Deterministic: the same spec and physics give the same file, byte for byte.
    """
    # Registering Newton's schemas first makes the output independent of what the caller imported
    # before (registered schema attributes are written without the ``custom`` keyword).
    import newton_usd_schemas  # noqa: F401
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdShade

    spec = spec or load_spec()
    physics = physics or HandPhysics()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdPhysics.SetStageKilogramsPerUnit(stage, 1.0)
    stage.SetMetadata(
        "comment",
        "DexHand13 right hand for d3grasp, generated by tools/build_hand.py from the kinematic figures "
        "in tools/specs/dexhand13_kinematics.json. Own box geometry; see assets_usd/hands/README.md.",
    )

    hand = UsdGeom.Xform.Define(stage, HAND_PRIM)
    stage.SetDefaultPrim(hand.GetPrim())
    UsdPhysics.ArticulationRootAPI.Apply(hand.GetPrim())
    # Hand links overlap by design (boxes fitted to the CAD bounds, pads sunk into the links), and
    # fingers may touch each other near full abduction: self-collision would only make spurious
    # contacts, so the whole articulation is filtered against itself.
    hand.GetPrim().AddAppliedSchema("NewtonArticulationRootAPI")
    hand.GetPrim().CreateAttribute("newton:selfCollisionEnabled", Sdf.ValueTypeNames.Bool).Set(False)

    UsdGeom.Scope.Define(stage, f"{HAND_PRIM}/materials")
    material = UsdShade.Material.Define(stage, f"{HAND_PRIM}/materials/skin")
    mat_api = UsdPhysics.MaterialAPI.Apply(material.GetPrim())
    mat_api.CreateStaticFrictionAttr(physics.friction)
    mat_api.CreateDynamicFrictionAttr(physics.friction)
    mat_api.CreateRestitutionAttr(physics.restitution)

    frames = spec_link_frames(spec)
    link_path = {name: f"{HAND_PRIM}/{name}" for name in (*ROOT_LINK_NAMES, *LINK_NAMES)}

    def _set_pose(xformable: UsdGeom.Xformable, m: np.ndarray) -> None:
        q = matrix_to_quat_xyzw_nonneg_w(m[:3, :3])
        xformable.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*(float(v) for v in m[:3, 3])))
        xformable.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(
            Gf.Quatd(float(q[3]), *(float(v) for v in q[:3]))
        )

    def _add_body(path: str, pose: np.ndarray, mass: float, com, inertia) -> Usd.Prim:
        xf = UsdGeom.Xform.Define(stage, path)
        _set_pose(xf, pose)
        prim = xf.GetPrim()
        UsdPhysics.RigidBodyAPI.Apply(prim)
        mass_api = UsdPhysics.MassAPI.Apply(prim)
        mass_api.CreateMassAttr(float(mass))
        mass_api.CreateCenterOfMassAttr(Gf.Vec3f(*(float(v) for v in com)))
        mass_api.CreateDiagonalInertiaAttr(Gf.Vec3f(*(float(v) for v in inertia)))
        mass_api.CreatePrincipalAxesAttr(Gf.Quatf(1.0, 0.0, 0.0, 0.0))
        return prim

    def _add_box(path: str, box_min, box_max, pose_in_parent: np.ndarray | None = None) -> None:
        parent = path.rsplit("/", 1)[0]
        if pose_in_parent is not None:
            _set_pose(UsdGeom.Xform.Define(stage, parent), pose_in_parent)
        lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
        cube = UsdGeom.Cube.Define(stage, path)
        cube.CreateSizeAttr(1.0)
        cube.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(
            Gf.Vec3d(*(float(v) for v in 0.5 * (lo + hi)))
        )
        cube.AddScaleOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*(float(v) for v in hi - lo)))
        UsdPhysics.CollisionAPI.Apply(cube.GetPrim())
        binding = UsdShade.MaterialBindingAPI.Apply(cube.GetPrim())
        binding.Bind(material, UsdShade.Tokens.weakerThanDescendants, "physics")

    # Root chain helpers: all at the palm origin in the rest pose, no colliders.
    i_root = physics.root_link_inertia
    for name in ROOT_LINK_NAMES:
        _add_body(link_path[name], np.eye(4), physics.root_link_mass, (0, 0, 0), (i_root, i_root, i_root))

    # Hand links: frame = joint frame; mass of a solid box filling the spec's link box.
    with_collider = _links_with_collider()
    for name in LINK_NAMES:
        box = spec.links[name]
        lo, hi = np.asarray(box.box_min), np.asarray(box.box_max)
        mass = physics.link_mass(name)
        _add_body(link_path[name], frames[name], mass, 0.5 * (lo + hi), box_inertia(mass, hi - lo))
        if name in with_collider:
            _add_box(f"{link_path[name]}/{LINK_COLLIDER}", lo, hi)

    # Tactile pads: a frame prim at the spec's pad frame holding the pad's own box collider.
    for pad in PAD_NAMES:
        pj = spec.pad(pad)
        box = spec.links[pad]
        pose = homogeneous(pj.xyz, rpy_matrix(pj.rpy))
        _add_box(
            f"{link_path[pj.parent]}/{pad}/{PAD_COLLIDER}", box.box_min, box.box_max, pose_in_parent=pose
        )

    UsdGeom.Scope.Define(stage, f"{HAND_PRIM}/joints")

    def _joint_common(joint, body0: str | None, body1: str, pos0, rot0: np.ndarray) -> None:
        if body0 is not None:
            joint.CreateBody0Rel().SetTargets([Sdf.Path(body0)])
        joint.CreateBody1Rel().SetTargets([Sdf.Path(body1)])
        q = matrix_to_quat_xyzw_nonneg_w(rot0)
        joint.CreateLocalPos0Attr(Gf.Vec3f(*(float(v) for v in pos0)))
        joint.CreateLocalRot0Attr(Gf.Quatf(float(q[3]), *(float(v) for v in q[:3])))
        joint.CreateLocalPos1Attr(Gf.Vec3f(0.0, 0.0, 0.0))
        joint.CreateLocalRot1Attr(Gf.Quatf(1.0, 0.0, 0.0, 0.0))

    def _drive(prim: Usd.Prim, kind: str, stiffness: float, damping: float, max_force: float) -> None:
        drive = UsdPhysics.DriveAPI.Apply(prim, kind)
        drive.CreateTypeAttr("force")
        drive.CreateStiffnessAttr(float(stiffness))
        drive.CreateDampingAttr(float(damping))
        drive.CreateMaxForceAttr(float(max_force))
        drive.CreateTargetPositionAttr(0.0)

    # UsdPhysics angular drive gains are per degree: N·m/rad · (pi/180) = N·m/deg.
    per_deg = math.pi / 180.0
    chain = [None, *(link_path[n] for n in ROOT_LINK_NAMES), link_path[PALM_LINK]]
    for i, name in enumerate(ROOT_JOINT_NAMES):
        axis = "XYZ"[i] if i < 3 else "ZYX"[i - 3]
        path = f"{HAND_PRIM}/joints/{name}"
        if i < 3:
            joint = UsdPhysics.PrismaticJoint.Define(stage, path)
            _drive(
                joint.GetPrim(),
                "linear",
                physics.root_linear_stiffness,
                physics.root_linear_damping,
                physics.root_linear_max_force,
            )
        else:
            joint = UsdPhysics.RevoluteJoint.Define(stage, path)
            _drive(
                joint.GetPrim(),
                "angular",
                physics.root_angular_stiffness * per_deg,
                physics.root_angular_damping * per_deg,
                physics.root_angular_max_force,
            )
        joint.CreateAxisAttr(axis)
        _joint_common(joint, chain[i], chain[i + 1], (0.0, 0.0, 0.0), np.eye(3))

    for name in FINGER_JOINT_NAMES:
        j = spec.joint(name)
        joint = UsdPhysics.RevoluteJoint.Define(stage, f"{HAND_PRIM}/joints/{name}")
        joint.CreateAxisAttr("Z")
        joint.CreateLowerLimitAttr(math.degrees(j.lower))
        joint.CreateUpperLimitAttr(math.degrees(j.upper))
        _joint_common(joint, link_path[j.parent], link_path[j.child], j.xyz, rpy_matrix(j.rpy))
        _drive(
            joint.GetPrim(),
            "angular",
            physics.finger_stiffness * per_deg,
            physics.finger_damping * per_deg,
            physics.finger_max_force,
        )

    export_layer(stage.GetRootLayer(), str(out_path))
    return out_path


# --------------------------------------------------------------------------------------------
# Loading into Newton.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HandIndices:
    """Where one imported hand lives inside a ``newton.ModelBuilder`` (and the finalized model).

    Index arrays follow the fixed orders of this module: ``finger_*`` follow
    :data:`FINGER_JOINT_NAMES`, ``root_*`` follow :data:`ROOT_JOINT_NAMES`, ``pad_*`` follow
    :data:`PAD_NAMES`. ``*_q`` index ``joint_q``/``control.joint_target_q`` and ``*_dof`` index
    ``joint_qd``, ``joint_target_ke`` and the other per-DoF arrays.
    """

    joint_range: tuple[int, int]
    body_range: tuple[int, int]
    shape_range: tuple[int, int]
    finger_joints: np.ndarray
    finger_q: np.ndarray
    finger_dof: np.ndarray
    root_joints: np.ndarray
    root_q: np.ndarray
    root_dof: np.ndarray
    palm_body: int
    link_bodies: dict[str, int]
    pad_shapes: np.ndarray
    pad_bodies: np.ndarray
    pad_xform_in_body: np.ndarray
    """(11, 7) pad frame in its body's frame: position, quaternion (x, y, z, w)."""


def _suffix_index(labels: Sequence[str], start: int, end: int, suffix: str, what: str) -> int:
    hits = [i for i in range(start, end) if labels[i].endswith(suffix)]
    if len(hits) != 1:
        raise ValueError(f"expected one {what} ending in {suffix!r} in the imported hand, found {len(hits)}")
    return hits[0]


def add_hand(
    builder: Any,
    usd_path: str | Path | None = None,
    xform: Any = None,
    *,
    kinematic_palm: bool = False,
    **add_usd_kwargs: Any,
) -> HandIndices:
    """Append one DexHand13 to ``builder`` (call inside ``begin_world``/``end_world`` for one hand per world).

    ``xform`` (a ``wp.transform``) is the frame the root chain is anchored to: root joint
    coordinates are the palm pose relative to it (see :func:`palm_pose_to_root_q`). Extra keyword
    arguments go to ``ModelBuilder.add_usd``. Returns the index ranges of what was added.

    ``kinematic_palm=True`` skips the driven root chain (its 6 joints and 5 helper bodies) and makes
    the palm a kinematic root body on a free joint: the caller prescribes the palm pose every
    substep (a real arm is stiff, so exact root tracking is the better model) and SolverVBD derives
    its velocity from the pose change. ``root_*`` then index that free joint (7 coordinates:
    position, quaternion x, y, z, w; 6 DoFs) and ``xform`` should be the identity.
    """
    import newton

    from d3grasp.paths import hand_usd

    usd_path = Path(usd_path) if usd_path is not None else hand_usd()
    if not usd_path.is_file():
        raise FileNotFoundError(f"hand USD not found: {usd_path} (run tools/build_hand.py)")
    if kinematic_palm:
        chain = [f"{HAND_PRIM}/joints/{n}" for n in ROOT_JOINT_NAMES] + [
            f"{HAND_PRIM}/{n}" for n in ROOT_LINK_NAMES
        ]
        add_usd_kwargs["ignore_paths"] = [*add_usd_kwargs.get("ignore_paths", []), *chain]
    j0, b0, s0 = builder.joint_count, builder.body_count, builder.shape_count
    builder.add_usd(str(usd_path), xform=xform, **add_usd_kwargs)
    j1, b1, s1 = builder.joint_count, builder.body_count, builder.shape_count

    jl, bl, sl = builder.joint_label, builder.body_label, builder.shape_label

    def _joints(names: Sequence[str]) -> np.ndarray:
        return np.array([_suffix_index(jl, j0, j1, f"/joints/{n}", "joint") for n in names], dtype=np.int32)

    finger_joints = _joints(FINGER_JOINT_NAMES)
    q_start, qd_start = builder.joint_q_start, builder.joint_qd_start
    bodies = LINK_NAMES if kinematic_palm else (*ROOT_LINK_NAMES, *LINK_NAMES)
    link_bodies = {n: _suffix_index(bl, b0, b1, f"/{n}", "body") for n in bodies}
    if kinematic_palm:
        palm = link_bodies[PALM_LINK]
        root_joints = np.array([j for j in range(j0, j1) if builder.joint_child[j] == palm], dtype=np.int32)
        if len(root_joints) != 1 or builder.joint_parent[int(root_joints[0])] != -1:
            raise ValueError(f"{usd_path}: expected the palm to be a root body on one free joint")
        builder.body_flags[palm] = int(newton.BodyFlags.KINEMATIC)
        j = int(root_joints[0])
        root_q = np.arange(q_start[j], q_start[j] + 7, dtype=np.int32)
        root_dof = np.arange(qd_start[j], qd_start[j] + 6, dtype=np.int32)
    else:
        root_joints = _joints(ROOT_JOINT_NAMES)
        root_q = np.array([q_start[j] for j in root_joints], dtype=np.int32)
        root_dof = np.array([qd_start[j] for j in root_joints], dtype=np.int32)

    pad_shapes, pad_bodies = [], []
    for pad in PAD_NAMES:
        shape = _suffix_index(sl, s0, s1, f"/{pad}/{PAD_COLLIDER}", "pad shape")
        pad_shapes.append(shape)
        pad_bodies.append(builder.shape_body[shape])
    pad_xforms = _read_pad_frames(str(usd_path.resolve()), usd_path.stat().st_mtime_ns)

    return HandIndices(
        joint_range=(j0, j1),
        body_range=(b0, b1),
        shape_range=(s0, s1),
        finger_joints=finger_joints,
        finger_q=np.array([q_start[j] for j in finger_joints], dtype=np.int32),
        finger_dof=np.array([qd_start[j] for j in finger_joints], dtype=np.int32),
        root_joints=root_joints,
        root_q=root_q,
        root_dof=root_dof,
        palm_body=link_bodies[PALM_LINK],
        link_bodies=link_bodies,
        pad_shapes=np.array(pad_shapes, dtype=np.int32),
        pad_bodies=np.array(pad_bodies, dtype=np.int32),
        pad_xform_in_body=pad_xforms.copy(),
    )


@functools.lru_cache(maxsize=8)
def _read_pad_frames(path: str, mtime_ns: int) -> np.ndarray:
    """(11, 7) pad frames relative to their links, read from the USD (cached: one read per file version)."""
    from pxr import Usd, UsdGeom

    del mtime_ns  # part of the cache key only
    stage = Usd.Stage.Open(path)
    cache = UsdGeom.XformCache()
    rows = []
    for pad in PAD_NAMES:
        # The pad frame prim, parent of the (off-centre) pad collider.
        prim = stage.GetPrimAtPath(f"{HAND_PRIM}/{_pad_parent_link(stage, pad)}/{pad}")
        m = np.array(cache.GetLocalTransformation(prim)[0], dtype=np.float64).T
        rows.append(np.concatenate([m[:3, 3], matrix_to_quat_xyzw_nonneg_w(m[:3, :3])]))
    out = np.array(rows)
    out.setflags(write=False)
    return out


def _pad_parent_link(stage: Any, pad: str) -> str:
    for link in LINK_NAMES:
        if stage.GetPrimAtPath(f"{HAND_PRIM}/{link}/{pad}"):
            return link
    raise ValueError(f"pad {pad!r} not found under any link of {HAND_PRIM}")
