"""Grasps synthesised by gradient descent on the differentiable grasp energy (kernels.grasp_energy).

The hand's kinematics come from the installed hand model, ``assets_usd/hands/dexhand13.usda``
(:func:`d3grasp.paths.hand_usd`): the 16 finger joints' frames, axes and limits, the 11 tactile
pads' frames and boxes, and the link colliders, exactly as the simulation loads them. The kinematic
spec in ``tools/specs/`` is not installed, so it is only an alternative source for a checkout
(:func:`hand_kinematics_from_spec`; the tests check both agree).

Contact points: each pad's outer face centre (the pad box's ``+z`` face in the pad frame, whose
``+z`` is the outward sensing normal, ``d3grasp.authoring.hand_spec.PAD_NORMAL_AXIS``), and a 3 x 3 grid on
the palm collider's palmar face (``+z``), its centre first. Which of them take part in the
force-closure and distance terms depends on the grasp type (:data:`CONTACT_SETS`): a pinch holds the
object between the index and thumb tips, the top hook and the side wrap between the three finger
tips and the thumb tip.

Starts are the type's geometric placement of ``d3grasp.envs.grasps.object_grasp`` (palm down for
``top`` and ``pinch``, palm vertical for ``side``) turned about the object's vertical axis, jittered,
with the fingers half closed; :func:`synthesise` descends from all of them at once and returns the
best.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from d3grasp.authoring.hand_spec import (
    HAND_PRIM,
    LINK_COLLIDER,
    PAD_COLLIDER,
    PAD_NORMAL_AXIS,
    PAD_NORMAL_SIGN,
    load_spec,
)
from d3grasp.dexhand13 import (
    ABDUCTION_JOINTS,
    FINGER_JOINT_NAMES,
    FINGER_PADS,
    LINK_NAMES,
    PAD_NAMES,
    PALM_LINK,
)
from d3grasp.envs.grasps import DROP_GAP, ObjectGrasp, object_grasp, rest_height
from d3grasp.geometry import matrix_to_quat_xyzw_nonneg_w, quat_xyzw_to_matrix, rot_z, rpy_matrix
from d3grasp.kernels.grasp_descent import descend
from d3grasp.kernels.grasp_energy_inputs import (
    POSE_PARAMS,
    TERM_NAMES,
    EnergyWeights,
    HandLayout,
    ObjectShape,
)
from d3grasp.vocabulary import GRASP_TYPES

PALM_CONTACT_NAMES: tuple[str, ...] = ("palm_centre", *(f"palm_{i}" for i in range(8)))
"""The palm face's contact points: its centre, then the other eight of the 3 x 3 grid."""

PALM_GRID = (0.2, 0.5, 0.8)
"""Where the palm face's grid points sit along x and y, as shares of the collider's extent."""

_INDEX_TIP, _MIDDLE_TIP, _RING_TIP, _THUMB_TIP = (PAD_NAMES[FINGER_PADS[f][-1]] for f in range(4))
_FINGERS_AND_THUMB = {_INDEX_TIP: 1.0, _MIDDLE_TIP: 1.0, _RING_TIP: 1.0, _THUMB_TIP: 3.0}
CONTACT_SETS: dict[str, dict[str, float]] = {
    "top": _FINGERS_AND_THUMB,
    "side": _FINGERS_AND_THUMB,
    "pinch": {_INDEX_TIP: 1.0, _THUMB_TIP: 1.0},
}
"""Contact weights in the force-closure and distance terms per grasp type (every hand point counts
for penetration). The weight is also the contact's force magnitude in ``E_fc``, so the thumb tip,
which alone opposes three finger tips, weighs 3: with unit weights the residual cannot drop below
``(3 - 1)^2``. Measured (64 starts, 300 steps, 4-12 cm spheres and boxes), these beat every pad and
the palm's centre with unit weights (residual 4-10, half the pads 1-5 cm off the surface: a small
object has no room for them all), the tips with unit weights, and the tips with the palm."""
assert set(CONTACT_SETS) == set(GRASP_TYPES)


# --------------------------------------------------------------------------------------------
# The hand's kinematics as the dict of HandLayout.from_dict.
# --------------------------------------------------------------------------------------------


