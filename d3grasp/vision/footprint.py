"""Registering the camera's view of an object to the object's own frame: what the planner needs.

The localiser (:mod:`d3grasp.vision.localisation`) fits the minimum-area rectangle round the
object's footprint. The planner places a grasp at the object's *body* pose: its origin is the centre
of the object's axis-aligned bounding box, its yaw the body's. The two agree only for footprints that
are rectangles aligned with the body's axes. For others the fit is off by the same amount every time
the object is seen, whatever the noise: a cross's fit lies at 45 degrees to its arms, a mug's
includes the handle (15 mm from the body's centre and 0.47 rad turned, either way, for ``mug_04``),
and a fit cannot tell an L-shape's two ends apart.

The object's mesh is known (its grasps are planned on it), so its footprint seen from above is too
(:class:`Footprint`, from the collision pieces). :func:`register` finds the body pose that lays the
model's footprint over the pixels the camera saw: the centroids coincide, and the yaw is the one,
of a search over the full turn, with the smallest two-way distance between the seen points and the
model's area and outline. Turns the shape cannot tell apart (a box's half turn, a cross's quarter
turns, any turn of a round object) score alike. Of those, the one whose heights match what the
camera saw (the model's top surface against each seen cell's highest pixel) is kept when it matches
clearly better, which tells a blob's taller end from its lower one; otherwise the smallest yaw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError, cKDTree

from d3grasp.geometry import quat_xyzw_to_matrix, rot_z, wrap_angle

RASTER_CELL = 0.001  # m, the grid the model's footprint is drawn on
YAW_STEP = math.radians(2.0)  # the full-turn scan; then refined to YAW_STEP / 5 round the pick
# m of score within which turns count as the same shape: the camera's pixel is ~2 mm at the table
# and its depth noise ~1.3 mm, which move the two-way distance by a fraction of a millimetre.
REGISTER_TIE = 0.0005
MAX_POINTS = 800  # seen cells and outline cells scored (an even subsample beyond)
SCAN_POINTS = 200  # of those, in the full-turn scan
SEEN_CELL = 0.003  # m, the grid the seen points are counted on (the camera's pixel: ~2.3 mm at the table)
SHIFT_RANGE = 0.006  # m, the search round the centroids' alignment, each way
# m of height mismatch by which one of the turns that score alike must beat the smallest yaw to be
# kept: the camera's depth noise (~1.3 mm a pixel) averages to ~0.1 mm over the ~100 cells of a
# small object, and a turn that puts a blob's ends the wrong way round misses by several millimetres
# where the ends differ.
HEIGHT_TIE = 0.001


@dataclass(frozen=True)
class Footprint:
    """An object's footprint seen from straight above, in its own (body) frame."""

    origin: np.ndarray  # (2,) m, the grid's lower corner
    cell: float  # m
    outside: np.ndarray  # (nx, ny) m, each cell's distance to the footprint (0 inside)
    outline: np.ndarray  # (m, 2) m, cells on the footprint's edge
    centroid: np.ndarray  # (2,) m, the area's centroid
    # (nx, ny) m, the top surface's height above the object's lowest point (NaN off the footprint);
    # None for pieces given without heights
    top: np.ndarray | None = None


def _rot2(a: float) -> np.ndarray:
    return rot_z(a)[:2, :2]


def footprint_of_pieces(pieces: list[np.ndarray], cell: float = RASTER_CELL) -> Footprint:
    """The footprint of an object made of convex ``pieces`` ((n, 2+) body-frame points each, their
    convex hulls the collision pieces): the union of the pieces' outlines from above, drawn on a
    grid of ``cell`` (overlapping hulls count once)."""
    full = [np.asarray(p, dtype=np.float64) for p in pieces if len(p)]
    if not full:
        raise ValueError("a footprint needs at least one piece with points")
    pts = [p[:, :2] for p in full]
    with_z = all(p.shape[1] >= 3 for p in full)
    every = np.concatenate(pts)
    lo, hi = every.min(axis=0) - 2.0 * cell, every.max(axis=0) + 2.0 * cell
    gx = np.arange(lo[0] + 0.5 * cell, hi[0], cell)
    gy = np.arange(lo[1] + 0.5 * cell, hi[1], cell)
    grid = np.stack(np.meshgrid(gx, gy, indexing="ij"), axis=-1).reshape(-1, 2)
    inside = np.zeros(len(grid), dtype=bool)
    top = np.full(len(grid), -np.inf)
    for p, p3 in zip(pts, full, strict=True):
        try:
            eq = ConvexHull(p).equations  # inside: normal . x + offset <= 0 for every facet
        except (QhullError, ValueError):
            continue  # a flat piece (a line from above) covers no area
        here = np.all(grid @ eq[:, :2].T + eq[:, 2] <= 1e-12, axis=1)
        inside |= here
        if with_z and here.any():
            top[here] = np.maximum(top[here], _top_of_hull(p3[:, :3], grid[here]))
    if not inside.any():
        raise ValueError("the pieces cover no area seen from above")
    mask = inside.reshape(len(gx), len(gy))
    bottom = min(float(p[:, 2].min()) for p in full) if with_z else 0.0
    edge = mask & ~ndimage.binary_erosion(mask)
    outline = grid[edge.reshape(-1)]
    if len(outline) > MAX_POINTS:
        outline = outline[:: int(math.ceil(len(outline) / MAX_POINTS))]
    return Footprint(
        origin=lo,
        cell=cell,
        outside=ndimage.distance_transform_edt(~mask) * cell,
        outline=outline,
        centroid=grid[inside].mean(axis=0),
        top=np.where(inside, top - bottom, np.nan).reshape(mask.shape) if with_z else None,
    )


