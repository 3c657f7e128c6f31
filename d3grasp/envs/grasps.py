"""The three archetypal grasp types and their pre-grasp palm poses, derived from the hand's geometry.

Palm frame (``assets_usd/hands/README.md``): fingers along +x, thumb on -y, palmar side +z. The
palm collider's front face is at x = 0.138 m and its palmar face at z = 0.0335 m; the fingers
hinge at x = 0.135 m and, open, lie in the palm plane (z -0.025..0.004). Curling all three
flexion joints together (the baseline's constant-speed closing) sweeps a fingertip through
(0.22, 0.07) at 0.4 rad, down to z ≈ 0.09 at x ≈ 0.16-0.18 near 0.8 rad and back to (0.12, 0.056)
at 1.3 rad, so flexing fingers pull an object towards the wrist (-x) and every grasp puts a
*backstop* on the object's -x side. The thumb (base x 0.04, y -0.037) opens sideways (tip at
y -0.18) and swings under the front of the palm: tip near (0.12-0.16, -0.04..-0.06, 0.06-0.10).

* ``top`` (hook, palm down): the object stands just in front of the palm's front face (2 mm gap),
  its top 17 mm below the palm plane, so the front face backs 16 mm of it; 2 cm towards the
  thumb. The fingers hook over its far (+x) face, the thumb closes across its -y side.
* ``side`` (wrap, palm vertical): the same relation turned 90° about the fingers' axis, thumb up;
  the hand is raised until its lower edge clears the table. On small objects the fingers close
  round the object and cage it.
* ``pinch`` (precision, palm down): the object under the front of the palm between the thumb
  tip and the index/middle tips, which meet near (0.12, -0.033, 0.05) when closed.

Measured (rule-based baseline, per-joint stopping, randomisation off, one episode per object and
type forced, as ``d3grasp-eval --checkpoint baseline --grasp-types TYPE`` runs it; lift = s_lift,
16 train objects: 5 small, 7 medium, 4 large):

==========  =============  ==============  ============  ===========
type        small          medium          large         all
==========  =============  ==============  ============  ===========
top         0/5            3/7             3/4           6/16
side        2/5            1/7             1/4           4/16
pinch       0/5            2/7             0/4           2/16
==========  =============  ==============  ============  ===========

Why they fail: objects lower than ~5 cm put the curling fingertips on the table (tip pads read
~10 N from the table at 0.2-0.4 rad, which stops the baseline's joints) before they reach round
the object; objects wider than ~7 cm along the palm's x are beyond the hook; bounding-box
placement misses shaped objects (a bottle's neck). Moving the object 2 cm lower in the hand
(top_z 0.037) lifted 2/16 instead of 6/16. :func:`choose_grasp` picks per object the type that
measured best for its size class. On 16 other train objects (6 small, 6 medium, 4 large; 6 soft)
the rule lifted 6/16 (small 2/6, medium 4/6, large 0/4; rigid 5/10, soft 1/6), 5/16 held under
the disturbance.

The grasp type only fixes the root pose and which fingers the scripted baseline closes; the
policy always drives all 16 joints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from d3grasp.geometry import matrix_to_quat_xyzw_nonneg_w, quat_xyzw_to_matrix, rot_y, rot_z
from d3grasp.vocabulary import GRASP_TYPES

PALM_FRONT_X = 0.138  # palm collider front face (m, palm frame)
PALM_FACE_Z = 0.0335  # palm collider palmar face (m, palm frame)
PALM_HALF_WIDTH = 0.0515  # palm collider half-extent along y (m)
TABLE_CLEARANCE = 0.006  # m kept between the lowest hand collider and the table at the grasp pose
DROP_GAP = 0.001  # m between an object's lowest point and the table where an episode places it


def rest_height(extents: np.ndarray) -> float:
    """Height of an upright object's centre (its body origin) above the table as the environment
    places it: half its height, DROP_GAP up. The planner's trials place it the same way."""
    return 0.5 * float(extents[2]) + DROP_GAP


@dataclass(frozen=True)
class GraspType:
    name: str
    near_face_x: float  # palm-frame x of the object's face nearest the wrist
    lateral_y: float  # preferred palm-frame y of the object's centre (negative: thumb side)
    top_z: float  # palm-frame z of the object's face nearest the palm
    baseline_fingers: tuple[int, ...]  # fingers (0 index, 1 middle, 2 ring, 3 thumb) the baseline closes
    palm_vertical: bool = False


