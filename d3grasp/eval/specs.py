"""What an evaluation runs: its settings, the objects it selects and each controller's run (the
checkpoint, the task it was trained on, its action interface), d3grasp.eval.evaluate runs them."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from d3grasp.authoring.manifest import AssetEntry, read_manifest
from d3grasp.envs.config import GRASP_TYPES
from d3grasp.envs.registry import DEFAULT_TASK, TASKS, get_task
from d3grasp.policies import ABLATION_NAMES, BASELINE, SHIPPED, resolve_checkpoint, shipped_ablation
from d3grasp.policies.teacher import TEACHER, TEACHER_WRIST

OBJECT_SETS: dict[str, tuple[str, ...]] = {
    "diverse": ("rigid",),
    "deformable": ("deformable",),
    "all": ("rigid", "deformable"),
}
GRASP_CHOICES: tuple[str, ...] = ("all", *GRASP_TYPES)
SPLITS: tuple[str, ...] = ("test", "train", "all")
# Where each controller's object pose comes from, by --perception. "paper" is the paper's protocol
# (the main command's): every controller under the camera, and the rule-based baseline once more under
# the oracle pose, the reference for perfect localisation (PAPER_REFERENCE).
PERCEPTIONS: dict[str, tuple[str, ...]] = {
    "oracle": ("oracle",),
    "camera": ("camera",),
    "both": ("oracle", "camera"),
    "paper": ("camera",),
}
PAPER_REFERENCE = f"{BASELINE}/oracle"
# Config fields the evaluation sets itself; an override of them would silently change what is measured.
RESERVED_OVERRIDES: frozenset[str] = frozenset(
    {"objects", "eval_mode", "num_envs", "seed", "grasp_types", "device", "perception"}
)


@dataclass
class EvalSettings:
    """What to evaluate and how. ``checkpoint`` is a ``model_<N>.pt`` path or ``"baseline"``; the
    ablation mode instead names several checkpoints in ``ablation`` (``"PATH"`` or ``"TASK=PATH"``)
    and sets ``checkpoint`` to None."""

    checkpoint: str | None = BASELINE
    task: str = DEFAULT_TASK
    objects: str | None = None  # diverse | deformable | all | a manifest path; None: the task's kinds
    split: str | None = None  # test | train | all; None: test (shipped library) or all (own manifest)
    episodes_per_object: int = 1
    grasp_types: str = "all"  # all: chosen per object by the rule; top | side | pinch: forced
    seed: int = 0
    num_envs: int = 16
    compare_baseline: bool = False
    device: str = "cpu"
    env_overrides: dict[str, Any] = field(default_factory=dict)  # e.g. {"phases__disturb_per_direction": 0.1}
    # oracle | camera | both (each controller under both, side by side) | paper (PERCEPTIONS)
    perception: str = "oracle"
    ablation: tuple[str, ...] = ()  # checkpoints of the ablation table, "PATH" or "TASK=PATH"
    # Read checkpoints that name code (--trust-checkpoint); episodes do not depend on it.
    trust_checkpoint: bool = False

    def validate(self) -> None:
        get_task(self.task)  # UnknownTaskError
        if (self.checkpoint is None) == (not self.ablation):
            raise ValueError("give either a checkpoint or the ablation checkpoints, not both or neither")
        if len(self.ablation) == 1 and self.ablation != (SHIPPED,):
            raise ValueError("--ablation compares several checkpoints: give two or more, or 'shipped'")
        if self.perception not in PERCEPTIONS:
            raise ValueError(f"--perception must be one of {list(PERCEPTIONS)}, got '{self.perception}'")
        if self.split is not None and self.split not in SPLITS:
            raise ValueError(f"--split must be one of {list(SPLITS)}, got '{self.split}'")
        if self.grasp_types not in GRASP_CHOICES:
            raise ValueError(f"--grasp-types must be one of {list(GRASP_CHOICES)}, got '{self.grasp_types}'")
        if self.episodes_per_object < 1:
            raise ValueError(f"--episodes-per-object must be >= 1, got {self.episodes_per_object}")
        if self.num_envs < 1:
            raise ValueError(f"--num_envs must be >= 1, got {self.num_envs}")
        if self.compare_baseline and self.checkpoint == BASELINE:
            raise ValueError("--compare baseline needs a policy checkpoint, not --checkpoint baseline")
        for key in self.env_overrides:
            head = key.split("__", 1)[0]
            if head in RESERVED_OVERRIDES:
                raise ValueError(f"override '{key}' is set by the evaluation itself (use the eval flags)")


@dataclass(frozen=True)
class RunSpec:
    """One controller of an evaluation: its label in the tables, the task whose environment it runs
    in and its checkpoint (or ``"baseline"``)."""

    label: str
    task: str
    checkpoint: str
    # The checkpoint's action interface (policies.checkpoint.interface_overrides); --set goes over it.
    env_overrides: dict[str, Any] = field(default_factory=dict)


def select_objects(
    objects: str | None, split: str | None, task: str = DEFAULT_TASK
) -> tuple[Path | None, list[AssetEntry]]:
    """``(manifest or None for the shipped library, entries)`` chosen by the object set and split."""
    from d3grasp.paths import default_manifest

    if objects is None:
        kinds = tuple(get_task(task).make_cfg().objects.kinds)
        manifest, path = None, default_manifest()
    elif objects in OBJECT_SETS:
        kinds = OBJECT_SETS[objects]
        manifest, path = None, default_manifest()
    else:
        kinds = OBJECT_SETS["all"]
        manifest = path = Path(objects)
        if not path.is_file():
            raise FileNotFoundError(
                f"--objects: manifest not found: {objects} (or use one of {list(OBJECT_SETS)})"
            )
    split = split or ("all" if manifest is not None else "test")
    entries = [e for e in read_manifest(path) if e.kind in kinds and (split == "all" or e.split == split)]
    if not entries:
        raise ValueError(f"{path}: no object of kinds {list(kinds)} in split '{split}'")
    return manifest, entries


def _task_from_run_folder(checkpoint: Path) -> str | None:
    """The ``--task`` of the ``d3grasp-train`` command recorded next to the checkpoint, if any."""
    import shlex

    command = checkpoint.parent / "params" / "command.txt"
    if not command.is_file():
        return None
    words = shlex.split(command.read_text(encoding="utf-8"))
    for i, word in enumerate(words):
        if word == "--task" and i + 1 < len(words):
            return words[i + 1]
        if word.startswith("--task="):
            return word.split("=", 1)[1]
    return DEFAULT_TASK  # d3grasp-train without --task trains the default task


def checkpoint_task(spec: str, trust: bool = False) -> tuple[str, str, dict[str, Any]]:
    """``(task, checkpoint path, checkpoint)`` of an ablation entry ``"PATH"`` or ``"TASK=PATH"``
    (the checkpoint as ``read_checkpoint`` loads it, read once).

    The task a checkpoint was trained on is read from the checkpoint (``d3grasp-train`` records it),
    else from its run folder's ``params/command.txt``. A given task must agree with the recorded one;
    a checkpoint whose task cannot be told needs it given. Raises ``CheckpointError`` (missing or
    unreadable file), ``UnknownTaskError`` or ``ValueError``.
    """
    from d3grasp.policies.checkpoint import read_checkpoint

    head, sep, rest = spec.partition("=")
    # Only a registered-looking task name before "=" splits the entry: a path may contain "=" too.
    given = head if sep and (head in TASKS or head.startswith("D3Grasp-")) else None
    path = rest if given is not None else spec
    if given is not None:
        get_task(given)
    data = read_checkpoint(path, trust=trust)
    infos = data.get("infos") or {}
    recorded = infos.get("task") or _task_from_run_folder(Path(path))
    if recorded is not None:
        get_task(recorded)
    if given is not None and recorded is not None and given != recorded:
        raise ValueError(f"checkpoint {path} was trained on task '{recorded}', not on '{given}'")
    task = given or recorded
    if task is None:
        raise ValueError(
            f"cannot tell which task checkpoint {path} was trained on (no task in the checkpoint, no "
            f"params/command.txt next to it): give it as TASK={path}"
        )
    return task, path, data


def _ablation_name(task: str) -> str:
    """``D3Grasp-DexHand13-Diverse-v0`` -> ``Diverse``; the paper's names for its ablation tasks."""
    parts = task.split("-")
    return ABLATION_NAMES.get(task, parts[2] if len(parts) == 4 else task)


