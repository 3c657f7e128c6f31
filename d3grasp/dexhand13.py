"""The Paxini DexHand13's vocabulary: joint, link and pad names, their fixed orders, and which
joints and pads belong to which finger. Authoring, the environment, the rule-based baseline, the
plots and the tests index with these (the Warp kernels keep their own pad count, checked equal in
the tests: kernels import nothing of the package).

Joint order (the policy's): index 0..3, middle 0..3, ring 0..3, thumb 0..3; joint ``4 f`` is finger
``f``'s abduction (or the thumb's rotation), joints ``4 f + 1 .. 4 f + 3`` its flexion joints,
proximal to distal. Pad order: index 0, 1, 2, middle 0, 1, 2, ring 0, 1, 2, thumb 0, 1.
"""

from __future__ import annotations

FINGERS: tuple[str, ...] = ("index", "middle", "ring", "thumb")
NUM_FINGERS = len(FINGERS)
JOINTS_PER_FINGER = 4
NUM_FINGER_JOINTS = NUM_FINGERS * JOINTS_PER_FINGER

FINGER_JOINT_NAMES: tuple[str, ...] = tuple(
    f"right_{f}_joint_{i}" for f in FINGERS for i in range(JOINTS_PER_FINGER)
)
"""The 16 actuated finger joints, index 0..3, middle 0..3, ring 0..3, thumb 0..3 (the policy's order)."""

ABDUCTION_JOINTS: tuple[int, ...] = tuple(JOINTS_PER_FINGER * f for f in range(NUM_FINGERS))
"""Each finger's first joint: abduction (the thumb's: rotation towards the palm)."""

FLEXION_JOINTS: tuple[int, ...] = tuple(
    JOINTS_PER_FINGER * f + k for f in range(NUM_FINGERS) for k in range(1, JOINTS_PER_FINGER)
)
"""Each finger's three flexion joints, proximal to distal."""


def finger_joints(finger: int) -> range:
    """Joint indices of finger ``finger`` (0 index .. 3 thumb): abduction, then three flexion joints."""
    return range(JOINTS_PER_FINGER * finger, JOINTS_PER_FINGER * (finger + 1))


ROOT_JOINT_NAMES: tuple[str, ...] = ("root_x", "root_y", "root_z", "root_rz", "root_ry", "root_rx")
"""The driven 6-DoF root chain, world to palm, in chain order."""

ROOT_LINK_NAMES: tuple[str, ...] = (
    "root_x_link",
    "root_y_link",
    "root_z_link",
    "root_rz_link",
    "root_ry_link",
)
"""Massive but collider-free intermediate bodies of the root chain (children of the first five joints)."""

PALM_LINK = "right_palm_link"

LINK_NAMES: tuple[str, ...] = (PALM_LINK,) + tuple(
    f"right_{f}_link_{i}" for f in FINGERS for i in range(JOINTS_PER_FINGER)
)
"""The 17 hand links of the spec (palm first, then each finger's links 0..3)."""
NUM_LINKS = len(LINK_NAMES)

PAD_NAMES: tuple[str, ...] = tuple(f"right_{f}_tactile_link_{i}" for f in FINGERS[:3] for i in range(3)) + (
    "right_thumb_tactile_link_0",
    "right_thumb_tactile_link_1",
)
"""The 11 tactile pads, index 0,1,2, middle 0,1,2, ring 0,1,2, thumb 0,1 (proximal to distal)."""
NUM_PADS = len(PAD_NAMES)

FINGER_PADS: tuple[tuple[int, ...], ...] = ((0, 1, 2), (3, 4, 5), (6, 7, 8), (9, 10))
"""Pad indices of each finger (index, middle, ring, thumb)."""

PAD_LINK: tuple[int, ...] = (1, 2, 3, 1, 2, 3, 1, 2, 3, 2, 3)
"""The finger link (1..3, proximal to distal) each pad sits on; the thumb's first flexion link
carries no pad, so its two pads are on links 2 and 3."""

THUMB_PADS: tuple[int, ...] = FINGER_PADS[3]
OPPOSING_PADS: tuple[int, ...] = FINGER_PADS[0] + FINGER_PADS[1] + FINGER_PADS[2]
"""The pads of the fingers that oppose the thumb."""


def pad_finger(pad: str | int) -> str:
    """Finger (``"index"``, ``"middle"``, ``"ring"`` or ``"thumb"``) that carries a pad (name or index)."""
    name = PAD_NAMES[pad] if isinstance(pad, int) else pad
    for finger in FINGERS:
        if name.startswith(f"right_{finger}_tactile_link_"):
            return finger
    raise ValueError(f"unknown pad {pad!r}; expected one of {PAD_NAMES}")


def pad_groups() -> dict[str, list[int]]:
    """Pad indices (into :data:`PAD_NAMES`) of the thumb and of the opposing fingers, for rewards."""
    return {"thumb": list(THUMB_PADS), "fingers": list(OPPOSING_PADS)}
