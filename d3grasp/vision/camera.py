"""An RGB-D camera per world on Newton's ray-traced ``SensorCamera`` (Warp; runs on CPU too).

Conventions. The camera frame is the one ``SensorCamera`` uses (USD/OpenGL): +x right, +y up, the
camera looks along -z. A pose is ``(position (3,), R (3, 3))`` whose columns are the camera axes in
the world. Pixel ``(row v, column u)`` has its centre at ``(u + 0.5, v + 0.5)``; row 0 is the top of
the image. Depth images are *planar* depth (distance along the optical axis, what RGB-D sensors
report), 0 where a ray hits nothing.

Noise (:func:`add_depth_noise`) follows the usual model of active-stereo sensors: Gaussian with a
standard deviation growing with the square of the depth, plus dropped pixels. Calibration error
(:func:`perturb_pose`) is modelled by rendering with the true camera pose and back-projecting with a
slightly wrong one, the pose the robot *believes* the camera has.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

from d3grasp.geometry import axis_angle_matrix, matrix_to_quat_xyzw_pivot_sign

Pose = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (square pixels, principal point at the image centre)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_y: float) -> CameraIntrinsics:
        """Intrinsics of a camera with vertical field of view ``fov_y`` (rad), as SensorCamera's rays."""
        if width < 1 or height < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        if not 0.0 < fov_y < math.pi:
            raise ValueError(f"fov_y must be in (0, pi) rad, got {fov_y}")
        f = 0.5 * height / math.tan(0.5 * fov_y)
        return cls(int(width), int(height), f, f, 0.5 * width, 0.5 * height)

    @property
    def fov_y(self) -> float:
        return 2.0 * math.atan(0.5 * self.height / self.fy)

    def backproject(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) planar depth -> (H, W, 3) points in the camera frame (invalid pixels give the origin)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        d = np.asarray(depth, dtype=np.float64)
        x = (u + 0.5 - self.cx) / self.fx * d
        y = -(v + 0.5 - self.cy) / self.fy * d  # image rows grow downwards, camera y upwards
        return np.stack([x, y, -d], axis=-1)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """(..., 3) camera-frame points in front of the camera -> (..., 2) pixel coordinates (u, v)."""
        p = np.asarray(points_cam, dtype=np.float64)
        d = -p[..., 2]
        u = p[..., 0] / d * self.fx + self.cx - 0.5
        v = -p[..., 1] / d * self.fy + self.cy - 0.5
        return np.stack([u, v], axis=-1)


