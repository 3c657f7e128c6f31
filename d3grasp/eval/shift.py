"""Brittleness: how many grasp outcomes a whole-scene shift of a millimetre flips.

Moving the object and the hand together over the infinite table plane (``GraspEnvConfig.scene_shift``)
changes nothing physical, so an outcome that changes under it was decided by round-off at a contact
onset, not by the grasp (docs/studies/millimetre.md). ``python -m d3grasp.bench shift`` evaluates the
rule-based baseline at the true pose on a split, unshifted and shifted by ``mm`` along +x, -x, +y
and -y, and prints the share of objects (and of episodes, object x seed) whose outcome, the pair
(s_lift, s_disturb), differs from the unshifted one under at least one shift.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

__all__ = ["SHIFT_DIRECTIONS", "ShiftReport", "outcome_changes", "run_shift_benchmark"]

SHIFT_DIRECTIONS: dict[str, tuple[float, float]] = {
    "+x": (1.0, 0.0),
    "-x": (-1.0, 0.0),
    "+y": (0.0, 1.0),
    "-y": (0.0, -1.0),
}
"""The four horizontal directions the scene is moved along (unit vectors, scaled by the shift)."""

Outcome = tuple[bool, bool]  # (s_lift, s_disturb)
EpisodeKey = tuple[str, int]  # (object, seed)


def outcomes(records: Sequence[dict[str, Any]], seed: int) -> dict[EpisodeKey, Outcome]:
    """``(object, seed) -> (s_lift, s_disturb)`` of one evaluation's episode records (one episode
    per object; ``ValueError`` on an object met twice)."""
    out: dict[EpisodeKey, Outcome] = {}
    for r in records:
        key = (str(r["object"]), seed)
        if key in out:
            raise ValueError(f"object {key[0]} has two episodes at seed {seed}: give one per object")
        out[key] = (bool(r["s_lift"]), bool(r["s_disturb"]))
    return out


@dataclass
class ShiftReport:
    """Outcomes unshifted and under each shift, by (object, seed)."""

    shift_m: float
    reference: dict[EpisodeKey, Outcome]
    shifted: dict[str, dict[EpisodeKey, Outcome]] = field(default_factory=dict)  # direction -> outcomes

    def changed(self, direction: str | None = None) -> set[EpisodeKey]:
        """Episodes whose outcome differs from the unshifted one under ``direction`` (None: any)."""
        dirs = [direction] if direction is not None else list(self.shifted)
        return {k for d in dirs for k in outcome_changes(self.reference, self.shifted[d])}

    def changed_objects(self, direction: str | None = None) -> set[str]:
        return {obj for obj, _ in self.changed(direction)}

    def rates(self, outcomes: dict[EpisodeKey, Outcome]) -> tuple[float, float]:
        n = max(1, len(outcomes))
        return (
            100.0 * sum(v[0] for v in outcomes.values()) / n,
            100.0 * sum(v[1] for v in outcomes.values()) / n,
        )

    def summary(self) -> str:
        objects = {obj for obj, _ in self.reference}
        seeds = sorted({s for _, s in self.reference})
        n_ep, n_obj = len(self.reference), len(objects)
        lines = [
            f"whole scene shifted by {1e3 * self.shift_m:g} mm (object and hand together), rule at the true "
            f"pose, {n_obj} objects x seeds {seeds}",
            f"{'shift':<10}{'s_lift %':>10}{'s_disturb %':>13}"
            f"{'episodes changed':>19}{'objects changed':>18}",
        ]
        lift, hold = self.rates(self.reference)
        lines.append(f"{'none':<10}{lift:>10.1f}{hold:>13.1f}{'':>19}{'':>18}")
        for d, out in self.shifted.items():
            lift, hold = self.rates(out)
            ep, ob = len(self.changed(d)), len(self.changed_objects(d))
            lines.append(f"{d:<10}{lift:>10.1f}{hold:>13.1f}{f'{ep} / {n_ep}':>19}{f'{ob} / {n_obj}':>18}")
        ep, ob = self.changed(), self.changed_objects()
        lines.append(
            f"changed under any shift: {len(ob)} of {n_obj} objects "
            f"({100.0 * len(ob) / max(1, n_obj):.1f}%), "
            f"{len(ep)} of {n_ep} episodes ({100.0 * len(ep) / max(1, n_ep):.1f}%)"
        )
        if ob:
            lines.append("objects: " + ", ".join(sorted(ob)))
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        def rows(out: dict[EpisodeKey, Outcome]) -> list[dict[str, Any]]:
            return [
                {"object": o, "seed": s, "s_lift": v[0], "s_disturb": v[1]}
                for (o, s), v in sorted(out.items())
            ]

        return {
            "shift_m": self.shift_m,
            "reference": rows(self.reference),
            "shifted": {d: rows(out) for d, out in self.shifted.items()},
            "changed_objects": sorted(self.changed_objects()),
            "changed_episodes": [list(k) for k in sorted(self.changed())],
        }


def outcome_changes(
    reference: dict[EpisodeKey, Outcome], shifted: dict[EpisodeKey, Outcome]
) -> set[EpisodeKey]:
    """The episodes of ``shifted`` whose outcome differs from ``reference``'s twin."""
    return {k for k, v in shifted.items() if reference.get(k) != v}


def run_shift_benchmark(
    shift_m: float = 0.001,
    seeds: Sequence[int] = (0,),
    split: str = "test",
    objects: str = "diverse",
    num_envs: int = 16,
    workers: int | None = None,
    overrides: dict[str, Any] | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> ShiftReport:
    """Evaluate the rule at the true pose unshifted and under the four shifts, every seed."""
    from d3grasp.eval.evaluate import EvalSettings, evaluate
    from d3grasp.parallel import default_workers
    from d3grasp.policies import BASELINE

    workers = workers or default_workers()
    extra = dict(overrides or {})
    if "scene_shift" in extra:
        raise ValueError("scene_shift is what this benchmark sets: give the shift with --mm")
    by_shift: dict[str, dict[EpisodeKey, Outcome]] = {}
    for name, (ux, uy) in {"none": (0.0, 0.0), **SHIFT_DIRECTIONS}.items():
        merged: dict[EpisodeKey, Outcome] = {}
        for seed in seeds:
            settings = EvalSettings(
                checkpoint=BASELINE,
                objects=objects,
                split=split,
                seed=seed,
                num_envs=num_envs,
                perception="oracle",
                env_overrides={**extra, "scene_shift": (shift_m * ux, shift_m * uy)},
            )
            log(f"[bench shift] {name}, seed {seed}")
            result = evaluate(settings, progress=progress, log=log, workers=workers)
            merged |= outcomes(result.runs[BASELINE], seed)
        by_shift[name] = merged
    reference = by_shift.pop("none")
    return ShiftReport(shift_m, reference, by_shift)
