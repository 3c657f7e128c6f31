"""The pictures ``d3grasp-play`` can take of a rollout, behind one object the play loop calls each step."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass
class PictureSettings:
    video: str | None = None  # out.gif | out.mp4
    video_fps: float = 30.0
    video_size: tuple[int, int] = (240, 180)  # px per tile (width, height)
    video_worlds: int = 4  # the first N worlds, tiled
    video_frames: int | None = None  # stop recording after this many frames
    usd: str | None = None  # out.usd | out.usda
    usd_worlds: int = 4
    tactile_plot: str | None = None  # out.png: pad forces of world 0's first episode

    @property
    def any(self) -> bool:
        return bool(self.video or self.usd or self.tactile_plot)


class RolloutPictures:
    def __init__(self, env: Any, settings: PictureSettings) -> None:
        self.settings = settings
        self.video = self.usd = self.tactile = None
        if settings.video:
            from d3grasp.viz.video import VideoRecorder, check_video_path

            check_video_path(settings.video)  # before the rollout, not when the file is written

            self.video = VideoRecorder(
                env,
                worlds=list(range(min(settings.video_worlds, env.num_envs))),
                tile=settings.video_size,
                fps=settings.video_fps,
                max_frames=settings.video_frames,
            )
        if settings.usd:
            from d3grasp.viz.usd_animation import UsdRecorder

            self.usd = UsdRecorder(
                env, worlds=list(range(min(settings.usd_worlds, env.num_envs))), fps=settings.video_fps
            )
        if settings.tactile_plot:
            from d3grasp.viz.tactile_plot import TactileTrace

            self.tactile = TactileTrace(env, world=0)
        if self.video is not None:
            self.video.capture()  # the reset state as the first frame
        if self.usd is not None:
            self.usd.capture()

    def after_step(self, extras: dict[str, Any]) -> None:
        if self.video is not None:
            self.video.capture()
        if self.usd is not None:
            self.usd.capture()
        if self.tactile is not None:
            self.tactile.record(extras.get("episodes"))

    def finish(self, log: Callable[[str], None] = print) -> dict[str, Path]:
        out: dict[str, Path] = {}
        if self.video is not None and self.video.frames:
            out["video"] = self.video.write(self.settings.video)
            per_frame = self.video.render_seconds / len(self.video.frames)
            log(
                f"[d3grasp] wrote {out['video']} ({len(self.video.frames)} frames at {self.video.fps:g} fps, "
                f"ray tracing {1000 * per_frame:.0f} ms per frame)"
            )
        if self.usd is not None and self.usd.samples:
            out["usd"] = self.usd.write(self.settings.usd)
            log(f"[d3grasp] wrote {out['usd']} ({self.usd.samples} time samples)")
        if self.tactile is not None and self.tactile.forces:
            out["tactile_plot"] = self.tactile.plot(self.settings.tactile_plot)
            log(f"[d3grasp] wrote {out['tactile_plot']}")
        return out
