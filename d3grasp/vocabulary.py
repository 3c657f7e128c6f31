"""The words the package counts and tabulates by: object kinds, size bins, grasp types, episode
phases and success metrics. One place, so the environment, training logs, curves and evaluation
tables cannot disagree on a spelling or an order."""

from __future__ import annotations

KINDS: tuple[str, ...] = ("rigid", "deformable")
"""Object kinds of a library (``AssetEntry.kind``)."""

SIZE_BINS: dict[str, tuple[float, float]] = {
    "small": (0.03, 0.06),
    "medium": (0.06, 0.12),
    "large": (0.12, 0.20),
}
"""Size bins, smallest first, by the longest side of the object's bounding box in its rest frame,
metres. Lower bound inclusive, upper bound exclusive (the last bin includes its upper bound). The
DexHand13 spans ~0.14 m from thumb base to finger tips, so 20 cm is the largest object it can
wrap; below 3 cm the pads (2.3-3.5 cm) cannot get two opposing contacts."""

GRASP_TYPES: tuple[str, ...] = ("top", "side", "pinch")
"""The three archetypal grasp types (``d3grasp.envs.grasps``): top power grasp, side wrap, pinch."""

PHASES: tuple[str, ...] = ("approach", "grasp", "lift", "hold", "disturb", "release")
"""Episode phases in order (durations in ``PhaseConfig``)."""

METRICS: tuple[str, ...] = ("s_grasp", "s_lift", "s_disturb")
"""The paper's success metrics, scored per episode."""
