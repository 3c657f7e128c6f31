"""Coarse object localisation from one depth image: the paper's visual modality (position, rough extent).

Pipeline (NumPy/SciPy, a few milliseconds at 320x240):

1. back-project the valid depth pixels into the world with the camera pose the robot believes in;
2. fit the table plane with RANSAC (the table fills most of the view) and refine it by least squares;
3. segment the object: pixels standing more than ``min_height`` above the plane, kept as the
   largest 8-connected image region. This is segmentation by depth and
   plane fit alone: no shape ids or other simulator ground truth are read. The hand is not in the
   view (the snapshot is taken before the approach, as a robot does from its home pose);
4. the object's footprint is the minimum-area rectangle round its points projected onto the plane
   (rotating calipers over the convex hull), which gives the centre, yaw and the two horizontal
   extents; the height is the 99th percentile of the point heights (robust to depth noise);
5. uncertainty from a sensor model: each footprint edge is known to within one pixel footprint
   (uniform, std ``s / sqrt(12)``) and to the calibration error (``range * rot_std`` and
   ``pos_std``); the height to the depth noise at the top.

Round objects seen at an angle hide part of their far side, which biases the footprint towards the
camera; a camera looking down (the default pose) keeps that bias to millimetres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

MIN_OBJECT_PIXELS = 12


@dataclass
class ObjectEstimate:
    """What the camera tells the grasp planner. Extents are along the estimate's yaw frame (x, y) and up."""

    centre: np.ndarray  # (3,) world, the bounding-box centre
    yaw: float  # rad, direction of the footprint rectangle's first side
    extents: np.ndarray  # (3,) m: along yaw, across, height
    centre_std: np.ndarray  # (3,) m, 1-sigma
    extents_std: np.ndarray  # (3,) m, 1-sigma
    num_points: int
    table_normal: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    table_offset: float = 0.0  # plane: normal . p = offset
    ok: bool = True  # False: no object found, the fields hold the fallback
    # (n, 3) world: the object's pixels projected onto the table plane (its footprint as seen)
    footprint: np.ndarray | None = None
    footprint_heights: np.ndarray | None = None  # (n,) m, those pixels' heights above the plane


def fit_plane_ransac(
    points: np.ndarray, rng: np.random.Generator, threshold: float, iterations: int = 64
) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane ``n . p = d`` of (N, 3) points: (unit normal with n_z >= 0, d, inlier mask)."""
    n_pts = len(points)
    if n_pts < 3:
        raise ValueError(f"a plane needs at least 3 points, got {n_pts}")
    best_count, best = -1, None
    for _ in range(iterations):
        a, b, c = points[rng.choice(n_pts, 3, replace=False)]
        normal = np.cross(b - a, c - a)
        norm = np.linalg.norm(normal)
        if norm < 1e-12:
            continue
        normal /= norm
        count = int(np.count_nonzero(np.abs(points @ normal - normal @ a) < threshold))
        if count > best_count:
            best_count, best = count, (normal, float(normal @ a))
    if best is None:
        raise ValueError("degenerate point set: no plane found")
    normal, d = best
    inliers = np.abs(points @ normal - d) < threshold
    # Least-squares refinement on the inliers: the normal is the direction of least spread.
    q = points[inliers]
    centroid = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - centroid, full_matrices=False)
    normal = vt[-1]
    if normal[2] < 0.0:
        normal = -normal
    d = float(normal @ centroid)
    inliers = np.abs(points @ normal - d) < threshold
    return normal, d, inliers


def min_area_rectangle(xy: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Minimum-area rectangle round 2-D points: (centre (2,), angle of side 0 in [0, pi/2), sizes (2,)).

    The optimal rectangle has a side collinear with an edge of the convex hull, so only the hull's
    edge directions (modulo 90 degrees) need to be tried.
    """
    pts = np.asarray(xy, dtype=np.float64)
    try:
        hull = pts[ConvexHull(pts).vertices]
    except (QhullError, ValueError):
        hull = pts  # collinear or too few points: every point is a candidate
    edges = np.roll(hull, -1, axis=0) - hull
    angles = np.unique(np.mod(np.arctan2(edges[:, 1], edges[:, 0]), 0.5 * math.pi))
    if len(angles) == 0:
        angles = np.zeros(1)
    best = None
    for a in angles:
        c, s = math.cos(a), math.sin(a)
        # Coordinates along the rectangle's axes u = (c, s), v = (-s, c).
        pu = hull @ np.array([c, s])
        pv = hull @ np.array([-s, c])
        area = (pu.max() - pu.min()) * (pv.max() - pv.min())
        if best is None or area < best[0]:
            best = (area, a, pu, pv)
    _, a, pu, pv = best
    c, s = math.cos(a), math.sin(a)
    mu, mv = 0.5 * (pu.max() + pu.min()), 0.5 * (pv.max() + pv.min())
    centre = mu * np.array([c, s]) + mv * np.array([-s, c])
    return centre, float(a), np.array([pu.max() - pu.min(), pv.max() - pv.min()])


