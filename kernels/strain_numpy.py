"""NumPy in, NumPy out: one-off calls of the strain kernels (:mod:`d3grasp.kernels.strain`) on the
current Warp device, for tests, benchmarks and tools, and a tetrahedral grid mesh to run them on.

The environment does not use these: it keeps a :class:`~d3grasp.kernels.strain.StrainLayout` and its
buffers on the device and launches :func:`~d3grasp.kernels.strain.compute_strain` every step.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from d3grasp.kernels.strain import (
    StrainBuffers,
    StrainLayout,
    _max_eig_of_f_kernel,  # private to strain: these calls launch its kernels as they are
    _sigma_kernel,
    compute_strain,
)

__all__ = ["deformation_sigma", "green_lagrange_max_eig", "grid_tet_mesh", "nodal_max_principal_strain"]


def _points_arg(x: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N,3), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def green_lagrange_max_eig(F: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of 1/2 (F^T F - I) for each F in a (T,3,3) array; returns (T,) float32."""
    f = np.asarray(F, dtype=np.float32)
    if f.ndim != 3 or f.shape[1:] != (3, 3):
        raise ValueError(f"F must have shape (T,3,3), got {f.shape}")
    dev = wp.get_device()
    fa = wp.array(f, dtype=wp.mat33, device=dev)
    out = wp.zeros(len(f), dtype=float, device=dev)
    if len(f):
        wp.launch(_max_eig_of_f_kernel, dim=len(f), inputs=[fa], outputs=[out], device=dev)
    return out.numpy()


def nodal_max_principal_strain(
    points: np.ndarray, rest_points: np.ndarray, tets: np.ndarray
) -> tuple[np.ndarray, float]:
    """Nodal eps_max (N,) (volume-weighted mean over adjacent tets) and the object mean eps_bar_max.

    Nodes that belong to no tet get 0 and are excluded from the mean (N_k counts tet nodes only).
    """
    p = _points_arg(points, "points")
    r = _points_arg(rest_points, "rest_points")
    if p.shape != r.shape:
        raise ValueError(f"points {p.shape} and rest_points {r.shape} differ in shape")
    layout = StrainLayout.from_arrays(r, tets)
    buf = StrainBuffers.allocate(layout)
    compute_strain(layout, wp.array(p.astype(np.float32), dtype=wp.vec3, device=layout.device), buf)
    return buf.node_eps.numpy(), float(buf.object_eps.numpy()[0])


def deformation_sigma(points: np.ndarray, rest_points: np.ndarray) -> float:
    """sigma = Std({||p_i - p_i^ref||^2}) (population std, ddof=0) over all N points."""
    p = _points_arg(points, "points")
    r = _points_arg(rest_points, "rest_points")
    if p.shape != r.shape or len(p) == 0:
        raise ValueError(f"points {p.shape} and rest_points {r.shape} must be equal non-empty shapes")
    dev = wp.get_device()
    n = len(p)
    out = wp.zeros(1, dtype=float, device=dev)
    wp.launch(
        _sigma_kernel,
        dim=1,
        inputs=[
            wp.array(p.astype(np.float32), dtype=wp.vec3, device=dev),
            wp.array(r.astype(np.float32), dtype=wp.vec3, device=dev),
            wp.array(np.arange(n, dtype=np.int32), dtype=wp.int32, device=dev),
            wp.array(np.array([0, n], dtype=np.int32), dtype=wp.int32, device=dev),
        ],
        outputs=[out],
        device=dev,
    )
    return float(out.numpy()[0])


def grid_tet_mesh(nx: int, ny: int, nz: int, spacing: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """A box of nx*ny*nz nodes, each cell split into 6 tets around the main diagonal (tests, benchmarks)."""
    if min(nx, ny, nz) < 2:
        raise ValueError("grid_tet_mesh needs at least 2 nodes per axis")
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    points = g.astype(np.float64) * spacing

    def node(i: np.ndarray, j: np.ndarray, k: np.ndarray) -> np.ndarray:
        return (i * ny + j) * nz + k

    ci, cj, ck = (
        a.ravel() for a in np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    )
    corner = [node(ci + (b & 1), cj + ((b >> 1) & 1), ck + ((b >> 2) & 1)) for b in range(8)]
    kuhn = ((0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7))
    tets = np.concatenate([np.stack([corner[a] for a in t], -1) for t in kuhn])
    return points, tets.astype(np.int32)
