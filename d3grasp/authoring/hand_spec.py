"""The DexHand13 right hand's definition: prim names, the kinematic spec, the physical choices and
the root chain's coordinates.

The USD writer (:mod:`d3grasp.authoring.hand_usd`) and the Newton loader
(:mod:`d3grasp.authoring.hand_newton`) both build on this module.

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

import json
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from d3grasp.dexhand13 import FINGER_JOINT_NAMES, FINGERS, LINK_NAMES, PAD_NAMES, PALM_LINK
from d3grasp.geometry import homogeneous, matrix_to_quat_xyzw_nonneg_w, quat_xyzw_to_matrix, rpy_matrix

# --------------------------------------------------------------------------------------------
# Names and fixed orders live in d3grasp.dexhand13 (the environment, the tactile kernel and the
# rewards index with them); the names of the authored USD's prims follow (the writer authors them,
# the loader and the grasp planner look them up).
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
# Frames: the root chain's coordinates, the spec's forward kinematics, box inertia (the rotation
# helpers are in d3grasp.geometry).
# --------------------------------------------------------------------------------------------


def palm_pose_to_root_q(pos: Sequence[float], quat_xyzw: Sequence[float]) -> np.ndarray:
    """Root joint coordinates ``(x, y, z, rz, ry, rx)`` that put the palm at ``pos``/``quat_xyzw``.

    The pose is relative to the hand's import frame (the ``xform`` given to
    :func:`d3grasp.authoring.hand_newton.add_hand`).
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