def _pad_contact(
    frame: np.ndarray, box_min: np.ndarray, box_max: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Outer face centre and outward normal of a pad box (in its pad frame ``frame``, 4x4 in the link)."""
    face = 0.5 * (box_min + box_max)
    face[PAD_NORMAL_AXIS] = box_max[PAD_NORMAL_AXIS] if PAD_NORMAL_SIGN > 0 else box_min[PAD_NORMAL_AXIS]
    normal = PAD_NORMAL_SIGN * frame[:3, PAD_NORMAL_AXIS]
    return frame[:3, :3] @ face + frame[:3, 3], normal


def _palm_contacts(box_min: np.ndarray, box_max: np.ndarray) -> list[dict[str, Any]]:
    grid = [(a, b) for a in PALM_GRID for b in PALM_GRID]
    grid.remove((0.5, 0.5))
    out = []
    for name, (a, b) in zip(PALM_CONTACT_NAMES, [(0.5, 0.5), *grid], strict=True):
        xyz = [
            box_min[0] + a * (box_max[0] - box_min[0]),
            box_min[1] + b * (box_max[1] - box_min[1]),
            box_max[2],
        ]
        out.append({"name": name, "link": PALM_LINK, "xyz": xyz, "normal": [0.0, 0.0, 1.0]})
    return out


def _with_collider(link: str) -> bool:
    # As the USD writer: the link_0 abduction carriers are buried in the palm and have no collider.
    return not link.endswith("_link_0")


def hand_kinematics_from_usd(usd_path: str | Path | None = None) -> dict[str, Any]:
    """The hand's kinematics (:meth:`HandLayout.from_dict`'s dict) read from the hand's USD file."""
    from pxr import Gf, Usd, UsdGeom

    from d3grasp.paths import hand_usd

    path = Path(usd_path) if usd_path is not None else hand_usd()
    if not path.is_file():
        raise FileNotFoundError(f"hand USD not found: {path}")
    stage = Usd.Stage.Open(str(path))

    def local(prim: Usd.Prim) -> np.ndarray:
        # Gf matrices act on row vectors: transpose to the column-vector convention.
        return np.array(UsdGeom.Xformable(prim).GetLocalTransformation(), dtype=np.float64).T

    def cube_box(prim: Usd.Prim) -> tuple[np.ndarray, np.ndarray]:
        m = local(prim)
        if not np.allclose(m[:3, :3], np.diag(np.diag(m[:3, :3])), atol=1e-12):
            raise ValueError(f"{prim.GetPath()}: a rotated collider box is not supported")
        half = 0.5 * float(prim.GetAttribute("size").Get()) * np.abs(np.diag(m[:3, :3]))
        return m[:3, 3] - half, m[:3, 3] + half

    joints = []
    for name in FINGER_JOINT_NAMES:
        prim = stage.GetPrimAtPath(f"{HAND_PRIM}/joints/{name}")
        if not prim.IsValid():
            raise ValueError(f"{path}: no joint {name}")
        body0 = prim.GetRelationship("physics:body0").GetTargets()[0].name
        body1 = prim.GetRelationship("physics:body1").GetTargets()[0].name
        rot0: Gf.Quatf = prim.GetAttribute("physics:localRot0").Get()
        quat = [*rot0.GetImaginary(), rot0.GetReal()]
        rot1: Gf.Quatf = prim.GetAttribute("physics:localRot1").Get()
        if any(abs(v) > 1e-6 for v in rot1.GetImaginary()) or any(
            abs(v) > 1e-6 for v in prim.GetAttribute("physics:localPos1").Get()
        ):
            raise ValueError(f"{path}: joint {name}'s child frame is not its link frame")
        axis = np.eye(3)["XYZ".index(str(prim.GetAttribute("physics:axis").Get()))]
        joints.append(
            {
                "name": name,
                "parent": body0,
                "child": body1,
                "xyz": [float(v) for v in prim.GetAttribute("physics:localPos0").Get()],
                "rot": quat_xyzw_to_matrix(quat).tolist(),
                "axis": axis.tolist(),
                "lower": math.radians(float(prim.GetAttribute("physics:lowerLimit").Get())),
                "upper": math.radians(float(prim.GetAttribute("physics:upperLimit").Get())),
            }
        )

    contacts, colliders = [], []
    for pad in PAD_NAMES:
        link = next(n for n in LINK_NAMES if stage.GetPrimAtPath(f"{HAND_PRIM}/{n}/{pad}").IsValid())
        frame_prim = stage.GetPrimAtPath(f"{HAND_PRIM}/{link}/{pad}")
        lo, hi = cube_box(frame_prim.GetChild(PAD_COLLIDER))
        xyz, normal = _pad_contact(local(frame_prim), lo, hi)
        contacts.append({"name": pad, "link": link, "xyz": xyz.tolist(), "normal": normal.tolist()})
    for link in LINK_NAMES:
        box_prim = stage.GetPrimAtPath(f"{HAND_PRIM}/{link}/{LINK_COLLIDER}")
        if box_prim.IsValid():
            lo, hi = cube_box(box_prim)
            colliders.append({"link": link, "box_min": lo.tolist(), "box_max": hi.tolist()})
            if link == PALM_LINK:
                contacts += _palm_contacts(lo, hi)
    return {"root": PALM_LINK, "joints": joints, "contacts": contacts, "colliders": colliders}


