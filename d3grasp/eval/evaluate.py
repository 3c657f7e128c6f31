"""Evaluate a policy checkpoint (or the rule-based baseline) on a set of objects, the paper's way.

Every object gets its own world, in batches of up to ``num_envs`` worlds of one object kind (rigid or
soft) run in one or more processes, with the environment in evaluation mode (all six 2-s
disturbance pushes, no randomisation of dynamics). Each object is
evaluated ``episodes_per_object`` times; repeat ``r`` builds the batch's environment with seed
``seed + r``, which draws the object's placement (position and yaw) and the tactile noise. Only
the first episode of each world counts: in evaluation mode every episode runs to its full length
unless the simulation breaks, so one ``max_episode_length`` of steps finishes every world.

With ``compare_baseline`` the baseline runs on the same objects, seeds and grasp types as the
policy, so the two tables differ only in the controller. The ablation mode evaluates several
checkpoints (the paper's Base, Base+Tactile and asymmetric variants), each on the task it was trained
on (read from the checkpoint, else from its run folder's ``params/command.txt``, or given as
``TASK=PATH``), on the same objects, seeds and grasp types, into one table. Everything written
to ``results.json`` depends only on the settings (no timings, no output paths): two runs with one
seed give the same file.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from d3grasp.authoring.manifest import AssetEntry, read_manifest
from d3grasp.envs import close_env
from d3grasp.envs.config import GRASP_TYPES
from d3grasp.envs.registry import DEFAULT_TASK, TASKS, apply_overrides, get_task
from d3grasp.eval.metrics import (
    COLUMNS,
    GROUPS,
    METRICS,
    ablation_markdown,
    aggregate,
    comparison_markdown,
    grasp_type_markdown,
    outcomes_markdown,
    table_markdown,
)
from d3grasp.eval.paired import compare_pairs, format_table, pair_episodes
from d3grasp.eval.resume import BatchStore, batch_keys
from d3grasp.files import atomic_write_text
from d3grasp.policies import ABLATION_NAMES, BASELINE, SHIPPED, resolve_checkpoint, shipped_ablation
from d3grasp.policies.teacher import TEACHER, TEACHER_WRIST
from d3grasp.vision.perception import localisation_markdown, localisation_summary

OBJECT_SETS: dict[str, tuple[str, ...]] = {
    "diverse": ("rigid",),
    "deformable": ("deformable",),
    "all": ("rigid", "deformable"),
}
GRASP_CHOICES: tuple[str, ...] = ("all", *GRASP_TYPES)
# A soft world's step against a rigid one's: ~6x at 5 solver iterations (bench env, 8 worlds: 307 / 55
# env-steps/s), and the soft objects' evaluation took 3.4x as long at their 20 (sim.soft_iterations).
SOFT_COST = 20.0
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

__all__ = [
    "BASELINE",
    "EvalResult",
    "EvalSettings",
    "RunSpec",
    "checkpoint_task",
    "evaluate",
    "perception_jobs",
    "plan_batches",
    "select_objects",
    "write_outputs",
]


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


@dataclass
class EvalResult:
    settings: EvalSettings
    objects: list[str]
    manifest: str | None  # None: the shipped library
    runs: dict[str, list[dict[str, Any]]]  # controller label ("policy" / "baseline") -> episode records
    wall_s: float = 0.0  # not part of results.json (not reproducible)
    specs: dict[str, RunSpec] = field(default_factory=dict)  # label -> what ran (task, checkpoint)

    def to_json(self) -> dict[str, Any]:
        """The reproducible content of ``results.json``: settings, objects, every episode, summaries."""
        return {
            "settings": {**asdict(self.settings), "manifest": self.manifest},
            "objects": self.objects,
            "runs": {
                label: {
                    **self._spec_json(label),
                    "episodes": eps,
                    "summary": summary_rows(eps),
                    **({"localisation": loc} if (loc := localisation_summary(eps)) is not None else {}),
                }
                for label, eps in self.runs.items()
            },
        }

    def _spec_json(self, label: str) -> dict[str, str]:
        spec = self.specs.get(label)
        return {} if spec is None else {"task": spec.task, "checkpoint": spec.checkpoint}


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


def _run_batch(
    env: Any,
    run: RunSpec,
    settings: EvalSettings,
    on_episode: Callable[[], None],
) -> list[dict[str, Any]]:
    """First finished episode of every world of ``env`` under the run's policy or the baseline."""
    # The same policy / baseline loader and episode loop as d3grasp-play and the grasp planner.
    from d3grasp.controllers import first_episodes, make_controller

    controller = make_controller(
        env, run.task, run.checkpoint, settings.device, trust=settings.trust_checkpoint
    )
    return first_episodes(env, controller, on_episode)