def look_at_pose(eye: np.ndarray, target: np.ndarray, up: np.ndarray = (0.0, 0.0, 1.0)) -> Pose:
    """Camera pose at ``eye`` looking at ``target`` with the image's up direction towards ``up``."""
    eye = np.asarray(eye, dtype=np.float64)
    fwd = np.asarray(target, dtype=np.float64) - eye
    n = np.linalg.norm(fwd)
    if n < 1e-9:
        raise ValueError("camera eye and target coincide")
    fwd /= n
    right = np.cross(fwd, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-6:  # looking straight along up: any right axis will do
        right = np.cross(fwd, np.array([0.0, 1.0, 0.0]))
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    return eye, np.stack([right, cam_up, -fwd], axis=1)


def perturb_pose(pose: Pose, rng: np.random.Generator, pos_std: float, rot_std: float) -> Pose:
    """A calibration error: the pose moved by N(0, pos_std) per axis and turned by N(0, rot_std) per axis."""
    pos, r = pose
    dp = rng.normal(0.0, pos_std, 3) if pos_std > 0 else np.zeros(3)
    dw = rng.normal(0.0, rot_std, 3) if rot_std > 0 else np.zeros(3)
    return np.asarray(pos) + dp, axis_angle_matrix(dw) @ np.asarray(r)


def depth_noise_std(depth: np.ndarray, base: float, quadratic: float) -> np.ndarray:
    """Standard deviation (m) of the depth noise at ``depth`` (m): ``base + quadratic * depth**2``."""
    return base + quadratic * np.square(depth)


def add_depth_noise(
    depth: np.ndarray, rng: np.random.Generator, base: float, quadratic: float, dropout: float
) -> np.ndarray:
    """A noisy copy of a planar depth image: Gaussian depth noise and a fraction of pixels dropped (0)."""
    d = np.asarray(depth, dtype=np.float64).copy()
    valid = d > 0.0
    if base > 0.0 or quadratic > 0.0:
        d[valid] += rng.normal(0.0, 1.0, int(valid.sum())) * depth_noise_std(d[valid], base, quadratic)
    if dropout > 0.0:
        d[valid & (rng.random(d.shape) < dropout)] = 0.0
    return d


def points_to_world(points_cam: np.ndarray, pose: Pose) -> np.ndarray:
    pos, r = pose
    return np.asarray(points_cam) @ np.asarray(r).T + np.asarray(pos)


class RGBDCamera:
    """Renders depth, colour and shape-index images of chosen worlds of a Newton model.

    One ``SensorCamera`` serves every world; a call renders one view per requested world, each from
    its own pose. Images come back as NumPy arrays: ``depth`` (V, H, W) float32 planar depth,
    ``color`` (V, H, W, 4) uint8 RGBA, ``shape_index`` (V, H, W) uint32 (0xFFFFFFFF: nothing hit,
    0xFFFFFFFD: a deformable surface triangle).
    """

    def __init__(self, model, intrinsics: CameraIntrinsics, shadows: bool = False) -> None:
        from newton.sensors import SensorCamera

        self.model = model
        self.intrinsics = intrinsics
        self.sensor = SensorCamera(model, load_textures=False)
        self.sensor.create_default_light(enable_shadows=shadows)
        self.sensor.default_render_config.enable_shadows = shadows
        self.rays = SensorCamera.compute_camera_rays_pinhole(
            intrinsics.width, intrinsics.height, camera_fov=intrinsics.fov_y, device=model.device
        )
        self._buffers: dict[tuple[str, int], wp.array] = {}

    def _buffer(self, kind: str, views: int) -> wp.array:
        key = (kind, views)
        if key not in self._buffers:
            w, h = self.intrinsics.width, self.intrinsics.height
            alloc = {
                "depth": self.sensor.allocate_image_depth_forward,
                "color": self.sensor.allocate_image_color,
                "shape_index": self.sensor.allocate_image_shape_index,
            }[kind]
            self._buffers[key] = alloc(views, w, h)
        return self._buffers[key]

    def render(
        self,
        state,
        poses: list[Pose],
        worlds: list[int],
        *,
        depth: bool = True,
        color: bool = False,
        shape_index: bool = False,
        refit: bool = True,
    ) -> dict[str, np.ndarray]:
        from newton.sensors import SensorCamera

        if len(poses) != len(worlds) or not worlds:
            raise ValueError(f"one pose per world needed, got {len(poses)} poses for {len(worlds)} worlds")
        views = len(worlds)
        dev = self.model.device
        tf = [
            wp.transformf(wp.vec3f(*map(float, p)), wp.quatf(*map(float, matrix_to_quat_xyzw_pivot_sign(r))))
            for p, r in poses
        ]
        transforms = wp.array(tf, dtype=wp.transformf, device=dev)
        world_idx = wp.array(np.asarray(worlds, dtype=np.int32), dtype=wp.int32, device=dev)
        if refit:
            # Bodies and particles moved since the last render: the ray tracer's BVHs must follow.
            self.model.bvh_refit_shapes(state)
            if self.model.particle_count:
                self.model.bvh_refit_particles(state)
        out: dict[str, wp.array] = {}
        if depth:
            out["depth"] = self._buffer("depth", views)
        if color:
            out["color"] = self._buffer("color", views)
        if shape_index:
            out["shape_index"] = self._buffer("shape_index", views)
        self.sensor.update(
            state,
            transforms,
            self.rays,
            forward_depth_image=out.get("depth"),
            color_image=out.get("color"),
            shape_index_image=out.get("shape_index"),
            world_indices=world_idx,
        )
        result: dict[str, np.ndarray] = {}
        if depth:
            result["depth"] = out["depth"].numpy().copy()
        if color:
            result["color"] = SensorCamera.Utils.to_rgba_from_color(out["color"]).numpy().copy()
        if shape_index:
            result["shape_index"] = out["shape_index"].numpy().copy()
        return result
