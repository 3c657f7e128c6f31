"""Rotations and quaternions in NumPy/Python float64: the one home of the package's helpers.

A leaf module: it imports only the standard library and NumPy, never the package, so every layer
(authoring, envs, vision, the planner) may use it. Warp functions (``kernels/``) and torch code keep
their own versions; ``kernels/`` may not import the package (``tests/test_layout.py``).

Conventions:

* Quaternions are ``(x, y, z, w)`` (Warp's and Newton's order), unit length.
* Rotation matrices are (3, 3) float64 whose columns are the rotated frame's axes in the parent
  frame; ``homogeneous`` builds (4, 4) transforms from them.
* ``rpy_matrix`` is URDF's ``Rz(yaw) · Ry(pitch) · Rx(roll)``.

Two quaternion-from-matrix functions are kept on purpose; they differ in the quaternion's sign and
in which pivot they take when two diagonal entries tie, so their outputs are not interchangeable bit
for bit, and the evaluation's results must not move:

* :func:`matrix_to_quat_xyzw_nonneg_w` returns the quaternion with ``w >= 0`` (the canonical
  hemisphere). The hand's authoring, the grasp poses and the root chain use it: grasp quaternions
  are written to ``grasps.json`` and USD files and compared there, so they need one sign per
  rotation.
* :func:`matrix_to_quat_xyzw_pivot_sign` keeps the sign Shepperd's method gives (the largest pivot
  component positive; ``w`` may be negative). The camera uses it for the pose it hands to Newton's
  ``SensorCamera``, where the sign does not matter; it is kept as it was so the rendered images and
  the perception results built on them stay identical.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np


def rpy_matrix(rpy: Sequence[float]) -> np.ndarray:
    """URDF rotation ``Rz(yaw) · Ry(pitch) · Rx(roll)`` for ``rpy = (roll, pitch, yaw)``."""
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return rz @ ry @ rx


def rot_y(a: float) -> np.ndarray:
    """Rotation matrix (3, 3) about y by ``a`` rad."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation matrix (3, 3) about world z by ``a`` rad."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wrap_angle(a: float) -> float:
    """``a`` rad as the same turn in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


def axis_angle_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of the rotation vector ``w`` (axis ``w / |w|``, angle ``|w|`` rad;
    Rodrigues' formula). The identity for ``|w| < 1e-12``."""
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.eye(3)
    k = w / theta
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * kx + (1.0 - math.cos(theta)) * kx @ kx


def homogeneous(xyz: Sequence[float], rot: np.ndarray) -> np.ndarray:
    """(4, 4) transform with rotation ``rot`` (3, 3) and translation ``xyz``."""
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = xyz
    return m


def quat_xyzw_to_matrix(q: Sequence[float]) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (x, y, z, w), normalised first."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat_xyzw_nonneg_w(rot: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix with ``w >= 0`` (Shepperd's method).

    One sign per rotation: what the hand's USD, the grasp poses (``grasps.json``) and the root chain
    store and compare. Pivot: the trace when positive, else the largest diagonal entry (ties go to
    the later axis).
    """
    m = np.asarray(rot, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0.0:
        s = math.sqrt(tr + 1.0) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0.0 else -q


def matrix_to_quat_xyzw_pivot_sign(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix, its sign as Shepperd's method gives it.

    The pivot component is positive: ``w`` when the trace is positive, else the component of the
    largest diagonal entry (``np.argmax``: ties go to the earlier axis), so ``w`` may be negative.
    The camera's pose for ``SensorCamera`` uses it (the sign is irrelevant there); kept apart from
    :func:`matrix_to_quat_xyzw_nonneg_w` so the rendered images do not change by a last digit.
    """
    m = np.asarray(r, dtype=np.float64)
    tr = np.trace(m)
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = [0.0, 0.0, 0.0, (m[k, j] - m[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)
