"""The grasp energy's float64 NumPy twin (forward only), written from the equations of
:mod:`d3grasp.kernels.grasp_energy` (rotation matrices and Rodrigues' formula, no Warp), for the tests.

:func:`reference_points` is the hand's forward kinematics and :func:`reference_energy` the energy and
its terms for a sphere or a box (the mesh's signed distance has no NumPy twin here).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from d3grasp.kernels.grasp_energy_inputs import (
    POSE_PARAMS,
    TERM_NAMES,
    EnergyWeights,
    HandLayout,
    ObjectShape,
    contact_weight_rows,
)

__all__ = ["reference_energy", "reference_points"]


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
    cw = contact_weight_rows(contact_weight, n, layout.num_contacts)
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