def run_specs(settings: EvalSettings) -> list[RunSpec]:
    """The controllers to evaluate, in table order; checks every checkpoint before any env is built."""
    from d3grasp.policies.checkpoint import interface_overrides, read_checkpoint

    if settings.ablation:
        entries = shipped_ablation() if settings.ablation == (SHIPPED,) else settings.ablation
        resolved = [checkpoint_task(spec, settings.trust_checkpoint) for spec in entries]
        names = [_ablation_name(task) for task, _, _ in resolved]
        specs = []
        for (task, path, data), name in zip(resolved, names, strict=True):
            if names.count(name) > 1 or name == BASELINE:  # two checkpoints of one task: tell them apart
                name = f"{name} ({Path(path).parent.name}/{Path(path).name})"
            specs.append(RunSpec(name, task, path, interface_overrides(data)))
        if len({s.label for s in specs}) != len(specs):
            raise ValueError(f"--ablation names one checkpoint twice: {list(settings.ablation)}")
    elif settings.checkpoint == BASELINE:
        specs = [RunSpec(BASELINE, settings.task, BASELINE)]
    elif settings.checkpoint == TEACHER:  # the privileged teacher, with a wrist if the task has none
        specs = [RunSpec(TEACHER, settings.task, TEACHER, _teacher_overrides(settings.task))]
    else:
        assert settings.checkpoint is not None  # validate() ensured it
        path = resolve_checkpoint(settings.checkpoint, settings.task)  # "shipped": the package's policy
        # A missing, unreadable or code-carrying file fails here, before any env is built.
        data = read_checkpoint(path, trust=settings.trust_checkpoint)
        specs = [RunSpec("policy", settings.task, path, interface_overrides(data))]
    if settings.compare_baseline:
        specs.append(RunSpec(BASELINE, settings.task, BASELINE))
    return specs


def _teacher_overrides(task: str) -> dict[str, Any]:
    from d3grasp.envs.mdp.actions import has_wrist

    cfg = get_task(task).make_cfg()
    return {} if has_wrist(cfg) else dict(TEACHER_WRIST)