def _eval_batch(
    spec: RunSpec,
    perception: str,
    chunk: tuple[str, ...],
    repeat: int,
    settings: EvalSettings,
    manifest: str | None,
    grasp_types: tuple[str, ...],
    env_factory: Callable[..., Any] | None = None,
    on_episode: Callable[[], None] = lambda: None,
) -> list[dict[str, Any]]:
    """One batch: the objects of ``chunk`` in one environment of seed ``settings.seed + repeat``,
    each world's first episode. Everything it depends on is in its arguments, so any process can run it."""
    from d3grasp.envs import make_env
    from d3grasp.seeding import seed_everything

    seed = settings.seed + repeat
    objects_cfg: dict[str, Any] = {"ids": chunk}
    if manifest is not None:
        objects_cfg["manifest"] = manifest
    seed_everything(seed)
    env = (env_factory or make_env)(
        spec.task,
        num_envs=len(chunk),
        device=settings.device,
        seed=seed,
        eval_mode=True,
        objects=objects_cfg,
        grasp_types=grasp_types,
        perception=perception,
        **{**spec.env_overrides, **settings.env_overrides},
    )
    try:
        eps = _run_batch(env, spec, settings, on_episode)
    finally:
        close_env(env)
    return [{**ep, "repeat": repeat, "seed": seed} for ep in eps]


def perception_jobs(specs: Sequence[RunSpec], perception: str) -> list[tuple[RunSpec, str]]:
    """``(controller, perception)`` of every run: a controller under the camera is labelled
    ``"<label>/camera"``; the paper's protocol adds the baseline under the oracle as ``PAPER_REFERENCE``."""
    jobs = [
        (spec if p == "oracle" else replace(spec, label=f"{spec.label}/camera"), p)
        for spec in specs
        for p in PERCEPTIONS[perception]
    ]
    if perception == "paper":
        jobs += [(replace(s, label=PAPER_REFERENCE), "oracle") for s in specs if s.checkpoint == BASELINE]
    return jobs


def plan_batches(
    jobs: Sequence[tuple[RunSpec, str]],
    ids: Sequence[str],
    kinds: Mapping[str, str],
    num_envs: int,
    repeats: int,
) -> list[tuple[RunSpec, str, tuple[str, ...], int]]:
    """The evaluation's batches ``(controller, perception, object ids, repeat)``, costliest first.

    A batch holds up to ``num_envs`` objects of one kind, in the order of ``ids``: the solver steps
    all worlds of an environment together and a soft world costs ~``SOFT_COST`` rigid ones, so a
    rigid object sharing a batch with soft ones would run at the soft pace. The costliest go first so
    that worker processes finish together (the results are sorted afterwards either way).
    """
    groups = [[i for i in ids if kinds[i] == kind] for kind in dict.fromkeys(kinds[i] for i in ids)]
    chunks = [tuple(g[s : s + num_envs]) for g in groups for s in range(0, len(g), num_envs)]
    batches = [(spec, p, chunk, r) for spec, p in jobs for chunk in chunks for r in range(repeats)]
    batches.sort(key=lambda b: -sum(SOFT_COST if kinds[i] == "deformable" else 1.0 for i in b[2]))
    return batches


