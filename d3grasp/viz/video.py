"""Headless rollout videos: the worlds of a ``GraspEnv`` ray-traced on CPU by Newton's SensorCamera,
tiled into one frame with an overlay of the episode phase and a force bar per tactile pad.

    rec = VideoRecorder(env, worlds=[0, 1, 2, 3], tile=(240, 180), fps=30)
    for _ in range(300):
        env.step(actions); rec.capture()
    rec.write("rollout.gif")   # or .mp4 (imageio-ffmpeg)
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from d3grasp.vision.camera import CameraIntrinsics, RGBDCamera, look_at_pose

VIDEO_SUFFIXES: tuple[str, ...] = (".gif", ".mp4")


def check_video_path(path: str | Path) -> Path:
    """``path`` as a Path if it names a format we write (GIF or MP4), else ``ValueError``."""
    path = Path(path)
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"--video must end in .gif or .mp4, got '{path.name}'")
    return path


# Display colours (sRGB, 0..1): only the pictures read them, physics never does.
HAND_COLOR = (0.62, 0.66, 0.72)
PAD_COLOR = (0.85, 0.35, 0.25)
OBJECT_COLOR = (0.95, 0.70, 0.25)
SOFT_COLOR = (0.45, 0.75, 0.95)
TABLE_COLOR = (0.80, 0.80, 0.78)
FINGER_BAR_COLORS = (
    (230, 90, 70),
    (240, 170, 60),
    (90, 180, 90),
    (80, 140, 230),
)  # index, middle, ring, thumb
PAD_FINGER = (0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3)  # hand.PAD_NAMES order
BAR_FULL_SCALE = 10.0  # N at a full-height pad bar
OVERLAY_MIN_SIZE = (160, 120)  # px: smaller tiles are left bare (the overlay would cover them)

DEFAULT_EYE = (0.32, -0.50, 0.34)  # m: in front of the thumb side, above the table
DEFAULT_TARGET = (-0.06, 0.0, 0.07)  # between object and palm (the palm sits on the -x side)
SKY_RGBA = 0xFFF2E8DE  # packed A, B, G, R: a pale blue behind the table


def paint_scene(env) -> None:
    """Give hand, pads, objects and table display colours (model.shape_color / tri_color)."""
    import warp as wp

    model, lay = env.model, env.layout
    colors = model.shape_color.numpy()
    world = model.shape_world.numpy()
    colors[world < 0] = TABLE_COLOR
    for w in range(env.num_envs):
        colors[lay.hand_shapes[w]] = HAND_COLOR
        colors[lay.pad_shapes[w]] = PAD_COLOR
    obj_body = set(int(b) for b in lay.object_body if b >= 0)
    bodies = model.shape_body.numpy()
    for s in range(model.shape_count):
        if int(bodies[s]) in obj_body:
            colors[s] = OBJECT_COLOR
    model.shape_color.assign(colors)
    tri_color = getattr(model, "tri_color", None)
    if isinstance(tri_color, wp.array) and tri_color.shape[0]:
        tri_color.assign(np.tile(np.asarray(SOFT_COLOR, dtype=np.float32), (tri_color.shape[0], 1)))


def tile_grid(n: int) -> tuple[int, int]:
    """(rows, columns) of the most square grid holding ``n`` tiles, wider than tall."""
    cols = math.ceil(math.sqrt(n))
    return math.ceil(n / cols), cols


def draw_overlay(tile: np.ndarray, lines: list[str], pad_forces: np.ndarray | None) -> np.ndarray:
    """Text lines at the top left and one bar per pad (|F| up to BAR_FULL_SCALE N) at the bottom."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(np.ascontiguousarray(tile[..., :3]))
    draw = ImageDraw.Draw(img)
    h, w = tile.shape[:2]
    if lines:
        # A light panel keeps the text readable over any background.
        width = max(draw.textlength(line) for line in lines)
        draw.rectangle((1, 1, 8 + width, 5 + 11 * len(lines)), fill=(250, 250, 250), outline=(120, 120, 120))
    for k, line in enumerate(lines):
        draw.text((4, 3 + 11 * k), line, fill=(20, 20, 20))
    if pad_forces is not None:
        bar_w, gap, max_h = 6, 2, max(12, h // 5)
        x0 = w - len(pad_forces) * (bar_w + gap) - 4
        y1 = h - 4
        draw.rectangle(
            (x0 - 2, y1 - max_h - 15, w - 3, y1 + 1), fill=(250, 250, 250), outline=(120, 120, 120)
        )
        for p, f in enumerate(pad_forces):
            frac = min(max(float(f), 0.0) / BAR_FULL_SCALE, 1.0)
            x = x0 + p * (bar_w + gap)
            if frac > 0.0:
                draw.rectangle(
                    (x, y1 - frac * max_h, x + bar_w - 1, y1), fill=FINGER_BAR_COLORS[PAD_FINGER[p]]
                )
        draw.text((x0, y1 - max_h - 13), f"pads 0-{BAR_FULL_SCALE:.0f} N", fill=(20, 20, 20))
    return np.asarray(img)


class VideoRecorder:
    """Collects tiled, annotated colour frames of chosen worlds; writes GIF or MP4."""

    def __init__(
        self,
        env,
        worlds: list[int] | None = None,
        tile: tuple[int, int] = (240, 180),
        fps: float = 30.0,
        eye: tuple[float, float, float] = DEFAULT_EYE,
        target: tuple[float, float, float] = DEFAULT_TARGET,
        fov_deg: float = 45.0,
        max_frames: int | None = None,
        overlay: bool = True,
        shadows: bool = True,
    ) -> None:
        self.env = env
        self.worlds = list(range(min(4, env.num_envs))) if worlds is None else [int(w) for w in worlds]
        if not self.worlds or max(self.worlds) >= env.num_envs or min(self.worlds) < 0:
            raise ValueError(f"video worlds must lie in [0, {env.num_envs}), got {self.worlds}")
        if fps <= 0:
            raise ValueError(f"fps must be positive, got {fps}")
        self.fps = float(fps)
        # Frames are taken every k-th control step so the video plays in real time at ``fps``.
        self.every = max(1, round(1.0 / (env.dt * self.fps)))
        self.max_frames = max_frames
        self.overlay = overlay
        paint_scene(env)
        self.intrinsics = CameraIntrinsics.from_fov(int(tile[0]), int(tile[1]), math.radians(fov_deg))
        self.camera = RGBDCamera(env.model, self.intrinsics, shadows=shadows)
        from newton.sensors import SensorCamera

        self.camera.sensor.default_clear_data = SensorCamera.ClearData(clear_color=SKY_RGBA)
        self.pose = look_at_pose(np.asarray(eye), np.asarray(target))
        self.frames: list[np.ndarray] = []
        self._step = 0
        self.render_seconds = 0.0

    @property
    def full(self) -> bool:
        return self.max_frames is not None and len(self.frames) >= self.max_frames

    def capture(self, force: bool = False) -> bool:
        """Render a frame if this control step is due (every ``self.every``-th call); True if rendered."""
        due = force or self._step % self.every == 0
        self._step += 1
        if not due or self.full:
            return False
        self.frames.append(self.render_frame())
        return True

    def render_frame(self) -> np.ndarray:
        import time

        from d3grasp.vocabulary import GRASP_TYPES, PHASES

        env = self.env
        t0 = time.perf_counter()
        rgba = self.camera.render(
            env.state_0, [self.pose] * len(self.worlds), self.worlds, depth=False, color=True
        )["color"]
        self.render_seconds += time.perf_counter() - t0
        rows, cols = tile_grid(len(self.worlds))
        th, tw = self.intrinsics.height, self.intrinsics.width
        frame = np.full((rows * th, cols * tw, 3), 255, dtype=np.uint8)
        phase = env.phase_of(env.episode_length_buf).tolist()
        forces = np.linalg.norm(env.view.pad_force_true.cpu().numpy(), axis=-1)
        for k, w in enumerate(self.worlds):
            tile = rgba[k][..., :3]
            if self.overlay and tw >= OVERLAY_MIN_SIZE[0] and th >= OVERLAY_MIN_SIZE[1]:
                e = env.world_entries[w]
                t = float(env.episode_length_buf[w]) * env.dt
                lines = [
                    f"{e.id} ({GRASP_TYPES[int(env.grasp.type_id[w])]})",
                    f"{PHASES[phase[w]]}  t={t:4.2f} s",
                ]
                tile = draw_overlay(tile, lines, forces[w])
            r, c = divmod(k, cols)
            frame[r * th : (r + 1) * th, c * tw : (c + 1) * tw] = tile
        return frame

    def write(self, path: str | Path) -> Path:
        """GIF (Pillow) or MP4 (ffmpeg via imageio-ffmpeg), chosen by the suffix."""
        import imageio.v2 as imageio

        path = check_video_path(path)
        if not self.frames:
            raise ValueError("no frames captured")
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix.lower() == ".gif":
            # Pillow's GIF writer takes the frame duration in milliseconds; loop=0 repeats forever.
            imageio.mimsave(path, self.frames, duration=1000.0 / self.fps, loop=0)
        else:  # .mp4
            # yuv420p needs even sizes; macro_block_size=2 pads to that instead of resizing to 16.
            with imageio.get_writer(
                path, fps=self.fps, codec="libx264", pixelformat="yuv420p", macro_block_size=2, quality=7
            ) as writer:
                for f in self.frames:
                    writer.append_data(f)
        return path