def hand_kinematics_from_spec(spec_path: str | Path | None = None) -> dict[str, Any]:
    """The same dict from the kinematic spec JSON (``tools/specs/dexhand13_kinematics.json`` of a
    checkout; the USD file is generated from it)."""
    spec = load_spec(spec_path)
    joints = [
        {
            "name": j.name,
            "parent": j.parent,
            "child": j.child,
            "xyz": list(j.xyz),
            "rot": rpy_matrix(j.rpy).tolist(),
            "axis": [0.0, 0.0, 1.0],
            "lower": j.lower,
            "upper": j.upper,
        }
        for j in (spec.joint(n) for n in FINGER_JOINT_NAMES)
    ]
    contacts, colliders = [], []
    for pad in PAD_NAMES:
        pj = spec.pad(pad)
        frame = np.eye(4)
        frame[:3, :3], frame[:3, 3] = rpy_matrix(pj.rpy), pj.xyz
        box = spec.links[pad]
        xyz, normal = _pad_contact(frame, np.asarray(box.box_min, float), np.asarray(box.box_max, float))
        contacts.append({"name": pad, "link": pj.parent, "xyz": xyz.tolist(), "normal": normal.tolist()})
    for link in LINK_NAMES:
        if _with_collider(link):
            box = spec.links[link]
            colliders.append({"link": link, "box_min": list(box.box_min), "box_max": list(box.box_max)})
            if link == PALM_LINK:
                contacts += _palm_contacts(np.asarray(box.box_min, float), np.asarray(box.box_max, float))
    return {"root": PALM_LINK, "joints": joints, "contacts": contacts, "colliders": colliders}


@functools.lru_cache(maxsize=4)
def hand_layout(usd_path: str | None = None) -> HandLayout:
    """The DexHand13's :class:`HandLayout` from its USD file (cached)."""
    return HandLayout.from_dict(hand_kinematics_from_usd(usd_path))


def contact_weights(layout: HandLayout, grasp_type: str) -> np.ndarray:
    """Weight per contact of the layout (the type's :data:`CONTACT_SETS`, 0 for the others)."""
    if grasp_type not in CONTACT_SETS:
        raise ValueError(f"unknown grasp type {grasp_type!r}; known: {sorted(CONTACT_SETS)}")
    chosen = CONTACT_SETS[grasp_type]
    return np.array([float(chosen.get(name, 0.0)) for name in layout.contact_names])


# --------------------------------------------------------------------------------------------
# Starts, descent, results.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SynthesisedGrasp:
    """A grasp found by descent, in the object frame (origin at its centre, z up)."""

    grasp: str
    palm_pos: np.ndarray  # (3,)
    palm_quat: np.ndarray  # (4,) x, y, z, w
    joint_q: np.ndarray  # (16,) rad, in FINGER_JOINT_NAMES order
    energy: float
    terms: dict[str, float]  # by TERM_NAMES, unweighted
    contact_gap: np.ndarray  # (contacts of the type,) signed distance of each chosen contact (m)

    def to_object_grasp(self) -> ObjectGrasp:
        """As the planner's grasp (approach along the palm normal, pre-shape = the abduction joints).
        The flexion joints are not part of an ``ObjectGrasp``: the closing controller finds them."""
        r = quat_xyzw_to_matrix(self.palm_quat)
        preshape = tuple(float(self.joint_q[j]) for j in ABDUCTION_JOINTS)
        return ObjectGrasp(
            self.grasp, self.palm_pos.copy(), self.palm_quat.copy(), r[:, 2].copy(), True, preshape
        )