def evaluate(
    settings: EvalSettings,
    progress: bool = True,
    log: Callable[[str], None] = print,
    env_factory: Callable[..., Any] | None = None,
    workers: int = 1,
    store: BatchStore | None = None,
) -> EvalResult:
    """Run the evaluation; ``CheckpointError`` / ``FileNotFoundError`` / ``ValueError`` on bad input.

    The batches (controller x ``num_envs`` objects x repeat) run in ``workers`` processes
    (d3grasp.parallel); a batch's episodes depend only on its objects and seed, so any number of
    workers gives the same results. A custom ``env_factory`` runs in this process. With a ``store``
    each finished batch is saved to it, and a batch it already holds for the same inputs is not run
    again (a stopped evaluation resumes).
    """
    import time

    from tqdm import tqdm

    from d3grasp.parallel import run_units

    t0 = time.perf_counter()
    settings.validate()
    jobs = perception_jobs(run_specs(settings), settings.perception)
    specs = [spec for spec, _ in jobs]
    if settings.split is None:  # record the split actually used
        own_manifest = settings.objects is not None and settings.objects not in OBJECT_SETS
        settings = replace(settings, split="all" if own_manifest else "test")
    manifest, entries = select_objects(settings.objects, settings.split, settings.task)
    ids = [e.id for e in entries]
    grasp_types = tuple(GRASP_TYPES) if settings.grasp_types == "all" else (settings.grasp_types,)
    K, W = settings.episodes_per_object, settings.num_envs
    kinds = {e.id: e.kind for e in entries}
    all_batches = plan_batches(jobs, ids, kinds, W, K)
    manifest_arg = str(manifest) if manifest is not None else None
    runs: dict[str, list[dict[str, Any]]] = {spec.label: [] for spec in specs}
    keys: list[dict[str, Any] | None] = [None] * len(all_batches)
    if store is not None:
        keys = list(batch_keys(settings, all_batches, manifest_arg, grasp_types))
    batches, keys_to_run = [], []  # the batches not stored by an earlier run, and their keys
    for b, key in zip(all_batches, keys, strict=True):
        stored = store.load(key) if store else None
        if stored is None:
            batches.append(b)
            keys_to_run.append(key)
        else:
            runs[b[0].label].extend(stored)
    if env_factory is not None:
        workers = 1
    workers = max(1, min(workers, len(batches)))
    total = len(ids) * K * len(specs)
    tasks = ", ".join(dict.fromkeys(spec.task for spec in specs))
    reused = len(all_batches) - len(batches)
    log(
        f"[d3grasp-eval] {len(ids)} objects x {K} episodes x {len(specs)} controller(s) = {total} "
        f"episodes on {tasks}, {W} worlds per batch, {len(all_batches)} batches on {workers} process(es)"
        + (f", {reused} of them finished by an earlier run and reused" if reused else "")
    )
    done_eps = sum(len(eps) for eps in runs.values())
    with tqdm(total=total, initial=done_eps, unit="ep", disable=not progress, dynamic_ncols=True) as bar:
        if workers == 1:  # in this process: the bar moves per episode

            def one_episode() -> None:
                bar.update(1)

            units = [(*b, settings, manifest_arg, grasp_types, env_factory, one_episode) for b in batches]
        else:  # in other processes: the bar moves per batch
            units = [(*b, settings, manifest_arg, grasp_types) for b in batches]

        def done(k: int, eps: list[dict[str, Any]]) -> None:
            runs[batches[k][0].label].extend(eps)
            if store is not None:
                store.save(keys_to_run[k], eps)
            if workers > 1:
                bar.update(len(eps))

        run_units(_eval_batch, units, workers, done)
    # Object order, then repeat: independent of the batch layout and of the order batches finish in.
    order = {i: n for n, i in enumerate(ids)}
    for eps in runs.values():
        eps.sort(key=lambda ep: (order[ep["object"]], ep["repeat"]))
    return EvalResult(
        settings=settings,
        objects=ids,
        manifest=manifest_arg,
        runs=runs,
        wall_s=time.perf_counter() - t0,
        specs={spec.label: spec for spec in specs},
    )