def segment_object(
    points_world: np.ndarray,
    valid: np.ndarray,
    normal: np.ndarray,
    offset: float,
    min_height: float,
) -> np.ndarray:
    """(H, W) bool mask of the object: above the plane, the largest 8-connected region."""
    height = points_world @ normal - offset
    mask = valid & (height > min_height)
    # Noisy table pixels above the threshold are isolated: the largest region drops them. (A
    # morphological opening would too, but it also erases thin parts such as a mug's handle.)
    labels, count = ndimage.label(mask, structure=np.ones((3, 3), dtype=bool))
    if count == 0:
        return mask
    sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, count + 1))
    return labels == (1 + int(np.argmax(sizes)))


def localise_object(
    depth: np.ndarray,
    intrinsics,
    pose: tuple[np.ndarray, np.ndarray],
    rng: np.random.Generator,
    *,
    min_height: float = 0.004,
    plane_threshold: float = 0.003,
    depth_std: float = 0.0,
    calib_pos_std: float = 0.0,
    calib_rot_std: float = 0.0,
    fallback_centre: np.ndarray | None = None,
    fallback_extents: np.ndarray | None = None,
) -> ObjectEstimate:
    """Estimate the object's bounding-box centre, yaw and extents from a planar depth image.

    ``pose`` is the camera pose the robot believes in; ``depth_std`` (m, at the object), ``calib_*``
    (the calibration's 1-sigma errors) only feed the reported uncertainty. With no object found the
    estimate holds ``fallback_*`` and ``ok=False``.
    """
    from d3grasp.vision.camera import points_to_world

    cam_pos, cam_r = np.asarray(pose[0], dtype=np.float64), np.asarray(pose[1], dtype=np.float64)
    valid = np.isfinite(depth) & (depth > 0.0)
    pts = points_to_world(intrinsics.backproject(np.where(valid, depth, 0.0)), (cam_pos, cam_r))
    fb_c = np.zeros(3) if fallback_centre is None else np.asarray(fallback_centre, dtype=np.float64)
    fb_e = np.full(3, 0.06) if fallback_extents is None else np.asarray(fallback_extents, dtype=np.float64)

    def failed(normal: np.ndarray, offset: float, n: int) -> ObjectEstimate:
        return ObjectEstimate(
            fb_c, 0.0, fb_e, np.full(3, np.inf), np.full(3, np.inf), n, normal, offset, False
        )

    if np.count_nonzero(valid) < 3:
        return failed(np.array([0.0, 0.0, 1.0]), 0.0, 0)
    normal, offset, _ = fit_plane_ransac(pts[valid], rng, plane_threshold)
    mask = segment_object(pts, valid, normal, offset, min_height)
    n_obj = int(mask.sum())
    if n_obj < MIN_OBJECT_PIXELS:
        return failed(normal, offset, n_obj)
    obj = pts[mask]
    heights = obj @ normal - offset
    # An orthonormal basis (e1, e2) of the plane, e1 as close to world x as the plane allows, so the
    # footprint's angle is a yaw about the table normal.
    e1 = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    uv = np.stack([obj @ e1, obj @ e2], axis=1)
    c2, yaw, size2 = min_area_rectangle(uv)
    top = float(np.percentile(heights, 99.0))
    base = offset * normal  # the plane's point closest to the world origin
    centre = base + (c2[0] - base @ e1) * e1 + (c2[1] - base @ e2) * e2 + 0.5 * top * normal

    # Sensor-model uncertainty (module docstring, step 5).
    rng_m = float(np.linalg.norm(centre - cam_pos))
    pixel = rng_m / float(intrinsics.fx)
    calib = math.hypot(rng_m * calib_rot_std, calib_pos_std)
    edge = math.sqrt(pixel**2 / 12.0 + depth_std**2)
    centre_std = np.array(
        [math.sqrt(edge**2 / 2.0 + calib**2)] * 2 + [math.sqrt((0.5 * depth_std) ** 2 + calib**2)]
    )
    extents_std = np.array([math.sqrt(2.0) * edge] * 2 + [max(depth_std, pixel / math.sqrt(12.0))])
    return ObjectEstimate(
        centre=centre,
        yaw=yaw,
        extents=np.array([size2[0], size2[1], top]),
        centre_std=centre_std,
        extents_std=extents_std,
        num_points=n_obj,
        table_normal=normal,
        table_offset=offset,
        ok=True,
        footprint=obj - np.outer(heights, normal),
        footprint_heights=heights,
    )