GRASPS: dict[str, GraspType] = {
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
assert tuple(GRASPS) == GRASP_TYPES  # the vocabulary's order is the grasp id of observations and logs

# Palm orientation for zero yaw: columns are the palm's x, y, z axes in the world.
_R_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # palm faces -z
_R_SIDE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # palm faces +y, thumb up


@dataclass(frozen=True)
class GraspPose:
    grasp: str
    palm_pos: np.ndarray  # (3,) world, at the grasp
    palm_quat: np.ndarray  # (4,) xyzw
    approach_dir: np.ndarray  # (3,) unit world direction the palm moves along during the approach
    feasible: bool
    preshape: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # abduction (rad) per finger


def side_feasible(extents: np.ndarray, table_height: float = 0.0) -> bool:
    """Whether the side wrap can reach the object without the hand's lower edge meeting the table."""
    obj_z = table_height + 0.5 * float(extents[2])
    lateral = max(GRASPS["side"].lateral_y, PALM_HALF_WIDTH + TABLE_CLEARANCE - (obj_z - table_height))
    return lateral <= 0.03


SMALL_MAX_EXTENT = 0.05  # m: below this largest extent only the side wrap's closing fingers cage the object
TOP_MAX_ALONG = 0.07  # m: the top hook's fingers reach round a short horizontal side up to this
TOP_MIN_HEIGHT = 0.05  # m: lower objects put the curling fingertips on the table before they hook


def choose_grasp(extents: np.ndarray, allowed: tuple[str, ...], table_height: float = 0.0) -> str:
    """Rule on size and shape, from the baseline's measured success per type (module docstring).

    Small (largest extent < 5 cm) → side wrap; tall enough (≥ 5 cm) with a short horizontal side
    ≤ 7 cm → top hook; anything else (wide or flat) → pinch. Falls back along top, pinch, side to
    the first allowed type.
    """
    del table_height  # the rule is on the object alone; kept for a table-aware rule later
    ex = np.asarray(extents, dtype=np.float64)
    if ex.shape != (3,) or not np.all(ex > 0):
        raise ValueError(f"extents must be three positive lengths, got {extents!r}")
    if float(ex.max()) < SMALL_MAX_EXTENT:
        preferred = "side"
    elif float(ex[2]) >= TOP_MIN_HEIGHT and float(min(ex[0], ex[1])) <= TOP_MAX_ALONG:
        preferred = "top"
    else:
        preferred = "pinch"
    for name in (preferred, "top", "pinch", "side"):
        if name in allowed:
            return name
    return allowed[0]


@dataclass(frozen=True)
class ObjectGrasp:
    """A grasp in the object's frame: origin at the centre of its bounding box as it rests on the
    table, z up, x and y along its first two extents (the manifest's ``extents``). Placed with the
    object's pose at run time (:meth:`place`), whatever estimated that pose (oracle or camera).

    ``preshape`` is the abduction of the four fingers' first joints (rad; index, middle, ring,
    thumb) the hand opens with and keeps: the type's posture before the fingers close."""

    grasp: str
    palm_pos: np.ndarray  # (3,) palm origin in the object frame
    palm_quat: np.ndarray  # (4,) xyzw, palm orientation in the object frame
    approach_dir: np.ndarray  # (3,) unit direction the palm moves along in the approach (object frame)
    feasible: bool = True
    preshape: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def place(self, obj_pos: np.ndarray, obj_yaw: float) -> GraspPose:
        """World pose of this grasp for an object at ``obj_pos`` (box centre) with yaw ``obj_yaw``."""
        r = rot_z(obj_yaw)
        return GraspPose(
            grasp=self.grasp,
            palm_pos=np.asarray(obj_pos, dtype=np.float64) + r @ self.palm_pos,
            palm_quat=matrix_to_quat_xyzw_nonneg_w(r @ quat_xyzw_to_matrix(self.palm_quat)),
            approach_dir=r @ self.approach_dir,
            feasible=self.feasible,
            preshape=self.preshape,
        )

    def to_json(self) -> dict:
        return {
            "grasp": self.grasp,
            "palm_pos": [float(x) for x in self.palm_pos],
            "palm_quat": [float(x) for x in self.palm_quat],
            "approach_dir": [float(x) for x in self.approach_dir],
            "preshape": [float(x) for x in self.preshape],
        }

    @classmethod
    def from_json(cls, d: dict) -> ObjectGrasp:
        if d.get("grasp") not in GRASPS:
            raise ValueError(f"unknown grasp type {d.get('grasp')!r}; known: {list(GRASPS)}")
        pos, quat, app = (
            np.asarray(d[k], dtype=np.float64) for k in ("palm_pos", "palm_quat", "approach_dir")
        )
        pre = tuple(float(x) for x in d.get("preshape", (0.0, 0.0, 0.0, 0.0)))
        if pos.shape != (3,) or quat.shape != (4,) or app.shape != (3,) or len(pre) != 4:
            raise ValueError("a grasp needs palm_pos (3), palm_quat (4), approach_dir (3), preshape (4)")
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat)) and np.linalg.norm(quat) > 0.5):
            raise ValueError("a grasp's palm_pos and palm_quat must be finite, the quaternion of unit length")
        quat, app = quat / np.linalg.norm(quat), app / max(float(np.linalg.norm(app)), 1e-9)
        return cls(d["grasp"], pos, quat, app, True, pre)


