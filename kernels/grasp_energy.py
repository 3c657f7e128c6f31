"""A differentiable grasp energy over the hand's kinematics, for many grasps at once (grasp synthesis).

A grasp is one row of parameters ``x = (p, q, theta)``: the palm position ``p`` (3, object frame, m),
the palm orientation as a quaternion ``q`` (4, ``x, y, z, w``; normalised inside the energy, so any
non-zero row is a rotation) and the joint angles ``theta`` (``J``, rad). Forward kinematics
(:class:`HandLayout`, revolute joints, URDF convention ``child = parent · origin · Rot(axis, theta)``)
places the hand's points in the object frame:

* contact points ``x_i`` with outward normals ``n_i`` (the tactile pads' outer face centres and
  points on the palm's palmar face; ``n_i`` points from the hand towards the object, so a pad pushes
  the object along ``+n_i``);
* penetration samples (grids over the link colliders) which only keep the hand out of the object.

The object is a signed distance ``d(x)`` with outward unit normal ``m(x)`` (sphere, box, or a closed
triangle mesh through ``wp.mesh_query_point_sign_normal``), in its own frame (origin at its centre).

Energy of one grasp (``w_i`` in [0, 1] the per-grasp contact selection, e.g. index tip and thumb tip
for a pinch)::

    E = w_fc E_fc + w_cone E_cone + w_dist E_dist + w_pen E_pen + w_joint E_joint

    E_fc    = || sum_i w_i n_i ||^2 + || sum_i w_i (x_i × n_i) / L ||^2        (= || G c ||^2)
    E_cone  = sum_i w_i max(0, cos(atan mu) + n_i · m(x_i))^2
    E_dist  = sum_i w_i |d(x_i)|
    E_pen   = sum_k max(0, -d(y_k)) + max(0, z_floor - y_k.z)       (y_k: every contact and sample)
    E_joint = sum_j max(0, theta_j - upper_j)^2 + max(0, lower_j - theta_j)^2

``E_fc`` is the force-closure relaxation of DexGraspNet (R. Wang et al., "DexGraspNet: A Large-Scale
Robotic Dexterous Grasp Dataset for General Objects Based on Simulation", ICRA 2023, Eq. 3, after
H. Dai et al., "Synthesis and optimization of force closure grasps via sequential semidefinite
programming", ISRR 2015/2018): ``|| G c ||^2`` with the grasp matrix ``G = [I ... I; [x_1]× ... [x_k]×]``
(6 × 3k) and ``c`` the stacked unit contact forces. Unit forces that sum to a zero wrench with every
force strictly inside its friction cone make the grasp force-closed (Dai et al.), so ``E_fc = 0``
together with ``E_cone = 0`` is the target. Two choices of ours: the contact force directions are the
hand's contact normals ``n_i`` (what a pad can push along), and ``E_cone`` keeps each ``n_i`` inside
the friction cone (half-angle ``atan mu``) of the surface's inward normal ``-m(x_i)`` -- the
friction-cone relaxation; DexGraspNet puts the object normal in ``c`` instead, which has no gradient
on a flat face. Torques are about the object origin and divided by a length ``L`` of the object (its
radius, or the mean half extent of its box), so the force and torque residuals are both
dimensionless and weigh the same for a 4 cm and a 20 cm object (DexGraspNet uses metres directly).
``E_dist`` and ``E_pen`` are DexGraspNet's distance and penetration terms (here the hand's points
are tested against the object's signed distance, plus an optional floor, the table under the
object); ``E_joint`` is a squared limit violation (DexGraspNet's is linear; squared keeps the
gradient continuous at the limit).

Kernels (float32, one thread per grasp and item, reductions by atomics, so the whole chain supports
``wp.Tape``): the palm pose, one launch per depth of the kinematic tree (a joint reads its parent
link written by the previous launch), the points' terms, the joint limits and the total.
:class:`GraspEnergy` holds the buffers for ``n`` grasps and returns energies and gradients;
:func:`descend` runs Adam on many starts at once. :func:`reference_energy` is a float64 NumPy twin
written from the equations above (rotation matrices and Rodrigues' formula, no Warp), for the tests.

This module imports nothing of the d3grasp package: the hand comes in as a plain dict
(:meth:`HandLayout.from_dict`, built by ``d3grasp.planner.synthesis`` from the hand's USD file).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import warp as wp

__all__ = [
    "POSE_PARAMS",
    "TERM_NAMES",
    "DescentResult",
    "EnergyWeights",
    "GraspEnergy",
    "HandLayout",
    "ObjectShape",
    "descend",
    "reference_energy",
    "reference_points",
]

POSE_PARAMS = 7
"""Parameters of the palm pose at the start of each row: position (3), quaternion x, y, z, w (4)."""

TERM_NAMES: tuple[str, ...] = ("fc", "cone", "dist", "pen", "joint")
"""The energy's terms, in the order of :class:`EnergyWeights` and of the ``terms`` arrays."""

