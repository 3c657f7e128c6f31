"""Camera perception for the grasp environment: one RGB-D snapshot per world and episode.

At reset, after the object has been placed and before the hand is, :meth:`CameraPerception.observe`
renders the world with the hand parked far above the scene (the robot looks from its home pose
before it reaches), adds the sensor's noise, localises the object and returns the estimate the
grasp planner uses instead of the true pose. The true pose is used only to score the error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
import warp as wp

from d3grasp.vision.camera import (
    CameraIntrinsics,
    RGBDCamera,
    add_depth_noise,
    depth_noise_std,
    look_at_pose,
    perturb_pose,
)
from d3grasp.vision.localisation import ObjectEstimate, localise_object

if TYPE_CHECKING:  # the environment's config is read, never imported: envs imports vision, not back
    from d3grasp.envs.config import CameraConfig

PARK_HEIGHT = 50.0  # m the hand's bodies are lifted for the snapshot: far outside every camera frustum


@dataclass
class LocalisationError:
    """Errors of one estimate against the truth (m and rad)."""

    centre: float  # 3-D distance between estimated and true bounding-box centres
    horizontal: float  # the same in the table plane
    extents: float  # largest |error| of the box's sides, compared along the same axes, and of its height
    yaw: float  # the box's orientation error, modulo its half turn (localisation_error)

    def as_record(self) -> dict[str, float]:
        return {
            "loc_error": self.centre,
            "loc_error_xy": self.horizontal,
            "loc_extent_error": self.extents,
            "loc_yaw_error": self.yaw,
        }


def localisation_error(
    est: ObjectEstimate, true_centre: np.ndarray, true_yaw: float, true_extents: np.ndarray
) -> LocalisationError:
    """The estimated box against the true one. A box is the same box turned by half a turn, and the
    same box written turned by a quarter turn with its two sides swapped: of the estimate's two
    writings (yaw, sides) and (yaw + 90 degrees, sides swapped), the one whose yaw is nearer the
    truth's (modulo a half turn) is compared, its sides with the truth's along the same axes. So a
    box turned by 90 degrees with its sides unswapped (another box, when the sides differ) reads as
    the difference of its sides, and the same box written the other way reads as no error."""
    d = est.centre - np.asarray(true_centre, dtype=np.float64)
    te = np.asarray(true_extents, dtype=np.float64)
    ex = np.asarray(est.extents, dtype=np.float64)

    def half_turn_error(yaw: float) -> float:
        dy = (yaw - true_yaw) % math.pi
        return min(dy, math.pi - dy)

    writings = [(est.yaw, ex[:2]), (est.yaw + 0.5 * math.pi, ex[1::-1])]
    yaw, sides = min(writings, key=lambda w: half_turn_error(w[0]))
    ext = max(float(np.max(np.abs(sides - te[:2]))), abs(float(ex[2] - te[2])))
    return LocalisationError(
        centre=float(np.linalg.norm(d)),
        horizontal=float(np.linalg.norm(d[:2])),
        extents=ext,
        yaw=float(half_turn_error(yaw)),
    )


class CameraPerception:
    """The perception camera of every world of a ``GraspEnv`` (same pose in every world's frame)."""

    def __init__(self, model, body_world: np.ndarray, object_body: np.ndarray, cfg: CameraConfig, seed: int):
        self.cfg = cfg
        self.model = model
        self.intrinsics = CameraIntrinsics.from_fov(cfg.width, cfg.height, math.radians(cfg.fov_deg))
        self.camera = RGBDCamera(model, self.intrinsics)
        self.pose = look_at_pose(np.asarray(cfg.position), np.asarray(cfg.target))
        # Its own stream: switching perception on must not change the episodes' random draws.
        self.rng = np.random.default_rng([int(seed), 0x7E1])
        W = len(object_body)
        self.hand_bodies = [
            np.setdiff1d(np.nonzero(body_world == w)[0], [object_body[w]]).astype(np.int64) for w in range(W)
        ]

    def observe(
        self,
        state,
        world: int,
        object_body: int,
        object_pose: np.ndarray | None,
        particles: tuple[int, np.ndarray] | None,
        fallback_extents: np.ndarray,
    ) -> ObjectEstimate:
        """Render ``world`` with its object at ``object_pose`` (7: pos, quat xyzw; rigid) or ``particles``
        ((first index, (n, 3) positions); soft) and the hand parked, then localise the object.

        Writes into ``state``'s body and particle arrays of that world; the caller's reset overwrites them.
        """
        cfg = self.cfg
        bq = wp.to_torch(state.body_q, requires_grad=False)
        hand = torch.as_tensor(self.hand_bodies[world])
        bq[hand, 2] += PARK_HEIGHT
        if object_pose is not None and object_body >= 0:
            bq[object_body] = torch.as_tensor(object_pose, dtype=bq.dtype)
        if particles is not None:
            p0, pts = particles
            pq = wp.to_torch(state.particle_q, requires_grad=False)
            pq[p0 : p0 + len(pts)] = torch.as_tensor(pts, dtype=pq.dtype)
        depth = self.camera.render(state, [self.pose], [world], depth=True)["depth"][0]
        believed = self.pose
        d_std = 0.0
        if cfg.noise:
            depth = add_depth_noise(
                depth, self.rng, cfg.depth_noise_base, cfg.depth_noise_quadratic, cfg.dropout
            )
            believed = perturb_pose(self.pose, self.rng, cfg.calib_pos_std, cfg.calib_rot_std)
            d_std = float(
                depth_noise_std(
                    np.linalg.norm(self.pose[0] - np.asarray(cfg.target)),
                    cfg.depth_noise_base,
                    cfg.depth_noise_quadratic,
                )
            )
        return localise_object(
            depth,
            self.intrinsics,
            believed,
            self.rng,
            min_height=cfg.min_height,
            depth_std=d_std,
            calib_pos_std=cfg.calib_pos_std if cfg.noise else 0.0,
            calib_rot_std=cfg.calib_rot_std if cfg.noise else 0.0,
            fallback_centre=np.asarray(cfg.target, dtype=np.float64)
            + np.array([0.0, 0.0, 0.5 * fallback_extents[2]]),
            fallback_extents=fallback_extents,
        )


def localisation_summary(episodes: list[dict]) -> dict[str, float] | None:
    """Mean and 95th percentile (mm) of the episodes' localisation errors; None without camera episodes."""
    rows = [ep for ep in episodes if ep.get("loc_error") is not None]
    if not rows:
        return None
    out: dict[str, float] = {
        "episodes": float(len(rows)),
        "failed": float(sum(not ep.get("loc_ok", True) for ep in rows)),
    }
    # Every camera episode has the box fit's errors; only registered ones the registered error.
    registered = [ep for ep in rows if ep.get("loc_registered_xy") is not None]
    for key, eps in (
        ("loc_error", rows),
        ("loc_error_xy", rows),
        ("loc_extent_error", rows),
        ("loc_registered_xy", registered),
    ):
        if eps:
            v = 1000.0 * np.asarray([float(ep[key]) for ep in eps])
            out[f"{key}_mean_mm"] = float(v.mean())
            out[f"{key}_p95_mm"] = float(np.percentile(v, 95.0))
    return out


def localisation_markdown(runs: dict[str, list[dict]]) -> str:
    """A table of the localisation errors of every run that used camera perception ('' if none did)."""
    lines = []
    for label, eps in runs.items():
        s = localisation_summary(eps)
        if s is None:
            continue
        lines.append(
            f"| {label} | {int(s['episodes'])} | "
            f"{s['loc_error_mean_mm']:.1f} | {s['loc_error_p95_mm']:.1f} | "
            f"{s['loc_error_xy_mean_mm']:.1f} | {s['loc_extent_error_mean_mm']:.1f} | "
            f"{s['loc_extent_error_p95_mm']:.1f} | {int(s['failed'])} | "
            + (f"{s['loc_registered_xy_mean_mm']:.1f} |" if "loc_registered_xy_mean_mm" in s else "– |")
        )
    if not lines:
        return ""
    head = [
        "Camera localisation error (mm): centre (3-D), horizontal centre, largest extent error of the box"
        " fit; horizontal error of the body origin registered to the object's footprint",
        "",
        "| run | episodes | centre mean | centre p95 | xy mean | extent mean | extent p95 | not found "
        "| registered xy mean |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    return "\n".join(head + lines) + "\n"