def object_shape(
    object_kind: str, size: Any, mesh: tuple[np.ndarray, np.ndarray] | None = None, table: bool = True
) -> tuple[ObjectShape, np.ndarray]:
    """The object of :func:`synthesise` and its bounding-box extents (m)."""
    if object_kind == "mesh":
        if mesh is None:
            raise ValueError("object_kind 'mesh' needs mesh=(points, faces)")
        pts = np.asarray(mesh[0], dtype=np.float64)
        extents = pts.max(axis=0) - pts.min(axis=0)
        floor = float(pts[:, 2].min()) - DROP_GAP if table else None
        return ObjectShape.from_mesh(pts, mesh[1], floor_z=floor), extents
    extents = np.broadcast_to(np.asarray(size, dtype=np.float64), (3,)).copy()
    floor = -0.5 * float(extents[2]) - DROP_GAP if table else None
    if object_kind == "sphere":
        if not np.allclose(extents, extents[0]):
            raise ValueError("a sphere's size is its diameter (one number)")
        return ObjectShape.sphere(0.5 * float(extents[0]), floor_z=floor), extents
    if object_kind == "box":
        return ObjectShape.box(0.5 * extents, floor_z=floor), extents
    raise ValueError(f"object_kind must be 'box', 'sphere' or 'mesh', got {object_kind!r}")


def initial_params(
    layout: HandLayout, grasp_type: str, extents: np.ndarray, starts: int, rng: np.random.Generator
) -> np.ndarray:
    """``starts`` parameter rows around the type's geometric placement (module docstring): turned
    about z (any angle for a round object, else the placement or its half turn), 5 mm and ~6°
    jitter, abduction within ±0.1 rad, flexion 0.2-0.7 rad, the thumb swung 0.6-1.2 rad."""
    ex = np.asarray(extents, dtype=np.float64)
    nominal = object_grasp(grasp_type, ex, rest_height(ex))
    r0 = quat_xyzw_to_matrix(nominal.palm_quat)
    round_object = abs(float(ex[0] - ex[1])) < 1e-6
    out = np.zeros((starts, layout.num_params))
    for s in range(starts):
        yaw = float(rng.uniform(0.0, 2.0 * math.pi)) if round_object else float(rng.choice([0.0, math.pi]))
        yaw += float(rng.normal(0.0, 0.1))
        tilt = rng.normal(0.0, 0.1, size=3)
        angle = float(np.linalg.norm(tilt))
        k = tilt / max(angle, 1e-12)
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        r_tilt = np.eye(3) + math.sin(angle) * kx + (1.0 - math.cos(angle)) * kx @ kx
        rz = rot_z(yaw)
        out[s, :3] = rz @ nominal.palm_pos + rng.normal(0.0, 0.005, size=3)
        out[s, 3:POSE_PARAMS] = matrix_to_quat_xyzw_nonneg_w(rz @ r_tilt @ r0)
        q = rng.uniform(0.2, 0.7, size=layout.num_joints)
        q[list(ABDUCTION_JOINTS)] = rng.uniform(-0.1, 0.1, size=len(ABDUCTION_JOINTS))
        q[ABDUCTION_JOINTS[3] + 1] = rng.uniform(0.6, 1.2)  # the thumb's swing under the palm
        out[s, POSE_PARAMS:] = q
    return out


def synthesise(
    object_kind: str,
    size: Any,
    grasp_type: str,
    starts: int = 64,
    steps: int = 500,
    seed: int = 0,
    keep: int = 8,
    mesh: tuple[np.ndarray, np.ndarray] | None = None,
    table: bool = True,
    weights: EnergyWeights | None = None,
) -> list[SynthesisedGrasp]:
    """The ``keep`` lowest-energy grasps of ``grasp_type`` found from ``starts`` starts in ``steps``
    Adam steps, best first.

    ``size``: the object's bounding-box extents (m; a box's side lengths, one number for a cube or a
    sphere's diameter); ``object_kind`` ``"mesh"`` takes ``mesh=(points, faces)`` instead, in the
    object frame. ``table``: the object stands on a table (hand points below it are penetration)."""
    if grasp_type not in CONTACT_SETS:
        raise ValueError(f"unknown grasp type {grasp_type!r}; known: {sorted(CONTACT_SETS)}")
    layout = hand_layout()
    obj, extents = object_shape(object_kind, size, mesh, table)
    rng = np.random.default_rng(seed)
    x0 = initial_params(layout, grasp_type, extents, starts, rng)
    weight = contact_weights(layout, grasp_type)
    result = descend(layout, x0, obj, weight, weights, steps=steps)
    chosen = np.flatnonzero(weight > 0.0)
    order = np.argsort(result.terms["energy"], kind="stable")[:keep]
    out = []
    for i in order:
        x = result.params[i]
        out.append(
            SynthesisedGrasp(
                grasp=grasp_type,
                palm_pos=x[:3].copy(),
                palm_quat=x[3:POSE_PARAMS].copy(),
                joint_q=x[POSE_PARAMS:].copy(),
                energy=float(result.terms["energy"][i]),
                terms={name: float(result.terms[name][i]) for name in TERM_NAMES},
                contact_gap=result.terms["sd"][i, chosen].copy(),
            )
        )
    return out
