"""The three archetypal grasp types and their pre-grasp palm poses, derived from the hand's geometry.

Palm frame (``assets_usd/hands/README.md``): fingers along +x, thumb on -y, palmar side +z. The
palm collider's front face is at x = 0.138 m and its palmar face at z = 0.0335 m; the fingers
hinge at x = 0.135 m and, open, reach z ≈ 0.014 m on the palmar side. Flexing fingers sweep an
object towards the wrist (-x), so every grasp puts a *backstop* on the object's -x side:

* ``top`` (power grasp, palm down): the object stands just in front of the palm's front face
  (2 mm gap) under the open fingers, its top 17 mm below the palm plane, offset 2 cm towards the
  thumb. Closing fingers press it against the palm's front face; the thumb closes across its -y
  side. Measured with the scripted closure on a 9.5 x 3.4 x 6.6 cm box: 8 of 9 placements within
  ±1.5 cm of this one lifted it by 0.1 m.
* ``side`` (wrap, palm vertical): the same hand-object relation turned 90° about the fingers'
  axis, so the fingers wrap horizontally and do not meet the table; the hand is raised until
  its lower edge clears the table, which limits it to objects tall enough to reach the fingers.
* ``pinch`` (precision, palm down): the object between the thumb tip and the index/middle tips,
  which meet near x = 0.12 m, y = -0.033 m, z = 0.05 m when closed; for small objects.

The grasp type only fixes the root pose and which fingers the scripted baseline closes; the
policy always drives all 16 joints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d3grasp.authoring.hand import matrix_to_quat_xyzw

PALM_FRONT_X = 0.138  # palm collider front face (m, palm frame)
PALM_HALF_WIDTH = 0.0515  # palm collider half-extent along y (m)
TABLE_CLEARANCE = 0.006  # m kept between the lowest hand collider and the table at the grasp pose


@dataclass(frozen=True)
class GraspType:
    name: str
    near_face_x: float  # palm-frame x of the object's face nearest the wrist
    lateral_y: float  # preferred palm-frame y of the object's centre (negative: thumb side)
    top_z: float  # palm-frame z of the object's face nearest the palm
    baseline_fingers: tuple[int, ...]  # fingers (0 index, 1 middle, 2 ring, 3 thumb) the baseline closes
    palm_vertical: bool = False


GRASP_TYPES: dict[str, GraspType] = {
    "top": GraspType(
        "top", near_face_x=PALM_FRONT_X + 0.002, lateral_y=-0.02, top_z=0.017, baseline_fingers=(0, 1, 2, 3)
    ),
    "side": GraspType(
        "side",
        near_face_x=PALM_FRONT_X + 0.002,
        lateral_y=-0.02,
        top_z=0.017,
        baseline_fingers=(0, 1, 2, 3),
        palm_vertical=True,
    ),
    "pinch": GraspType("pinch", near_face_x=0.10, lateral_y=-0.033, top_z=0.035, baseline_fingers=(0, 1, 3)),
}
GRASP_NAMES: tuple[str, ...] = tuple(GRASP_TYPES)

# Palm orientation for zero yaw: columns are the palm's x, y, z axes in the world.
_R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # palm faces -z
_R_SIDE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # palm faces +y, thumb up


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class GraspPose:
    grasp: str
    palm_pos: np.ndarray  # (3,) world, at the grasp
    palm_quat: np.ndarray  # (4,) xyzw
    approach_dir: np.ndarray  # (3,) unit world direction the palm moves along during the approach
    feasible: bool


def side_feasible(extents: np.ndarray, table_height: float = 0.0) -> bool:
    """Whether the side wrap can reach the object without the hand's lower edge meeting the table."""
    obj_z = table_height + 0.5 * float(extents[2])
    lateral = max(GRASP_TYPES["side"].lateral_y, PALM_HALF_WIDTH + TABLE_CLEARANCE - (obj_z - table_height))
    return lateral <= 0.03


def choose_grasp(extents: np.ndarray, allowed: tuple[str, ...], table_height: float = 0.0) -> str:
    """Rule on size and shape: small → pinch, tall → side wrap, otherwise top power grasp."""
    ex = np.asarray(extents, dtype=np.float64)
    candidates = []
    if max(ex) < 0.05:
        candidates.append("pinch")
    if ex[2] >= max(ex[0], ex[1]) and side_feasible(ex, table_height):
        candidates.append("side")
    candidates.append("top")
    for name in candidates:
        if name in allowed:
            return name
    return allowed[0]


def grasp_pose(
    grasp: str, obj_pos: np.ndarray, obj_yaw: float, extents: np.ndarray, table_height: float = 0.0
) -> GraspPose:
    """Palm pose for grasping an upright object at ``obj_pos`` (its bounding-box centre) with yaw ``obj_yaw``.

    The palm's x axis is aligned with the object's shorter horizontal side, so the fingers wrap
    its narrow dimension.
    """
    g = GRASP_TYPES[grasp]
    ex = np.asarray(extents, dtype=np.float64)
    short_is_x = ex[0] <= ex[1]
    along = ex[0] if short_is_x else ex[1]  # extent along the palm's x
    across = ex[1] if short_is_x else ex[0]  # extent along the other horizontal axis
    yaw = obj_yaw + (0.0 if short_is_x else 0.5 * math.pi)
    yaw = math.atan2(math.sin(yaw), math.cos(yaw))
    # The two yaws that align the palm with the short side are equivalent for the object;
    # pick the one facing +x so the hand never reaches across itself.
    if abs(yaw) > 0.5 * math.pi:
        yaw -= math.copysign(math.pi, yaw)
    feasible = True
    if g.palm_vertical:
        r = _rz(yaw) @ _R_SIDE
        depth = across  # extent along the palm normal (horizontal)
        obj_height = float(obj_pos[2]) - table_height
        lateral = max(g.lateral_y, PALM_HALF_WIDTH + TABLE_CLEARANCE - obj_height)
        feasible = lateral <= 0.03
        offset = np.array([g.near_face_x + 0.5 * along, lateral, g.top_z + 0.5 * depth])
    else:
        r = _rz(yaw) @ _R_DOWN
        if grasp == "pinch":
            offset = np.array([g.near_face_x + 0.5 * along, g.lateral_y, g.top_z + 0.5 * ex[2]])
        else:
            offset = np.array([g.near_face_x + 0.5 * along, g.lateral_y, g.top_z + 0.5 * ex[2]])
    palm_pos = np.asarray(obj_pos, dtype=np.float64) - r @ offset
    return GraspPose(
        grasp=grasp,
        palm_pos=palm_pos,
        palm_quat=matrix_to_quat_xyzw(r),
        approach_dir=r[:, 2].copy(),
        feasible=feasible,
    )