def _top_of_hull(points: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Height (body z) of the top of the convex hull of ``points`` (n, 3) above each of ``xy`` (m, 2),
    which lie inside the hull's outline from above: the lowest of its upward facets' planes there
    (inside, ``n . p + d <= 0`` for each facet, so ``z <= -(d + n_x x + n_y y) / n_z`` where n_z > 0).
    A hull flat in z (a sheet) is its highest point."""
    try:
        eq = ConvexHull(points).equations
    except (QhullError, ValueError):
        return np.full(len(xy), float(points[:, 2].max()))
    up = eq[eq[:, 2] > 1e-9]
    planes = -(up[:, 3][None, :] + xy @ up[:, :2].T) / up[:, 2][None, :]
    return np.minimum(planes.min(axis=1), float(points[:, 2].max()))


def _score(ref: Footprint, seen: np.ndarray, tree: cKDTree, yaw: float, shift: np.ndarray) -> float:
    """Two-way distance (m) between the seen points and the model at ``yaw``, its centroid at
    ``shift`` from theirs: seen points outside the model's area, model outline far from any seen point."""
    r = _rot2(yaw)
    body = (seen - shift) @ r + ref.centroid  # seen points in the body frame
    ij = np.floor((body - ref.origin) / ref.cell).astype(np.int64)
    n = np.array(ref.outside.shape)
    clipped = np.clip(ij, 0, n - 1)
    beyond = np.linalg.norm((ij - clipped) * ref.cell, axis=1)  # off the grid: at least this far
    outside = ref.outside[clipped[:, 0], clipped[:, 1]] + beyond
    unseen, _ = tree.query((ref.outline - ref.centroid) @ r.T + shift)
    return float(outside.mean() + unseen.mean())


def _height_mismatch(ref: Footprint, cells_xy: np.ndarray, cells_top: np.ndarray, yaw: float) -> float:
    """Mean absolute difference (m) between the seen cells' highest pixels (``cells_top``, above the
    table) and the model's top at ``yaw`` (``cells_xy`` centred on their centroid), after removing
    their median difference: a shared offset (the table's height, the object's lowest point hidden)
    does not count, a turn that puts the tall end where the camera saw the low one does. Mean, not
    median, so that a difference over a third of the object (one end) counts. Inf with no overlap."""
    body = cells_xy @ _rot2(yaw) + ref.centroid
    ij = np.floor((body - ref.origin) / ref.cell).astype(np.int64)
    on = np.all((ij >= 0) & (ij < np.array(ref.top.shape)), axis=1)
    model = np.full(len(body), np.nan)
    model[on] = ref.top[ij[on, 0], ij[on, 1]]
    both = np.isfinite(model)
    if both.sum() < 3:
        return math.inf
    diff = cells_top[both] - model[both]
    return float(np.mean(np.abs(diff - np.median(diff))))


def register(
    seen_points: np.ndarray,
    ref: Footprint,
    tie: float = REGISTER_TIE,
    heights: np.ndarray | None = None,
) -> tuple[np.ndarray, float, np.ndarray]:
    """The body pose that lays ``ref`` over ``seen_points`` ((n, 2+) world, the footprint the camera
    saw): (origin (2,) world, yaw, extents (2,) of the seen points along the body's axes).

    The seen points are first reduced to the cells of a SEEN_CELL grid they fall in: walls facing the
    camera put many pixels on a thin strip of the footprint, and counting each cell once keeps its
    centroid the area's. Then a full-turn scan of the yaw with the centroids together, a search of
    the shift round that (up to SHIFT_RANGE each way), and a finer yaw. ``heights`` ((n,) m, each seen
    point's height above the table) choose among turns that score alike (module docstring)."""
    pts = np.asarray(seen_points, dtype=np.float64)[:, :2]
    cells, which = np.unique(np.floor(pts / SEEN_CELL).astype(np.int64), axis=0, return_inverse=True)
    seen_all = (cells + 0.5) * SEEN_CELL
    c = seen_all.mean(axis=0)
    seen = seen_all - c
    if len(seen) > MAX_POINTS:
        seen = seen[:: int(math.ceil(len(seen) / MAX_POINTS))]
    tree = cKDTree(seen)
    # The scan on a coarser subsample: it only has to land within a step of the best turn.
    few = seen[:: int(math.ceil(len(seen) / SCAN_POINTS))]
    coarse = replace(ref, outline=ref.outline[:: int(math.ceil(len(ref.outline) / SCAN_POINTS))])
    few_tree = cKDTree(few)
    zero = np.zeros(2)
    yaws = np.arange(-math.pi, math.pi, YAW_STEP)
    scores = np.array([_score(coarse, few, few_tree, y, zero) for y in yaws])
    # Local minima of the circular scan within ``tie`` of the best: the smallest |yaw| of them, unless
    # the heights match another clearly better.
    minima = (scores <= np.roll(scores, 1)) & (scores <= np.roll(scores, -1))
    picks = np.nonzero(minima & (scores <= scores.min() + tie))[0]
    pick = min(picks, key=lambda k: abs(yaws[k]))
    if len(picks) > 1 and heights is not None and ref.top is not None:
        # Each cell's highest pixel: pixels on walls facing the camera project inside the outline
        # at heights below the top surface above them.
        cells_top = np.full(len(cells), -np.inf)
        np.maximum.at(cells_top, which.reshape(-1), np.asarray(heights, dtype=np.float64))
        mismatch = {k: _height_mismatch(ref, seen_all - c, cells_top, float(yaws[k])) for k in picks}
        best = min(picks, key=lambda k: mismatch[k])
        if mismatch[best] < mismatch[pick] - HEIGHT_TIE:
            pick = best
    yaw = float(yaws[pick])
    shift = zero
    for step in (SHIFT_RANGE / 3.0, SHIFT_RANGE / 12.0):  # a 7 x 7 grid, then a finer 7 x 7 round its best
        ticks = np.arange(-3, 4) * step
        grid = shift + np.stack(np.meshgrid(ticks, ticks, indexing="ij"), axis=-1).reshape(-1, 2)
        shift = grid[np.argmin([_score(ref, seen, tree, yaw, d) for d in grid])]
    fine = yaw + np.linspace(-YAW_STEP, YAW_STEP, 11)
    yaw = wrap_angle(float(fine[np.argmin([_score(ref, seen, tree, y, shift) for y in fine])]))
    origin = c + shift - _rot2(yaw) @ ref.centroid
    body = (seen_all - origin) @ _rot2(yaw)
    return origin, yaw, np.ptp(body, axis=0)


def object_pieces(model, layout, world: int) -> list[np.ndarray]:
    """World ``world``'s object as convex pieces of body-frame points: a rigid object's collision
    shapes (meshes' vertices, boxes' corners, round shapes' rims), a soft object's rest nodes."""
    import newton

    p0, n = int(layout.particle_start[world]), int(layout.particle_count[world])
    if n:
        return [np.asarray(layout.rest_particle_q[p0 : p0 + n], dtype=np.float64)]
    gt = newton.GeoType
    shapes = np.asarray(layout.object_shapes[world])
    collide = (model.shape_flags.numpy()[shapes] & int(newton.ShapeFlags.COLLIDE_SHAPES)) != 0
    types, scales = model.shape_type.numpy(), model.shape_scale.numpy()
    xforms = model.shape_transform.numpy()
    ring = np.linspace(0.0, 2.0 * math.pi, 32, endpoint=False)
    pieces = []
    for s in shapes[collide] if collide.any() else shapes:
        kind, scale = int(types[s]), np.asarray(scales[s], dtype=np.float64)
        if kind in (gt.MESH, gt.CONVEX_MESH) and model.shape_source[s] is not None:
            local = np.asarray(model.shape_source[s].vertices, dtype=np.float64) * scale
        elif kind == gt.BOX:
            local = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]) * scale
        elif kind in (gt.SPHERE, gt.CAPSULE, gt.CYLINDER):
            r = scale[0]
            half = 0.0 if kind == gt.SPHERE else scale[1] + (r if kind == gt.CAPSULE else 0.0)
            circle = np.stack([r * np.cos(ring), r * np.sin(ring), np.zeros_like(ring)], axis=1)
            local = np.concatenate([circle + [0.0, 0.0, -half], circle + [0.0, 0.0, half]])
        else:
            continue
        xf = xforms[s]
        pieces.append(local @ quat_xyzw_to_matrix(xf[3:7]).T + xf[:3])
    return pieces