def summary_rows(episodes: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (group, metric): successes, trials, rate and 95% Wilson interval (None if no trials).

    The groups are the evaluation table's columns and Diverse (every rigid object, the comparison table's).
    """
    summary = aggregate(episodes)
    rows = []
    for col in GROUPS:
        for m in METRICS:
            rate = summary[col][m]
            lo, hi = rate.interval
            rows.append(
                {
                    "column": col,
                    "metric": m,
                    "successes": rate.successes,
                    "trials": rate.trials,
                    "rate": None if math.isnan(rate.value) else rate.value,
                    "ci_low": None if math.isnan(lo) else lo,
                    "ci_high": None if math.isnan(hi) else hi,
                }
            )
    return rows


def _conditions(s: EvalSettings) -> str:
    """What every run of one evaluation shares: objects, split, repeats, grasp types and seed."""
    return (
        f"objects {s.objects or 'task default'}, split {s.split}, {s.episodes_per_object} episode(s) per "
        f"object, grasp types {s.grasp_types}, seed {s.seed}"
    )


def _spec_of(result: EvalResult, label: str) -> RunSpec:
    # A result built by hand (not by evaluate()) may carry no specs: fall back to its settings.
    s = result.settings
    checkpoint = BASELINE if label == BASELINE else str(s.checkpoint)
    return result.specs.get(label) or RunSpec(label, s.task, checkpoint)


def _baseline_name(task: str, overrides: Mapping[str, Any]) -> str:
    """What ``--checkpoint baseline`` ran on ``task``: the paper's touch rule, or the stall rule of the
    Base task (``rule.stop_on="stall"``: the Base ablation's prior, which reads no pad)."""
    cfg = apply_overrides(get_task(task).make_cfg(), dict(overrides))
    return "rule-based baseline" if cfg.rule.stop_on == "touch" else f"{cfg.rule.stop_on} rule (no touch)"


def _title(spec: RunSpec, s: EvalSettings) -> str:
    if spec.checkpoint == BASELINE:
        who = _baseline_name(spec.task, s.env_overrides)
    else:
        ckpt = Path(spec.checkpoint)
        who = f"{'policy' if spec.label == 'policy' else spec.label} {ckpt.name}"
        if s.ablation:  # several checkpoints are often all model_<N>.pt: name the run folder too
            who = f"{spec.label} {ckpt.parent.name}/{ckpt.name}"
    if spec.label.endswith("/camera"):  # a controller under camera perception (camera, both, paper)
        who += ", camera perception"
    elif spec.label == PAPER_REFERENCE:
        who += ", oracle pose (the reference for perfect localisation)"
    return f"{who} on {spec.task}: {_conditions(s)}"


def _ablation_header(spec: RunSpec, label: str, overrides: Mapping[str, Any]) -> str:
    """The ablation table's column head of run ``label``: which senses the actor reads and whether the
    critic is asymmetric (reads the privileged group), as in the paper's ablation table; the baseline's
    with its perception where the label names one (``baseline/camera`` beside ``baseline/oracle``)."""
    if spec.checkpoint == BASELINE:
        _, _, perception = label.partition("/")
        name = _baseline_name(spec.task, overrides)
        return f"{name}, {perception}" if perception else name
    task = get_task(spec.task)
    actor = "proprioception + tactile" if task.make_cfg().tactile_obs else "proprioception"
    if "privileged" in task.critic_groups:
        return f"{spec.label} (asymmetric; actor: {actor}; critic: + privileged)"
    return f"{spec.label} (symmetric; actor: {actor})"


def _finite_or_null(value: Any) -> Any:
    """A copy of a JSON-able value with NaN and infinities replaced by ``None``."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(v) for v in value]
    return value


def write_outputs(
    result: EvalResult, out_dir: str | os.PathLike[str], log: Callable[[str], None] = print
) -> dict[str, Path]:
    """Write results.json, summary.csv, table.md and plot.png; returns their paths.

    table.md holds, in this order: the ablation table (ablation mode), the comparison table (two or
    more runs) and the evaluation table of every run.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"results": out / "results.json", "summary": out / "summary.csv", "table": out / "table.md"}
    # Strict JSON: a non-finite number (the max strain of an episode whose state blew up) is null.
    doc = json.dumps(_finite_or_null(result.to_json()), indent=1, sort_keys=True, allow_nan=False)
    atomic_write_text(paths["results"], doc + "\n")

    with paths["summary"].open("w", newline="") as f:
        fields = ["run", "column", "metric", "successes", "trials", "rate", "ci_low", "ci_high"]
        writer = csv.DictWriter(f, fieldnames=fields)
        writer.writeheader()
        for label, eps in result.runs.items():
            for row in summary_rows(eps):
                writer.writerow(
                    {
                        "run": label,
                        **{
                            k: ("" if v is None else (f"{v:.6f}" if isinstance(v, float) else v))
                            for k, v in row.items()
                        },
                    }
                )

    summaries = {label: aggregate(eps) for label, eps in result.runs.items()}
    specs = {label: _spec_of(result, label) for label in result.runs}
    tables = []
    if result.settings.ablation:
        overrides = result.settings.env_overrides
        headers = {label: _ablation_header(spec, label, overrides) for label, spec in specs.items()}
        title = f"Ablation, every episode: {_conditions(result.settings)}"
        tables.append(ablation_markdown(summaries, headers, title))
    if len(summaries) > 1:
        tables.append(comparison_markdown(summaries, f"Comparison: {_conditions(result.settings)}"))
    for label_a, label_b in _paired_runs(result.runs):
        results = compare_pairs(pair_episodes(result.runs[label_a], result.runs[label_b]))
        title = f"**Paired by object and seed: {label_a} against {label_b}** (exact sign test)"
        tables.append(f"{title}\n\n{format_table(results, label_a, label_b)}\n")
    tables += [table_markdown(summaries[label], _title(specs[label], result.settings)) for label in summaries]
    tables.append(grasp_type_markdown(result.runs, "By grasp type"))
    tables.append(outcomes_markdown(result.runs, "How the episodes ended (first cause)"))
    loc_table = localisation_markdown(result.runs)
    if loc_table:
        tables.append(loc_table)
    paths["table"].write_text("\n".join(tables))

    paths["plot"] = out / "plot.png"
    _plot(result, paths["plot"])
    return paths


