"""Pose estimators: what the grasp planner is told of each world's freshly placed object.

One interface, :class:`PoseEstimator`, and a registry, :data:`ESTIMATORS`, of three:

- ``oracle``: the simulator's true pose (the reference for perfect localisation);
- ``box_fit``: the camera's depth image fitted with a box (d3grasp.vision.localisation), its centre,
  yaw and sides as seen;
- ``footprint``: that fit registered to the object's known footprint (d3grasp.vision.footprint),
  the body's own pose (the paper's protocol: the camera registered to the object's footprint).

The environment makes the configured one at construction (:func:`estimator_name`: ``perception``
and ``camera.register_footprint``, or ``pose_estimator`` by name) and calls ``estimate`` once per
world and episode, at reset, after the object is placed and before the hand is. A new estimator is
a class with ``estimate``, registered in ``ESTIMATORS``; ``--set
pose_estimator=NAME`` selects it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from d3grasp.geometry import wrap_angle

if TYPE_CHECKING:
    from d3grasp.envs.config import CameraConfig
    from d3grasp.vision.perception import CameraPerception

# A box fit that failed (nothing seen) plans with a 6 cm cube at the fit's centre.
FALLBACK_EXTENTS = np.full(3, 0.06)


@dataclass
class PlacedObject:
    """One world's object as the simulator placed it: what an estimator may look at (the scene, by
    rendering it) and what scores its error (the truth)."""

    world: int
    body: int  # the object's body index (-1: soft)
    pos: np.ndarray  # (3,) true position of the body origin (the box centre)
    quat: np.ndarray  # (4,) xyzw, a turn about z by ``yaw``
    yaw: float
    extents: np.ndarray  # (3,) the object's box sides in its own frame
    particles: tuple[int, np.ndarray] | None = None  # a soft object's (first index, (n, 3) nodes)


@dataclass
class PlanningPose:
    """What the planner is told: a position, a yaw and box sides, whether they came from a sensor
    (``estimated``: the episode records the error and the correction) and whether they are the
    body's own pose (``registered``: the library's grasps are placed as planned) rather than a box
    seen from outside (the grasps are fitted to the box); ``record``: the episode's ``loc_*`` fields."""

    pos: np.ndarray
    yaw: float
    extents: np.ndarray
    estimated: bool
    registered: bool
    record: dict[str, Any] = field(default_factory=dict)


class PoseEstimator(Protocol):
    """Estimates a placed object's pose for the planner (module docstring)."""

    def estimate(self, state: Any, placed: PlacedObject) -> PlanningPose: ...


class OracleEstimator:
    """The true pose: no sensor, no error."""

    def estimate(self, state: Any, placed: PlacedObject) -> PlanningPose:
        return PlanningPose(placed.pos, placed.yaw, placed.extents, estimated=False, registered=False)


class BoxFitEstimator:
    """The camera's box fit as seen: its centre, yaw and sides (``camera.register_footprint=false``)."""

    def __init__(self, perception: CameraPerception) -> None:
        self.perception = perception

    def observe(self, state: Any, placed: PlacedObject) -> tuple[Any, dict[str, Any]]:
        """The camera's estimate of ``placed`` and its error record against the truth."""
        from d3grasp.vision.perception import localisation_error

        soft = placed.particles is not None
        est = self.perception.observe(
            state,
            placed.world,
            placed.body,
            None if soft else np.concatenate([placed.pos, placed.quat]),
            placed.particles,
            fallback_extents=FALLBACK_EXTENTS,
        )
        err = localisation_error(est, placed.pos, placed.yaw, placed.extents)
        return est, {"perception": "camera", "loc_ok": bool(est.ok), **err.as_record()}

    def estimate(self, state: Any, placed: PlacedObject) -> PlanningPose:
        est, record = self.observe(state, placed)
        return PlanningPose(est.centre, est.yaw, est.extents, estimated=True, registered=False, record=record)


class FootprintEstimator(BoxFitEstimator):
    """The box fit registered to the object's footprint (d3grasp.vision.footprint.register): the
    body's position and yaw, and its footprint's sides; the fit as seen when it saw nothing."""

    def __init__(self, perception: CameraPerception, footprints: Sequence[Any], heights: bool) -> None:
        super().__init__(perception)
        self.footprints = footprints  # per world, in the object's own frame
        self.heights = heights  # register with the seen heights too (camera.register_heights)

    def estimate(self, state: Any, placed: PlacedObject) -> PlanningPose:
        from d3grasp.vision.footprint import register

        est, record = self.observe(state, placed)
        if not est.ok:  # nothing seen to register: the fit's fallback box
            return PlanningPose(est.centre, est.yaw, est.extents, True, False, record)
        xy, body_yaw, body_ex = register(
            est.footprint,
            self.footprints[placed.world],
            heights=est.footprint_heights if self.heights else None,
        )
        pos = np.array([xy[0], xy[1], est.centre[2]])  # the body origin is the box's centre: half its height
        record.update(
            loc_registered_xy=float(np.linalg.norm(xy - np.asarray(placed.pos)[:2])),
            loc_registered_yaw=float(abs(wrap_angle(body_yaw - placed.yaw))),
        )
        extents = np.array([body_ex[0], body_ex[1], est.extents[2]])
        return PlanningPose(pos, body_yaw, extents, estimated=True, registered=True, record=record)


@dataclass
class EstimatorScene:
    """What an estimator may be built from: the Newton model, the environment's layout (object bodies,
    particles), each world's object id, the camera's settings and the environment's seed."""

    model: Any
    layout: Any
    object_ids: Sequence[str]
    camera: CameraConfig
    seed: int

    def camera_perception(self) -> CameraPerception:
        from d3grasp.vision.perception import CameraPerception

        return CameraPerception(
            self.model, self.model.body_world.numpy(), self.layout.object_body, self.camera, self.seed
        )

    def footprints(self) -> list[Any]:
        """Each world's object footprint in its own frame (computed once per object)."""
        from d3grasp.vision.footprint import footprint_of_pieces, object_pieces

        seen: dict[str, Any] = {}
        out = []
        for w, oid in enumerate(self.object_ids):
            if oid not in seen:
                seen[oid] = footprint_of_pieces(object_pieces(self.model, self.layout, w))
            out.append(seen[oid])
        return out


ESTIMATORS: dict[str, Callable[[EstimatorScene], PoseEstimator]] = {
    "oracle": lambda scene: OracleEstimator(),
    "box_fit": lambda scene: BoxFitEstimator(scene.camera_perception()),
    "footprint": lambda scene: FootprintEstimator(
        scene.camera_perception(), scene.footprints(), scene.camera.register_heights
    ),
}
"""The pose estimators by name, each made from an :class:`EstimatorScene`."""


def estimator_name(perception: str, register_footprint: bool, pose_estimator: str | None = None) -> str:
    """The estimator a configuration selects: ``pose_estimator`` when given, else the true pose for
    ``perception="oracle"`` and the camera's fit, registered or not, for ``"camera"``."""
    if pose_estimator is not None:
        if pose_estimator not in ESTIMATORS:
            raise ValueError(f"unknown pose_estimator '{pose_estimator}'; known: {list(ESTIMATORS)}")
        return pose_estimator
    if perception == "oracle":
        return "oracle"
    return "footprint" if register_footprint else "box_fit"


def make_pose_estimator(name: str, scene: EstimatorScene) -> PoseEstimator:
    """The registered estimator ``name`` for ``scene``."""
    return ESTIMATORS[name](scene)
