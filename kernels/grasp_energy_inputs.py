"""What the grasp energy reads: the hand's layout, the object's shape and the terms' weights.

:class:`HandLayout` is the hand as arrays (a tree of revolute joints, contact points with outward
normals and penetration samples), built from a plain dict (:meth:`HandLayout.from_dict`; the planner,
``d3grasp.planner.synthesis``, makes that dict from the hand's USD file), so this module imports
nothing of the d3grasp package. :class:`ObjectShape` is the object's signed distance (sphere, box or
closed triangle mesh) and :class:`EnergyWeights` the weights of the energy's terms and the friction
coefficient. The energy itself (its equations and Warp kernels) is :mod:`d3grasp.kernels.grasp_energy`,
its float64 NumPy twin :mod:`d3grasp.kernels.grasp_energy_reference`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

__all__ = [
    "POSE_PARAMS",
    "TERM_NAMES",
    "EnergyWeights",
    "HandLayout",
    "ObjectShape",
    "contact_weight_rows",
    "matrix_to_quat_xyzw",
]

POSE_PARAMS = 7
"""Parameters of the palm pose at the start of each row: position (3), quaternion x, y, z, w (4)."""

TERM_NAMES: tuple[str, ...] = ("fc", "cone", "dist", "pen", "joint")
"""The energy's terms, in the order of :class:`EnergyWeights` and of the ``terms`` arrays."""

OBJECT_SPHERE = 0
OBJECT_BOX = 1
OBJECT_MESH = 2
# Object kinds as the kernels number them (grasp_energy._object_sdf branches on these values).
_OBJECT_KINDS = {"sphere": OBJECT_SPHERE, "box": OBJECT_BOX, "mesh": OBJECT_MESH}


# --------------------------------------------------------------------------------------------
# Layout of the hand: kinematic tree, contact points, penetration samples.
# --------------------------------------------------------------------------------------------


def _as_rotation(value: Any) -> np.ndarray:
    r = np.asarray(value, dtype=np.float64)
    if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0.0:
        raise ValueError(f"expected a 3x3 rotation matrix, got {value!r}")
    return r


def matrix_to_quat_xyzw(r: np.ndarray) -> np.ndarray:
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
    units (:mod:`d3grasp.kernels.grasp_energy`); ``floor_z`` is the table's height in the object
    frame (hand points below it count as penetration; ``None``: no table)."""

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
    """Weights of the terms (:mod:`d3grasp.kernels.grasp_energy`) and the friction coefficient of the cone.

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
# Contact weights.
# --------------------------------------------------------------------------------------------


def contact_weight_rows(contact_weight: Any, num_grasps: int, num_contacts: int) -> np.ndarray:
    """The contact weights as one row per grasp (n, C): a single row (C,) is shared by every grasp."""
    w = np.asarray(contact_weight, dtype=np.float64)
    if w.ndim == 1:
        w = np.broadcast_to(w, (num_grasps, w.shape[0]))
    if w.shape != (num_grasps, num_contacts):
        raise ValueError(
            f"contact weights must be ({num_contacts},) or ({num_grasps}, {num_contacts}), got {w.shape}"
        )
    return np.ascontiguousarray(w)