def object_grasp(
    grasp: str,
    extents: np.ndarray,
    rest_height: float,
    *,
    long_side: bool = False,
    near_face_x: float | None = None,
    lateral_y: float | None = None,
    top_z: float | None = None,
    pitch: float = 0.0,
    preshape: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0),
) -> ObjectGrasp:
    """The grasp type's palm pose in the object frame (:class:`ObjectGrasp`) for an upright object of
    ``extents`` whose centre rests ``rest_height`` above the table.

    By default the palm's x axis lies along the object's shorter horizontal side, so the fingers wrap
    its narrow dimension (``long_side``: along the longer one), and the object sits where the type's
    constants put it (:data:`GRASPS`); ``near_face_x``, ``lateral_y`` and ``top_z`` place it elsewhere
    in the palm frame (the planner's candidates, ``d3grasp.planner``). ``pitch`` turns the hand about
    the palm's y axis through the object's centre (rad; > 0 raises the finger tips of a palm-down
    hand away from the table).
    """
    g = GRASPS[grasp]
    ex = np.asarray(extents, dtype=np.float64)
    short_is_x = (ex[0] <= ex[1]) != bool(long_side)
    along = ex[0] if short_is_x else ex[1]  # extent along the palm's x
    across = ex[1] if short_is_x else ex[0]  # extent along the other horizontal axis
    yaw = 0.0 if short_is_x else 0.5 * math.pi
    near_x = g.near_face_x if near_face_x is None else float(near_face_x)
    lat = g.lateral_y if lateral_y is None else float(lateral_y)
    top = g.top_z if top_z is None else float(top_z)
    feasible = True
    if g.palm_vertical:
        r = rot_z(yaw) @ _R_SIDE
        depth = across  # extent along the palm normal (horizontal)
        # Palm y points down: the hand's lower edge clears the table when the object's centre is
        # high enough in the palm (lateral y no less than the edge's reach below it).
        lateral = max(lat, PALM_HALF_WIDTH + TABLE_CLEARANCE - rest_height)
        feasible = lateral <= 0.03
        offset = np.array([near_x + 0.5 * along, lateral, top + 0.5 * depth])
    else:
        r = rot_z(yaw) @ _R_DOWN
        # Palm down (top and pinch): the type's own placement constants differ, the rule does not.
        offset = np.array([near_x + 0.5 * along, lat, top + 0.5 * ex[2]])
    if pitch:
        r = r @ rot_y(pitch)
    return ObjectGrasp(
        grasp=grasp,
        palm_pos=-(r @ offset),
        palm_quat=matrix_to_quat_xyzw_nonneg_w(r),
        approach_dir=r[:, 2].copy(),
        feasible=feasible,
        preshape=tuple(float(x) for x in preshape),
    )


def grasp_pose(
    grasp: str, obj_pos: np.ndarray, obj_yaw: float, extents: np.ndarray, table_height: float = 0.0
) -> GraspPose:
    """Palm pose for grasping an upright object at ``obj_pos`` (its bounding-box centre) with yaw
    ``obj_yaw`` by the type's geometric rule (:func:`object_grasp` with no variation).

    Of the two yaws that put the palm's x along the object's short side, the one whose fingers point
    towards +x is taken, so the hand never reaches across itself.
    """
    og = object_grasp(grasp, extents, float(obj_pos[2]) - table_height)
    pose = og.place(obj_pos, obj_yaw)
    fingers = quat_xyzw_to_matrix(pose.palm_quat)[:, 0]
    if fingers[0] < -1e-9 or (abs(fingers[0]) <= 1e-9 and fingers[1] < 0.0):
        pose = og.place(obj_pos, obj_yaw + math.pi)
    return pose
