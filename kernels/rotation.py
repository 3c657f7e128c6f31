"""Global pose of deformable objects for every world in one launch (paper, Methods, adaptive rotation).

The paper picks the rotation estimate by the deformation metric ``sigma`` (see :mod:`.strain`)::

    sigma <  tau1 (0.01)        -> "average"   rotation
    tau1 <= sigma < tau2 (0.1)  -> "principal" rotation
    sigma >= tau2               -> "rigid"     rotation

The paper defers the three definitions to an appendix we do not have, so ours are (all sums over the
object's N nodes with weights ``w_i`` (particle masses in the simulation, 1 in the NumPy API),
``c = sum w p / sum w`` and ``c_ref`` likewise on the reference nodes, ``x_i = p_i - c``,
``y_i = p_i^ref - c_ref``, ``A = sum w x y^T`` the cross-covariance, ``C_ref = sum w y y^T`` and
``C_cur = sum w x x^T``):

- **rigid** -- the best-fit rotation (Kabsch/Horn): ``R = argmax_{R in SO(3)} tr(R^T A)``, i.e. the
  rotation minimising ``sum w ||R y_i - x_i||^2``. Equals ``U diag(1, 1, det(U V^T)) V^T`` for
  ``A = U S V^T``.
- **average** -- the rotation of the object's average deformation gradient. The least-squares affine
  fit ``F_bar = argmin_F sum w ||F y_i - x_i||^2 = A C_ref^-1`` equals the deformation gradient of every
  element when the deformation is affine, so it is the mesh's average deformation gradient; the
  rotation is the polar factor ``R = argmax_{R in SO(3)} tr(R^T F_bar)`` (``F_bar = R S``). It needs
  only node positions (no per-element rotations) and is exact for rigid motions.
- **principal** -- the rotation that takes the reference principal axes to the current ones:
  ``R = G E^T`` with ``E`` and ``G`` the eigenvectors of ``C_ref`` and ``C_cur`` as columns, sorted by
  decreasing eigenvalue. Eigenvectors carry no sign, so each current axis ``g_k`` is flipped to make
  ``g_k^T A e_k >= 0`` (it points the way the nodes that lay along ``e_k`` moved; node correspondence
  makes this work for symmetric shapes where third moments vanish); if ``det(G E^T) < 0`` the axis with
  the smallest ``|g_k^T A e_k|`` (least determined) is flipped. Axes of equal extent (spheres, cubes)
  make this estimate arbitrary about those axes: a limitation of principal axes, not of the code.

Both maximisations run a few steps of the rotation-extraction iteration of Mueller et al. (2016),
started from ``wp.svd3``'s answer, because ``svd3`` alone carries ~1e-3 errors in float32 for
ill-conditioned covariance matrices; the iteration converges to float32 precision.

Quaternions are Warp's (x, y, z, w) with ``w >= 0``. Velocities: ``v = (c(t) - c(t - dt)) / dt`` (paper)
and the angular velocity ``omega = log(q(t) q(t-dt)^-1) / dt`` (axis times angle over dt), which jumps
when the estimator switches mode; reset the history on episode reset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .strain import StrainLayout, _sigma_kernel

__all__ = [
    "MODE_NAMES",
    "ObjectPoseBuffers",
    "compute_object_pose",
    "update_object_velocity",
    "reset_object_history",
    "object_rotation",
]

MODE_NAMES: tuple[str, str, str] = ("average", "principal", "rigid")
_REFINE_ITERS = 20


@wp.func
def rotation_maximising_trace(a_in: wp.mat33, iters: int) -> wp.quat:
    """Unit quaternion of ``argmax_{R in SO(3)} tr(R^T A)`` (polar factor with det correction)."""
    scale = wp.sqrt(wp.ddot(a_in, a_in))
    a = a_in
    if scale > 0.0:
        a = a_in / scale
    u = wp.mat33()
    s = wp.vec3()
    v = wp.mat33()
    wp.svd3(a, u, s, v)
    r = u @ wp.transpose(v)
    if wp.determinant(r) < 0.0:
        # svd3 returns singular values in decreasing order: flip the direction of the smallest.
        r = u @ wp.diag(wp.vec3(1.0, 1.0, -1.0)) @ wp.transpose(v)
    q = wp.normalize(wp.quat_from_matrix(r))
    at = wp.transpose(a)
    for _ in range(iters):
        rt = wp.transpose(wp.quat_to_matrix(q))
        omega = wp.cross(rt[0], at[0]) + wp.cross(rt[1], at[1]) + wp.cross(rt[2], at[2])
        denom = wp.abs(wp.dot(rt[0], at[0]) + wp.dot(rt[1], at[1]) + wp.dot(rt[2], at[2])) + 1.0e-9
        omega = omega / denom
        ang = wp.length(omega)
        if ang > 1.0e-12:
            q = wp.normalize(wp.quat_from_axis_angle(omega / ang, ang) * q)
    return q


@wp.func
def sorted_eigenvectors(c: wp.mat33) -> wp.mat33:
    """Eigenvectors of symmetric ``c`` as columns, sorted by decreasing eigenvalue."""
    q, d = wp.eig3(c)
    qt = wp.transpose(q)
    i0 = int(0)  # noqa: UP018 (Warp: a typed, mutable local)
    i1 = int(1)  # noqa: UP018 (Warp: a typed, mutable local)
    i2 = int(2)  # noqa: UP018 (Warp: a typed, mutable local)
    if d[i1] > d[i0]:
        tmp = i0
        i0 = i1
        i1 = tmp
    if d[i2] > d[i1]:
        tmp = i1
        i1 = i2
        i2 = tmp
    if d[i1] > d[i0]:
        tmp = i0
        i0 = i1
        i1 = tmp
    return wp.matrix_from_cols(qt[i0], qt[i1], qt[i2])


@wp.func
def principal_axes_rotation(c_ref: wp.mat33, c_cur: wp.mat33, a: wp.mat33) -> wp.quat:
    e = sorted_eigenvectors(c_ref)
    g = sorted_eigenvectors(c_cur)
    et = wp.transpose(e)
    gt = wp.transpose(g)
    g0 = gt[0]
    g1 = gt[1]
    g2 = gt[2]
    s0 = wp.dot(g0, a @ et[0])
    s1 = wp.dot(g1, a @ et[1])
    s2 = wp.dot(g2, a @ et[2])
    if s0 < 0.0:
        g0 = -g0
    if s1 < 0.0:
        g1 = -g1
    if s2 < 0.0:
        g2 = -g2
    r = wp.matrix_from_cols(g0, g1, g2) @ et
    if wp.determinant(r) < 0.0:
        a0 = wp.abs(s0)
        a1 = wp.abs(s1)
        a2 = wp.abs(s2)
        if a0 <= a1 and a0 <= a2:
            g0 = -g0
        elif a1 <= a2:
            g1 = -g1
        else:
            g2 = -g2
        r = wp.matrix_from_cols(g0, g1, g2) @ et
    return wp.normalize(wp.quat_from_matrix(r))


@wp.kernel
def _object_pose_kernel(
    points: wp.array(dtype=wp.vec3),
    rest_points: wp.array(dtype=wp.vec3),
    weights: wp.array(dtype=float),
    object_particles: wp.array(dtype=wp.int32),
    object_start: wp.array(dtype=wp.int32),
    sigma: wp.array(dtype=float),
    tau1: float,
    tau2: float,
    forced_mode: int,
    iters: int,
    out_quat: wp.array(dtype=wp.quat),
    out_mode: wp.array(dtype=wp.int32),
    out_com: wp.array(dtype=wp.vec3),
):
    o = wp.tid()
    s0 = object_start[o]
    s1 = object_start[o + 1]
    wsum = float(0.0)  # noqa: UP018 (Warp: a typed, mutable local)
    c = wp.vec3()
    cr = wp.vec3()
    for j in range(s0, s1):
        p = object_particles[j]
        w = weights[p]
        wsum += w
        c += w * points[p]
        cr += w * rest_points[p]
    c = c / wsum
    cr = cr / wsum
    a = wp.mat33()
    c_ref = wp.mat33()
    c_cur = wp.mat33()
    for j in range(s0, s1):
        p = object_particles[j]
        w = weights[p]
        x = points[p] - c
        y = rest_points[p] - cr
        a += w * wp.outer(x, y)
        c_ref += w * wp.outer(y, y)
        c_cur += w * wp.outer(x, x)

    mode = forced_mode
    if mode < 0:
        sg = sigma[o]
        if sg < tau1:
            mode = 0
        elif sg < tau2:
            mode = 1
        else:
            mode = 2
    q = wp.quat_identity()
    if mode == 0:
        q = rotation_maximising_trace(a @ wp.inverse(c_ref), iters)
    elif mode == 1:
        q = principal_axes_rotation(c_ref, c_cur, a)
    else:
        q = rotation_maximising_trace(a, iters)
    if q[3] < 0.0:
        q = -q
    out_quat[o] = q
    out_mode[o] = mode
    out_com[o] = c


@wp.kernel
def _velocity_kernel(
    com: wp.array(dtype=wp.vec3),
    quat: wp.array(dtype=wp.quat),
    inv_dt: float,
    com_prev: wp.array(dtype=wp.vec3),
    quat_prev: wp.array(dtype=wp.quat),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
):
    o = wp.tid()
    lin_vel[o] = (com[o] - com_prev[o]) * inv_dt
    dq = quat[o] * wp.quat_inverse(quat_prev[o])
    if dq[3] < 0.0:
        dq = -dq
    xyz = wp.vec3(dq[0], dq[1], dq[2])
    sn = wp.length(xyz)
    omega = wp.vec3()
    if sn > 1.0e-12:
        angle = 2.0 * wp.atan2(sn, dq[3])
        omega = xyz * (angle / sn * inv_dt)
    ang_vel[o] = omega
    com_prev[o] = com[o]
    quat_prev[o] = quat[o]


@wp.kernel
def _reset_history_kernel(
    mask: wp.array(dtype=wp.int32),
    com: wp.array(dtype=wp.vec3),
    quat: wp.array(dtype=wp.quat),
    com_prev: wp.array(dtype=wp.vec3),
    quat_prev: wp.array(dtype=wp.quat),
    lin_vel: wp.array(dtype=wp.vec3),
    ang_vel: wp.array(dtype=wp.vec3),
):
    o = wp.tid()
    if mask[o] != 0:
        com_prev[o] = com[o]
        quat_prev[o] = quat[o]
        lin_vel[o] = wp.vec3()
        ang_vel[o] = wp.vec3()


@dataclass
class ObjectPoseBuffers:
    """Per-object pose state: current estimate, history for finite differences, velocities."""

    weights: wp.array  # (particle_count,) node weights (masses)
    quat: wp.array  # (O,) xyzw
    mode: wp.array  # (O,) int32 index into MODE_NAMES
    com: wp.array  # (O,) vec3
    com_prev: wp.array
    quat_prev: wp.array
    lin_vel: wp.array
    ang_vel: wp.array

    @classmethod
    def allocate(cls, layout: StrainLayout, particle_mass: wp.array | None = None) -> ObjectPoseBuffers:
        d = layout.device
        o = layout.object_count
        if particle_mass is None:
            particle_mass = wp.ones(layout.particle_count, dtype=float, device=d)
        elif particle_mass.shape[0] != layout.particle_count:
            raise ValueError("particle_mass must have one entry per particle of the layout")
        quat_prev = wp.array(
            np.tile([0.0, 0.0, 0.0, 1.0], (o, 1)).astype(np.float32), dtype=wp.quat, device=d
        )
        return cls(
            weights=particle_mass,
            quat=wp.zeros(o, dtype=wp.quat, device=d),
            mode=wp.zeros(o, dtype=wp.int32, device=d),
            com=wp.zeros(o, dtype=wp.vec3, device=d),
            com_prev=wp.zeros(o, dtype=wp.vec3, device=d),
            quat_prev=quat_prev,
            lin_vel=wp.zeros(o, dtype=wp.vec3, device=d),
            ang_vel=wp.zeros(o, dtype=wp.vec3, device=d),
        )


def compute_object_pose(
    layout: StrainLayout,
    points: wp.array,
    sigma: wp.array,
    out: ObjectPoseBuffers,
    tau1: float = 0.01,
    tau2: float = 0.1,
    forced_mode: int = -1,
) -> None:
    """Rotation (by sigma's mode), mode and centre of mass of every object; no host sync."""
    wp.launch(
        _object_pose_kernel,
        dim=layout.object_count,
        inputs=[
            points,
            layout.rest_points,
            out.weights,
            layout.object_particles,
            layout.object_start,
            sigma,
            float(tau1),
            float(tau2),
            int(forced_mode),
            _REFINE_ITERS,
        ],
        outputs=[out.quat, out.mode, out.com],
        device=layout.device,
    )


def update_object_velocity(out: ObjectPoseBuffers, dt: float) -> None:
    """Finite-difference linear/angular velocity from the last call's pose, then store the pose."""
    if dt <= 0.0:
        raise ValueError(f"dt must be positive, got {dt}")
    wp.launch(
        _velocity_kernel,
        dim=out.com.shape[0],
        inputs=[out.com, out.quat, 1.0 / dt],
        outputs=[out.com_prev, out.quat_prev, out.lin_vel, out.ang_vel],
        device=out.com.device,
    )


def reset_object_history(out: ObjectPoseBuffers, mask: wp.array) -> None:
    """For objects with ``mask != 0`` (int32, (O,)): history := current pose, velocities := 0."""
    wp.launch(
        _reset_history_kernel,
        dim=out.com.shape[0],
        inputs=[mask, out.com, out.quat],
        outputs=[out.com_prev, out.quat_prev, out.lin_vel, out.ang_vel],
        device=out.com.device,
    )


def object_rotation(
    points: np.ndarray,
    rest_points: np.ndarray,
    tau1: float = 0.01,
    tau2: float = 0.1,
    force_mode: str | None = None,
) -> tuple[np.ndarray, str]:
    """Global rotation of one object from its nodes: (unit quaternion xyzw (4,), mode name).

    The mode follows sigma and the thresholds unless ``force_mode`` names one of ``MODE_NAMES``.
    Node weights are uniform.
    """
    p = np.asarray(points, dtype=np.float64)
    r = np.asarray(rest_points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape != r.shape:
        raise ValueError(f"points and rest_points must both have shape (N,3), got {p.shape} and {r.shape}")
    if len(p) < 4:
        raise ValueError("need at least 4 nodes to define a rotation")
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(r))):
        raise ValueError("points or rest_points contain non-finite values")
    if not 0.0 <= tau1 <= tau2:
        raise ValueError(f"need 0 <= tau1 <= tau2, got {tau1}, {tau2}")
    forced = -1
    if force_mode is not None:
        if force_mode not in MODE_NAMES:
            raise ValueError(f"force_mode must be one of {MODE_NAMES}, got {force_mode!r}")
        forced = MODE_NAMES.index(force_mode)
    dev = wp.get_device()
    n = len(p)
    pa = wp.array(p.astype(np.float32), dtype=wp.vec3, device=dev)
    ra = wp.array(r.astype(np.float32), dtype=wp.vec3, device=dev)
    ids = wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=dev)
    start = wp.array(np.array([0, n], dtype=np.int32), dtype=wp.int32, device=dev)
    sigma = wp.zeros(1, dtype=float, device=dev)
    wp.launch(_sigma_kernel, dim=1, inputs=[pa, ra, ids, start], outputs=[sigma], device=dev)
    quat = wp.zeros(1, dtype=wp.quat, device=dev)
    mode = wp.zeros(1, dtype=wp.int32, device=dev)
    com = wp.zeros(1, dtype=wp.vec3, device=dev)
    wp.launch(
        _object_pose_kernel,
        dim=1,
        inputs=[
            pa,
            ra,
            wp.ones(n, dtype=float, device=dev),
            ids,
            start,
            sigma,
            float(tau1),
            float(tau2),
            forced,
            _REFINE_ITERS,
        ],
        outputs=[quat, mode, com],
        device=dev,
    )
    return quat.numpy()[0].astype(np.float64), MODE_NAMES[int(mode.numpy()[0])]
