"""A differentiable grasp energy over the hand's kinematics, for many grasps at once (grasp synthesis).

A grasp is one row of parameters ``x = (p, q, theta)``: the palm position ``p`` (3, object frame, m),
the palm orientation as a quaternion ``q`` (4, ``x, y, z, w``; normalised inside the energy, so any
non-zero row is a rotation) and the joint angles ``theta`` (``J``, rad). Forward kinematics
(:class:`~d3grasp.kernels.grasp_energy_inputs.HandLayout`, revolute joints, URDF convention
``child = parent · origin · Rot(axis, theta)``) places the hand's points in the object frame:

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
:class:`GraspEnergy` holds the buffers for ``n`` grasps and returns energies and gradients.

Around it: :mod:`d3grasp.kernels.grasp_energy_inputs` (the hand's layout, the object's shape, the
weights), :mod:`d3grasp.kernels.grasp_descent` (Adam on many starts at once) and
:mod:`d3grasp.kernels.grasp_energy_reference` (a float64 NumPy twin written from the equations above,
for the tests). None of them imports the d3grasp package outside ``d3grasp.kernels``: the hand comes
in as a plain dict (``HandLayout.from_dict``, built by ``d3grasp.planner.synthesis`` from the hand's
USD file).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import warp as wp
from d3grasp.kernels.grasp_energy_inputs import (
    TERM_NAMES,
    EnergyWeights,
    HandLayout,
    ObjectShape,
    contact_weight_rows,
    matrix_to_quat_xyzw,
)

__all__ = ["GraspEnergy"]

_MESH_MAX_DIST = 10.0  # m: a mesh query farther than this finds nothing (no hand point is that far)


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
# Host side: buffers, energy and gradient.
# --------------------------------------------------------------------------------------------


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
                np.array([matrix_to_quat_xyzw(r) for r in layout.joint_origin_rot]).reshape(-1, 4),
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
        w = contact_weight_rows(contact_weight, self.num_grasps, self.layout.num_contacts)
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