def _paired_runs(runs: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The runs compared pair by pair in table.md: the policy (or the teacher) against the baseline
    under the same perception, and under the paper's protocol the baseline under the camera against
    its reference."""
    pairs = [(f"{who}{s}", f"{BASELINE}{s}") for who in ("policy", TEACHER) for s in ("", "/camera")]
    pairs.append((f"{BASELINE}/camera", PAPER_REFERENCE))
    return [(a, b) for a, b in pairs if a in runs and b in runs]


def _plot(result: EvalResult, path: Path) -> None:
    """Bars of s_lift and s_disturb per column, one colour per controller, with Wilson error bars."""
    from d3grasp.viz.figure import pyplot, save_figure

    plt = pyplot()

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
    labels = list(result.runs)
    width = 0.8 / len(labels)
    for ax, metric in zip(axes, ("s_lift", "s_disturb"), strict=True):
        for k, label in enumerate(labels):
            summary = aggregate(result.runs[label])
            vals, err_lo, err_hi = [], [], []
            for col in COLUMNS:
                rate = summary[col][metric]
                v = 0.0 if math.isnan(rate.value) else rate.value
                lo, hi = rate.interval
                # No bar (NaN) for a column without episodes: a 0 bar would read as "all failed".
                vals.append(100 * v if rate.trials else math.nan)
                # max(0, .): at 0/n or n/n the Wilson bound equals the rate up to round-off (-1e-17).
                err_lo.append(0.0 if math.isnan(lo) else max(0.0, 100 * (v - lo)))
                err_hi.append(0.0 if math.isnan(hi) else max(0.0, 100 * (hi - v)))
            xs = [i + (k - (len(labels) - 1) / 2) * width for i in range(len(COLUMNS))]
            ax.bar(xs, vals, width, yerr=[err_lo, err_hi], capsize=3, label=label)
        # Every controller ran the same objects, so the first run's episode counts label the columns.
        counts = aggregate(result.runs[labels[0]]) if labels else {}
        ticks = [f"{col}\n(n={counts[col][metric].trials})" if counts else col for col in COLUMNS]
        ax.set_xticks(range(len(COLUMNS)), ticks)
        ax.set_title(metric)
        ax.set_ylim(0, 100)
    axes[0].set_ylabel("success (%, 95% CI)")
    axes[-1].legend()
    save_figure(fig, path, dpi=120)