OBJECT_SPHERE = 0
OBJECT_BOX = 1
OBJECT_MESH = 2
_OBJECT_KINDS = {"sphere": OBJECT_SPHERE, "box": OBJECT_BOX, "mesh": OBJECT_MESH}

_MESH_MAX_DIST = 10.0  # m: a mesh query farther than this finds nothing (no hand point is that far)


# --------------------------------------------------------------------------------------------
# Layout of the hand: kinematic tree, contact points, penetration samples.
# --------------------------------------------------------------------------------------------


def _as_rotation(value: Any) -> np.ndarray:
    r = np.asarray(value, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0.0:
        raise ValueError(f"expected a 3x3 rotation matrix, got {value!r}")
    return r


def _matrix_to_quat_xyzw(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (the largest of the four pivots)."""
    t = np.trace(r)
    pivots = (t, r[0, 0], r[1, 1], r[2, 2])
    k = int(np.argmax(pivots))
    if k == 0:
        s = 2.0 * math.sqrt(1.0 + t)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif k == 1:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif k == 2:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def _box_grid(box_min: np.ndarray, box_max: np.ndarray, per_axis: int) -> np.ndarray:
    axes = [np.linspace(box_min[a], box_max[a], per_axis) for a in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)


@dataclass(frozen=True)
class HandLayout:
    """The hand as arrays: a tree of revolute joints, contact points and penetration samples.

    Links are numbered ``0`` (the root, the palm) and ``1 + j`` (the child link of joint ``j``); the
    joints are in the order of the joint angles in a parameter row. Points are the contacts first
    (``num_contacts`` of them, with outward normals), then the penetration samples (zero normals).
    Build it with :meth:`from_dict`.
    """

    joint_names: tuple[str, ...]
    joint_parent: np.ndarray  # (J,) int: link index of each joint's parent
    joint_origin_pos: np.ndarray  # (J, 3) joint frame's origin in the parent link frame
    joint_origin_rot: np.ndarray  # (J, 3, 3) joint frame's rotation in the parent link frame
    joint_axis: np.ndarray  # (J, 3) unit axis in the joint frame
    joint_lower: np.ndarray  # (J,) rad
    joint_upper: np.ndarray  # (J,) rad
    joint_levels: tuple[tuple[int, ...], ...]  # joints grouped by depth in the tree, root first
    contact_names: tuple[str, ...]
    point_link: np.ndarray  # (P,) int: link of each point
    point_pos: np.ndarray  # (P, 3) in its link's frame
    point_normal: np.ndarray  # (P, 3) outward unit normal of a contact in its link's frame; 0 for samples

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_links(self) -> int:
        return 1 + self.num_joints

    @property
    def num_contacts(self) -> int:
        return len(self.contact_names)

    @property
    def num_points(self) -> int:
        return len(self.point_link)

    @property
    def num_params(self) -> int:
        return POSE_PARAMS + self.num_joints

    def contact_index(self, name: str) -> int:
        return self.contact_names.index(name)

    @classmethod
    def from_dict(
        cls, d: dict[str, Any], samples_per_axis: int = 3, pad_clearance: float = 0.001
    ) -> HandLayout:
        """The layout of a hand described by ``d``:

        * ``root``: the root link's name;
        * ``joints``: list of ``{name, parent, child, xyz, rot, axis, lower, upper}`` in the order of
          the joint angles (``rot`` a 3x3 rotation matrix: the joint frame in the parent link frame,
          ``axis`` in the joint frame, limits in rad);
        * ``contacts``: list of ``{name, link, xyz, normal}`` (a point and outward normal in the
          link's frame);
        * ``colliders``: list of ``{link, box_min, box_max}`` (boxes in the link's frame).

        Each collider box gets a ``samples_per_axis``³ grid of penetration samples. A sample is
        dropped if it lies less than ``pad_clearance`` behind the plane of a contact on the same link
        (the collider boxes are the links' bounding boxes and stick out past the pads a little in
        places; such samples would fight the distance term where a pad touches the object).
        """
        root = str(d["root"])
        joints = list(d["joints"])
        link_index = {root: 0}
        for j, jd in enumerate(joints):
            if jd["child"] in link_index:
                raise ValueError(f"link {jd['child']!r} is the child of two joints")
            link_index[jd["child"]] = 1 + j
        parent = np.array([link_index.get(jd["parent"], -1) for jd in joints], dtype=np.int32)
        if np.any(parent < 0):
            missing = [jd["parent"] for jd, p in zip(joints, parent, strict=True) if p < 0]
            raise ValueError(f"joints with unknown parent links: {missing}")
        depth = np.zeros(len(joints), dtype=np.int64)
        for _ in range(len(joints)):  # depth = 1 + the parent joint's depth (root children: 0)
            for j in range(len(joints)):
                depth[j] = 0 if parent[j] == 0 else depth[parent[j] - 1] + 1
        if len(joints) and int(depth.max()) >= len(joints):
            raise ValueError("the joints do not form a tree")
        levels = tuple(
            tuple(int(j) for j in np.flatnonzero(depth == k))
            for k in range(int(depth.max()) + 1 if joints else 0)
        )
        axis = np.array([np.asarray(jd["axis"], dtype=np.float64) for jd in joints]).reshape(-1, 3)
        if len(axis) and not np.allclose(np.linalg.norm(axis, axis=1), 1.0, atol=1e-6):
            raise ValueError("joint axes must be unit vectors")
        lower = np.array([float(jd["lower"]) for jd in joints])
        upper = np.array([float(jd["upper"]) for jd in joints])
        if np.any(lower > upper):
            raise ValueError("a joint's lower limit is above its upper limit")

        contacts = list(d.get("contacts", ()))
        if not contacts:
            raise ValueError("a hand layout needs at least one contact point")
        c_link = np.array([link_index[c["link"]] for c in contacts], dtype=np.int32)
        c_pos = np.array([np.asarray(c["xyz"], dtype=np.float64) for c in contacts])
        c_nrm = np.array([np.asarray(c["normal"], dtype=np.float64) for c in contacts])
        c_nrm /= np.linalg.norm(c_nrm, axis=1, keepdims=True)

        s_link: list[int] = []
        s_pos: list[np.ndarray] = []
        for box in d.get("colliders", ()):
            link = link_index[box["link"]]
            grid = _box_grid(
                np.asarray(box["box_min"], float), np.asarray(box["box_max"], float), samples_per_axis
            )
            on_link = c_link == link
            if np.any(on_link):
                # signed height of each sample over each same-link contact's plane, along its normal
                height = np.einsum("skc,kc->sk", grid[:, None, :] - c_pos[None, on_link], c_nrm[on_link])
                grid = grid[np.all(height < -pad_clearance, axis=1)]
            s_link += [link] * len(grid)
            s_pos.append(grid)
        samples = np.concatenate(s_pos) if s_pos else np.zeros((0, 3))
        return cls(
            joint_names=tuple(str(jd["name"]) for jd in joints),
            joint_parent=parent,
            joint_origin_pos=np.array([np.asarray(jd["xyz"], dtype=np.float64) for jd in joints]).reshape(
                -1, 3
            ),
            joint_origin_rot=np.array([_as_rotation(jd["rot"]) for jd in joints]).reshape(-1, 3, 3),
            joint_axis=axis,
            joint_lower=lower,
            joint_upper=upper,
            joint_levels=levels,
            contact_names=tuple(str(c["name"]) for c in contacts),
            point_link=np.concatenate([c_link, np.asarray(s_link, dtype=np.int32)]).astype(np.int32),
            point_pos=np.concatenate([c_pos, samples]),
            point_normal=np.concatenate([c_nrm, np.zeros_like(samples)]),
        )


# --------------------------------------------------------------------------------------------
# The object.
# --------------------------------------------------------------------------------------------


@dataclass
class ObjectShape:
    """The object's signed distance, in its own frame: ``kind`` ``"sphere"`` (``size[0]`` the radius),
    ``"box"`` (``size`` the half extents) or ``"mesh"`` (a closed, consistently wound triangle mesh;
    ``size`` its bounding box's half extents). ``torque_length`` (m) scales torques to the forces'
    units (module docstring); ``floor_z`` is the table's height in the object frame (hand points
    below it count as penetration; ``None``: no table)."""

    kind: str
    size: tuple[float, float, float]
    torque_length: float
    floor_z: float | None = None
    mesh: wp.Mesh | None = None
    mesh_points: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in _OBJECT_KINDS:
            raise ValueError(f"object kind must be one of {sorted(_OBJECT_KINDS)}, got {self.kind!r}")
        if self.kind == "mesh" and self.mesh is None:
            raise ValueError("a mesh object needs its wp.Mesh (ObjectShape.from_mesh)")
        if not self.torque_length > 0.0:
            raise ValueError("torque_length must be positive")

    @property
    def kind_id(self) -> int:
        return _OBJECT_KINDS[self.kind]

    @property
    def mesh_id(self) -> int:
        return int(self.mesh.id) if self.mesh is not None else 0

    @classmethod
    def sphere(cls, radius: float, floor_z: float | None = None) -> ObjectShape:
        return cls("sphere", (float(radius), 0.0, 0.0), float(radius), floor_z)

    @classmethod
    def box(cls, half_extents: Any, floor_z: float | None = None) -> ObjectShape:
        h = tuple(float(v) for v in np.broadcast_to(np.asarray(half_extents, dtype=np.float64), (3,)))
        return cls("box", h, float(np.mean(h)), floor_z)

    @classmethod
    def from_mesh(
        cls, points: np.ndarray, faces: np.ndarray, floor_z: float | None = None, device: Any = None
    ) -> ObjectShape:
        """A closed triangle mesh (``points`` (V, 3) in the object frame, ``faces`` (F, 3), outward
        counter-clockwise winding)."""
        pts = np.asarray(points, dtype=np.float64)
        tri = np.asarray(faces, dtype=np.int32).reshape(-1, 3)
        mesh = wp.Mesh(
            points=wp.array(pts.astype(np.float32), dtype=wp.vec3, device=device),
            indices=wp.array(tri.ravel(), dtype=wp.int32, device=device),
        )
        half = 0.5 * (pts.max(axis=0) - pts.min(axis=0))
        return cls("mesh", tuple(float(v) for v in half), float(np.mean(half)), floor_z, mesh, pts, tri)


@dataclass(frozen=True)
class EnergyWeights:
    """Weights of the terms (module docstring) and the friction coefficient of the cone.

    Distances are in metres: ``dist`` 100 /m makes 1 cm of gap per contact cost as much as a unit
    force residual (DexGraspNet's weight); ``pen`` 300 /m per point makes a link sunk 3 mm into the
    object cost about as much. ``mu`` 0.5 is a margin under the simulated hand's friction of 1.0."""

    fc: float = 1.0
    cone: float = 1.0
    dist: float = 100.0
    pen: float = 300.0
    joint: float = 10.0
    mu: float = 0.5

    def as_tuple(self) -> tuple[float, float, float, float, float]:
        return (self.fc, self.cone, self.dist, self.pen, self.joint)


# --------------------------------------------------------------------------------------------
# Warp functions and kernels.
# --------------------------------------------------------------------------------------------


@wp.func
def _sign_nonneg(x: float) -> float:
    if x >= 0.0:
        return 1.0
    return -1.0


@wp.func
def _sphere_sdf(p: wp.vec3, radius: float) -> wp.vec4:
    """Outward normal (xyz) and signed distance (w) of a sphere at the origin."""
    r = wp.length(p)
    if r < 1.0e-9:
        return wp.vec4(0.0, 0.0, 1.0, -radius)
    n = p / r
    return wp.vec4(n[0], n[1], n[2], r - radius)


@wp.func
def _box_sdf(p: wp.vec3, half: wp.vec3) -> wp.vec4:
    """Outward normal (xyz) and signed distance (w) of an axis-aligned box centred at the origin.

    Outside: distance to the closest point of the box, normal from it to ``p``. Inside: the nearest
    face's (negative) distance and that face's normal."""
    sx = _sign_nonneg(p[0])
    sy = _sign_nonneg(p[1])
    sz = _sign_nonneg(p[2])
    qx = wp.abs(p[0]) - half[0]
    qy = wp.abs(p[1]) - half[1]
    qz = wp.abs(p[2]) - half[2]
    q_max = wp.max(qx, wp.max(qy, qz))
    if q_max > 0.0:
        o = wp.vec3(sx * wp.max(qx, 0.0), sy * wp.max(qy, 0.0), sz * wp.max(qz, 0.0))
        d = wp.length(o)
        n = o / d
        return wp.vec4(n[0], n[1], n[2], d)
    if qx >= qy and qx >= qz:
        return wp.vec4(sx, 0.0, 0.0, qx)
    if qy >= qz:
        return wp.vec4(0.0, sy, 0.0, qy)
    return wp.vec4(0.0, 0.0, sz, qz)


@wp.func
def _mesh_sdf(p: wp.vec3, mesh: wp.uint64) -> wp.vec4:
    """Outward normal (xyz) and signed distance (w) of a closed triangle mesh (pseudo-normal sign)."""
    hit = wp.mesh_query_point_sign_normal(mesh, p, _MESH_MAX_DIST)
    if not hit.result:
        return wp.vec4(0.0, 0.0, 1.0, _MESH_MAX_DIST)
    closest = wp.mesh_eval_position(mesh, hit.face, hit.u, hit.v)
    delta = p - closest
    d = wp.length(delta)
    if d < 1.0e-7:
        n = wp.mesh_eval_face_normal(mesh, hit.face)
        return wp.vec4(n[0], n[1], n[2], 0.0)
    n = hit.sign * delta / d
    return wp.vec4(n[0], n[1], n[2], hit.sign * d)


@wp.func
def _object_sdf(p: wp.vec3, kind: int, size: wp.vec3, mesh: wp.uint64) -> wp.vec4:
    if kind == 0:
        return _sphere_sdf(p, size[0])
    if kind == 1:
        return _box_sdf(p, size)
    return _mesh_sdf(p, mesh)


@wp.kernel
def _palm_kernel(params: wp.array2d(dtype=float), link_xf: wp.array2d(dtype=wp.transform)):
    g = wp.tid()
    pos = wp.vec3(params[g, 0], params[g, 1], params[g, 2])
    rot = wp.normalize(wp.quat(params[g, 3], params[g, 4], params[g, 5], params[g, 6]))
    link_xf[g, 0] = wp.transform(pos, rot)


@wp.kernel
def _joint_level_kernel(
    params: wp.array2d(dtype=float),
    level_joints: wp.array(dtype=wp.int32),
    joint_parent: wp.array(dtype=wp.int32),
    joint_origin: wp.array(dtype=wp.transform),
    joint_axis: wp.array(dtype=wp.vec3),
    link_xf: wp.array2d(dtype=wp.transform),
):
    # One depth of the tree: every parent link was written by the previous launch.
    g, i = wp.tid()
    j = level_joints[i]
    angle = params[g, 7 + j]
    turn = wp.transform(wp.vec3(0.0, 0.0, 0.0), wp.quat_from_axis_angle(joint_axis[j], angle))
    link_xf[g, 1 + j] = wp.transform_multiply(
        wp.transform_multiply(link_xf[g, joint_parent[j]], joint_origin[j]), turn
    )


@wp.kernel
def _point_terms_kernel(
    link_xf: wp.array2d(dtype=wp.transform),
    point_link: wp.array(dtype=wp.int32),
    point_pos: wp.array(dtype=wp.vec3),
    point_normal: wp.array(dtype=wp.vec3),
    num_contacts: int,
    contact_weight: wp.array2d(dtype=float),
    object_kind: int,
    object_size: wp.vec3,
    object_mesh: wp.uint64,
    floor_z: float,
    inv_torque_length: float,
    cos_cone: float,
    out_pos: wp.array2d(dtype=wp.vec3),
    out_normal: wp.array2d(dtype=wp.vec3),
    out_sd: wp.array2d(dtype=float),
    e_dist: wp.array(dtype=float),
    e_pen: wp.array(dtype=float),
    e_cone: wp.array(dtype=float),
    force: wp.array(dtype=wp.vec3),
    torque: wp.array(dtype=wp.vec3),
):
    g, k = wp.tid()
    xf = link_xf[g, point_link[k]]
    x = wp.transform_point(xf, point_pos[k])
    n = wp.transform_vector(xf, point_normal[k])
    surf = _object_sdf(x, object_kind, object_size, object_mesh)
    sd = surf[3]
    out_pos[g, k] = x
    out_normal[g, k] = n
    out_sd[g, k] = sd
    wp.atomic_add(e_pen, g, wp.max(-sd, 0.0) + wp.max(floor_z - x[2], 0.0))
    if k < num_contacts:
        w = contact_weight[g, k]
        if w > 0.0:
            wp.atomic_add(e_dist, g, w * wp.abs(sd))
            # n must lie in the friction cone about the inward normal -m: -n·m >= cos(atan mu)
            gap = wp.max(cos_cone + wp.dot(n, wp.vec3(surf[0], surf[1], surf[2])), 0.0)
            wp.atomic_add(e_cone, g, w * gap * gap)
            wp.atomic_add(force, g, w * n)
            wp.atomic_add(torque, g, (w * inv_torque_length) * wp.cross(x, n))


@wp.kernel
def _joint_limit_kernel(
    params: wp.array2d(dtype=float),
    lower: wp.array(dtype=float),
    upper: wp.array(dtype=float),
    e_joint: wp.array(dtype=float),
):
    g, j = wp.tid()
    angle = params[g, 7 + j]
    above = wp.max(angle - upper[j], 0.0)
    below = wp.max(lower[j] - angle, 0.0)
    wp.atomic_add(e_joint, g, above * above + below * below)


@wp.kernel
def _total_kernel(
    force: wp.array(dtype=wp.vec3),
    torque: wp.array(dtype=wp.vec3),
    e_cone: wp.array(dtype=float),
    e_dist: wp.array(dtype=float),
    e_pen: wp.array(dtype=float),
    e_joint: wp.array(dtype=float),
    w_fc: float,
    w_cone: float,
    w_dist: float,
    w_pen: float,
    w_joint: float,
    e_fc: wp.array(dtype=float),
    energy: wp.array(dtype=float),
):
    g = wp.tid()
    f = force[g]
    t = torque[g]
    fc = wp.dot(f, f) + wp.dot(t, t)
    e_fc[g] = fc
    energy[g] = w_fc * fc + w_cone * e_cone[g] + w_dist * e_dist[g] + w_pen * e_pen[g] + w_joint * e_joint[g]


# --------------------------------------------------------------------------------------------
# Host side: buffers, energy and gradient, descent.
# --------------------------------------------------------------------------------------------


def _contact_weight_rows(contact_weight: Any, num_grasps: int, num_contacts: int) -> np.ndarray:
    w = np.asarray(contact_weight, dtype=np.float64)
    if w.ndim == 1:
        w = np.broadcast_to(w, (num_grasps, w.shape[0]))
    if w.shape != (num_grasps, num_contacts):
        raise ValueError(
            f"contact weights must be ({num_contacts},) or ({num_grasps}, {num_contacts}), got {w.shape}"
        )
    return np.ascontiguousarray(w)


class GraspEnergy:
    """Buffers and launches of the energy of ``num_grasps`` grasps of one hand on one object.

    :meth:`evaluate` returns the energies (and, with ``grad=True``, their gradients with respect to
    the parameter rows through ``wp.Tape``); :meth:`terms` reads every term of the last evaluation.
    """

    def __init__(
        self,
        layout: HandLayout,
        obj: ObjectShape,
        num_grasps: int,
        contact_weight: Any,
        weights: EnergyWeights | None = None,
        device: Any = None,
    ) -> None:
        self.layout = layout
        self.obj = obj
        self.weights = weights or EnergyWeights()
        self.num_grasps = int(num_grasps)
        self.device = wp.get_device(device)
        n, p, d = self.num_grasps, layout.num_points, self.device
        origins = np.concatenate(
            [
                layout.joint_origin_pos,
                np.array([_matrix_to_quat_xyzw(r) for r in layout.joint_origin_rot]).reshape(-1, 4),
            ],
            axis=1,
        )
        self._joint_origin = wp.array(origins.astype(np.float32), dtype=wp.transform, device=d)
        self._joint_axis = wp.array(layout.joint_axis.astype(np.float32), dtype=wp.vec3, device=d)
        self._joint_parent = wp.array(layout.joint_parent, dtype=wp.int32, device=d)
        self._levels = [
            wp.array(np.asarray(lv, dtype=np.int32), dtype=wp.int32, device=d) for lv in layout.joint_levels
        ]
        self._lower = wp.array(layout.joint_lower.astype(np.float32), dtype=float, device=d)
        self._upper = wp.array(layout.joint_upper.astype(np.float32), dtype=float, device=d)
        self._point_link = wp.array(layout.point_link, dtype=wp.int32, device=d)
        self._point_pos = wp.array(layout.point_pos.astype(np.float32), dtype=wp.vec3, device=d)
        self._point_normal = wp.array(layout.point_normal.astype(np.float32), dtype=wp.vec3, device=d)
        self._contact_weight = wp.zeros((n, layout.num_contacts), dtype=float, device=d)
        self.set_contact_weight(contact_weight)

        def buf(shape: Any, dtype: Any) -> wp.array:
            return wp.zeros(shape, dtype=dtype, device=d, requires_grad=True)

        self.params = buf((n, layout.num_params), float)
        self.link_xf = buf((n, layout.num_links), wp.transform)
        self.points = buf((n, p), wp.vec3)
        self.normals = buf((n, p), wp.vec3)
        self.sd = buf((n, p), float)
        self._e = {name: buf(n, float) for name in TERM_NAMES}
        self.force = buf(n, wp.vec3)
        self.torque = buf(n, wp.vec3)
        self.energy = buf(n, float)
        self._ones = wp.ones(n, dtype=float, device=d)

    def set_contact_weight(self, contact_weight: Any) -> None:
        """Which contacts take part (weight per contact, per grasp or one row for all)."""
        w = _contact_weight_rows(contact_weight, self.num_grasps, self.layout.num_contacts)
        self._contact_weight.assign(w.astype(np.float32))

    def _launch(self) -> None:
        n, lay, d, obj = self.num_grasps, self.layout, self.device, self.obj
        wp.launch(_palm_kernel, dim=n, inputs=[self.params], outputs=[self.link_xf], device=d)
        for level in self._levels:
            wp.launch(
                _joint_level_kernel,
                dim=(n, level.shape[0]),
                inputs=[self.params, level, self._joint_parent, self._joint_origin, self._joint_axis],
                outputs=[self.link_xf],
                device=d,
            )
        wp.launch(
            _point_terms_kernel,
            dim=(n, lay.num_points),
            inputs=[
                self.link_xf,
                self._point_link,
                self._point_pos,
                self._point_normal,
                lay.num_contacts,
                self._contact_weight,
                obj.kind_id,
                wp.vec3(*obj.size),
                wp.uint64(obj.mesh_id),
                float(obj.floor_z) if obj.floor_z is not None else -1.0e6,
                1.0 / obj.torque_length,
                1.0 / math.sqrt(1.0 + self.weights.mu**2),
            ],
            outputs=[
                self.points,
                self.normals,
                self.sd,
                self._e["dist"],
                self._e["pen"],
                self._e["cone"],
                self.force,
                self.torque,
            ],
            device=d,
        )
        if lay.num_joints:
            wp.launch(
                _joint_limit_kernel,
                dim=(n, lay.num_joints),
                inputs=[self.params, self._lower, self._upper],
                outputs=[self._e["joint"]],
                device=d,
            )
        w = self.weights
        wp.launch(
            _total_kernel,
            dim=n,
            inputs=[
                self.force,
                self.torque,
                self._e["cone"],
                self._e["dist"],
                self._e["pen"],
                self._e["joint"],
                w.fc,
                w.cone,
                w.dist,
                w.pen,
                w.joint,
            ],
            outputs=[self._e["fc"], self.energy],
            device=d,
        )

    def evaluate(self, params: np.ndarray, grad: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Energies (n,) of the parameter rows ``params`` (n, 7 + J); with ``grad`` also dE/dparams."""
        x = np.asarray(params, dtype=np.float32)
        if x.shape != (self.num_grasps, self.layout.num_params):
            raise ValueError(f"params must be ({self.num_grasps}, {self.layout.num_params}), got {x.shape}")
        self.params.assign(x)
        for a in (*self._e.values(), self.force, self.torque):
            a.zero_()
        if not grad:
            self._launch()
            return self.energy.numpy().astype(np.float64), None
        tape = wp.Tape()
        with tape:
            self._launch()
        tape.backward(grads={self.energy: self._ones})
        g = self.params.grad.numpy().astype(np.float64)
        tape.zero()
        return self.energy.numpy().astype(np.float64), g

    def terms(self) -> dict[str, np.ndarray]:
        """The last evaluation's terms (n,) by :data:`TERM_NAMES`, ``energy``, and per point
        ``points`` (n, P, 3), ``normals`` (n, P, 3) and ``sd`` (n, P)."""
        out = {name: a.numpy().astype(np.float64) for name, a in self._e.items()}
        out["energy"] = self.energy.numpy().astype(np.float64)
        out["points"] = self.points.numpy().astype(np.float64)
        out["normals"] = self.normals.numpy().astype(np.float64)
        out["sd"] = self.sd.numpy().astype(np.float64)
        return out


@dataclass
class DescentResult:
    """Final parameters (n, 7 + J) with unit quaternions, their terms, and the energy per step."""

    params: np.ndarray
    terms: dict[str, np.ndarray]
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (steps + 1, n)


def descend(
    layout: HandLayout,
    params0: np.ndarray,
    obj: ObjectShape,
    contact_weight: Any,
    weights: EnergyWeights | None = None,
    steps: int = 200,
    lr_position: float = 2.0e-3,
    lr_rotation: float = 2.0e-2,
    lr_joint: float = 3.0e-2,
    lr_final: float = 0.1,
    clamp_joints: bool = True,
    device: Any = None,
) -> DescentResult:
    """Adam (Kingma & Ba 2015, beta 0.9/0.999) on every row of ``params0`` at once.

    Learning rates are per group because the parameters have different units (m, quaternion
    components, rad): Adam's step is about ``lr`` per parameter, so ``lr_position`` 2 mm and
    ``lr_joint`` 0.03 rad move the hand by a few mm per step; the rates decay exponentially to
    ``lr_final`` times these by the last step, so the end is not an Adam jitter of that size (a pad
    gap of a few mm at a constant rate). After each step the quaternions are
    renormalised and, with ``clamp_joints``, the joint angles projected into their limits (then the
    limit term only matters for starts outside them)."""
    energy_fn = GraspEnergy(layout, obj, len(params0), contact_weight, weights, device)
    x = np.array(params0, dtype=np.float64)
    lr = np.full(layout.num_params, lr_joint)
    lr[:3] = lr_position
    lr[3:POSE_PARAMS] = lr_rotation
    m = np.zeros_like(x)
    v = np.zeros_like(x)
    beta1, beta2, eps = 0.9, 0.999, 1.0e-12
    history = []
    for step in range(1, steps + 1):
        e, g = energy_fn.evaluate(x, grad=True)
        history.append(e)
        g = np.nan_to_num(g)
        m = beta1 * m + (1.0 - beta1) * g
        v = beta2 * v + (1.0 - beta2) * g * g
        m_hat = m / (1.0 - beta1**step)
        v_hat = v / (1.0 - beta2**step)
        decay = lr_final ** ((step - 1) / max(steps - 1, 1))
        x -= (decay * lr) * m_hat / (np.sqrt(v_hat) + eps)
        x[:, 3:POSE_PARAMS] /= np.linalg.norm(x[:, 3:POSE_PARAMS], axis=1, keepdims=True)
        if clamp_joints:
            x[:, POSE_PARAMS:] = np.clip(x[:, POSE_PARAMS:], layout.joint_lower, layout.joint_upper)
    e, _ = energy_fn.evaluate(x)
    history.append(e)
    return DescentResult(params=x, terms=energy_fn.terms(), history=np.array(history))


# --------------------------------------------------------------------------------------------
# NumPy float64 twin (forward only), from the equations of the module docstring.
# --------------------------------------------------------------------------------------------


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotation matrices of (n, 4) quaternions (x, y, z, w), normalised first."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=1,
    )


def _rodrigues(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(n, 3, 3) rotations by ``angle`` (n,) about the unit ``axis`` (3,)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def reference_points(layout: HandLayout, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Object-frame positions and normals (n, P, 3) of the layout's points (float64 forward kinematics)."""
    x = np.asarray(params, dtype=np.float64)
    rot = [_quat_matrix(x[:, 3:POSE_PARAMS])] + [None] * layout.num_joints
    pos = [x[:, :3]] + [None] * layout.num_joints
    for level in layout.joint_levels:
        for j in level:
            pr, pp = rot[layout.joint_parent[j]], pos[layout.joint_parent[j]]
            r_joint = layout.joint_origin_rot[j] @ _rodrigues(layout.joint_axis[j], x[:, POSE_PARAMS + j])
            rot[1 + j] = pr @ r_joint
            pos[1 + j] = pp + pr @ layout.joint_origin_pos[j]
    rots, poss = np.stack(rot, axis=1), np.stack(pos, axis=1)  # (n, L, 3, 3), (n, L, 3)
    r_pt = rots[:, layout.point_link]
    points = np.einsum("npij,pj->npi", r_pt, layout.point_pos) + poss[:, layout.point_link]
    normals = np.einsum("npij,pj->npi", r_pt, layout.point_normal)
    return points, normals


def _reference_sdf(obj: ObjectShape, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (...,) and outward normal (..., 3) of a sphere or box (float64)."""
    if obj.kind == "sphere":
        r = np.linalg.norm(p, axis=-1)
        return r - obj.size[0], p / np.maximum(r, 1e-12)[..., None]
    if obj.kind != "box":
        raise NotImplementedError("the NumPy twin covers the sphere and the box")
    half = np.asarray(obj.size)
    sign = np.where(p >= 0.0, 1.0, -1.0)
    q = np.abs(p) - half
    outside = np.maximum(q, 0.0)
    out_d = np.linalg.norm(outside, axis=-1)
    in_axis = np.argmax(q, axis=-1)  # the nearest face inside (first of equals, as the kernel)
    in_d = np.take_along_axis(q, in_axis[..., None], axis=-1)[..., 0]
    in_n = np.eye(3)[in_axis] * sign
    is_out = q.max(axis=-1) > 0.0
    sd = np.where(is_out, out_d, in_d)
    n = np.where(is_out[..., None], sign * outside / np.maximum(out_d, 1e-12)[..., None], in_n)
    return sd, n


def reference_energy(
    layout: HandLayout,
    params: np.ndarray,
    obj: ObjectShape,
    contact_weight: Any,
    weights: EnergyWeights | None = None,
) -> dict[str, np.ndarray]:
    """The energy and its terms (n,) in float64, by :data:`TERM_NAMES` and ``energy`` (sphere and box)."""
    w = weights or EnergyWeights()
    x = np.asarray(params, dtype=np.float64)
    n = x.shape[0]
    cw = _contact_weight_rows(contact_weight, n, layout.num_contacts)
    points, normals = reference_points(layout, x)
    sd, m = _reference_sdf(obj, points)
    floor = obj.floor_z if obj.floor_z is not None else -1.0e6
    pen = np.sum(np.maximum(-sd, 0.0) + np.maximum(floor - points[..., 2], 0.0), axis=1)
    c = layout.num_contacts
    active = cw > 0.0
    cw = np.where(active, cw, 0.0)
    dist = np.sum(cw * np.abs(sd[:, :c]), axis=1)
    cos_cone = 1.0 / math.sqrt(1.0 + w.mu**2)
    alignment = -np.sum(normals[:, :c] * m[:, :c], axis=-1)
    cone = np.sum(cw * np.maximum(cos_cone - alignment, 0.0) ** 2, axis=1)
    force = np.einsum("nc,nci->ni", cw, normals[:, :c])
    torque = np.einsum("nc,nci->ni", cw, np.cross(points[:, :c], normals[:, :c])) / obj.torque_length
    fc = np.sum(force**2, axis=1) + np.sum(torque**2, axis=1)
    q = x[:, POSE_PARAMS:]
    joint = np.sum(
        np.maximum(q - layout.joint_upper, 0.0) ** 2 + np.maximum(layout.joint_lower - q, 0.0) ** 2, axis=1
    )
    terms = {"fc": fc, "cone": cone, "dist": dist, "pen": pen, "joint": joint}
    terms["energy"] = sum(wt * terms[name] for wt, name in zip(w.as_tuple(), TERM_NAMES, strict=True))
    return terms
