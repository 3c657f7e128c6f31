"""Evaluate a policy checkpoint (or the rule-based baseline) on a set of objects, the paper's way.

Every object gets its own world, in batches of ``num_envs`` worlds, with the environment in
evaluation mode (all six 2-s disturbance pushes, no randomisation of dynamics). Each object is
evaluated ``episodes_per_object`` times; repeat ``r`` builds the batch's environment with seed
``seed + r``, which draws the object's placement (position and yaw) and the tactile noise. Only
the first episode of each world counts: in evaluation mode every episode runs to its full length
unless the simulation breaks, so one ``max_episode_length`` of steps finishes every world.

With ``compare_baseline`` the baseline runs on the same objects, seeds and grasp types as the
policy, so the two tables differ only in the controller. Everything written to ``results.json``
depends only on the settings (no timings, no output paths): two runs with one seed give the
same file.
"""

from __future__ import annotations

import csv
import importlib.util
import json
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import torch

from d3grasp.authoring.manifest import AssetEntry, read_manifest
from d3grasp.envs.config import GRASP_TYPES
from d3grasp.envs.registry import DEFAULT_TASK, get_task
from d3grasp.eval.metrics import COLUMNS, METRICS, aggregate, table_markdown

OBJECT_SETS: dict[str, tuple[str, ...]] = {
    "diverse": ("rigid",),
    "deformable": ("deformable",),
    "all": ("rigid", "deformable"),
}
GRASP_CHOICES: tuple[str, ...] = ("all", *GRASP_TYPES)
SPLITS: tuple[str, ...] = ("test", "train", "all")
BASELINE = "baseline"
# Config fields the evaluation sets itself; an override of them would silently change what is measured.
RESERVED_OVERRIDES: frozenset[str] = frozenset(
    {"objects", "eval_mode", "num_envs", "seed", "grasp_types", "device"}
)

__all__ = [
    "BASELINE",
    "EvalResult",
    "EvalSettings",
    "evaluate",
    "load_policy",
    "select_objects",
    "write_outputs",
]


@dataclass
class EvalSettings:
    """What to evaluate and how. ``checkpoint`` is a ``model_<N>.pt`` path or ``"baseline"``."""

    checkpoint: str = BASELINE
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

    def validate(self) -> None:
        get_task(self.task)  # UnknownTaskError
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


@dataclass
class EvalResult:
    settings: EvalSettings
    objects: list[str]
    manifest: str | None  # None: the shipped library
    runs: dict[str, list[dict[str, Any]]]  # controller label ("policy" / "baseline") -> episode records
    wall_s: float = 0.0  # not part of results.json (not reproducible)

    def to_json(self) -> dict[str, Any]:
        """The reproducible content of ``results.json``: settings, objects, every episode, summaries."""
        return {
            "settings": {**asdict(self.settings), "manifest": self.manifest},
            "objects": self.objects,
            "runs": {
                label: {"episodes": eps, "summary": summary_rows(eps)} for label, eps in self.runs.items()
            },
        }


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


def load_policy(env: Any, task: str, checkpoint: str | os.PathLike[str], device: str) -> Any:
    """The checkpoint's deterministic actor (the same loader as ``d3grasp-play``)."""
    from d3grasp.train.play import load_runner

    policy = load_runner(env, task, checkpoint, device).get_inference_policy(device)
    policy.reset()
    return policy


def _run_batch(
    env: Any,
    controller: str,
    settings: EvalSettings,
    on_episode: Callable[[], None],
) -> list[dict[str, Any]]:
    """First finished episode of every world of ``env`` under the policy or the baseline."""
    if controller == BASELINE:
        from d3grasp.envs.baseline import RuleBasedController

        ctl = RuleBasedController(env)
        act: Callable[[Any], torch.Tensor] = ctl.act
        reset: Callable[[torch.Tensor], None] = lambda dones: None  # noqa: E731 (resets itself at t = 0)
    else:
        policy = load_policy(env, settings.task, settings.checkpoint, settings.device)
        act = lambda obs: policy(obs.to(settings.device))  # noqa: E731
        reset = lambda dones: policy.reset(dones.to(settings.device))  # noqa: E731 (fresh LSTM state)
    first: dict[int, dict[str, Any]] = {}
    obs = env.get_observations()
    with torch.inference_mode():
        for _ in range(int(env.max_episode_length)):
            obs, _, dones, extras = env.step(act(obs).to(env.device))
            reset(dones)
            for ep in extras.get("episodes", ()):
                if ep["env"] not in first:
                    first[ep["env"]] = ep
                    on_episode()
            if len(first) == env.num_envs:
                break
    if len(first) != env.num_envs:
        missing = sorted(set(range(env.num_envs)) - set(first))
        raise RuntimeError(f"worlds {missing} did not finish an episode in {env.max_episode_length} steps")
    return [first[w] for w in range(env.num_envs)]


def evaluate(
    settings: EvalSettings,
    progress: bool = True,
    log: Callable[[str], None] = print,
    env_factory: Callable[..., Any] | None = None,
) -> EvalResult:
    """Run the evaluation; ``CheckpointError`` / ``FileNotFoundError`` / ``ValueError`` on bad input."""
    import time

    from tqdm import tqdm

    from d3grasp.envs import make_env
    from d3grasp.train.runner import read_checkpoint
    from d3grasp.train.train import seed_everything

    t0 = time.perf_counter()
    settings.validate()
    if settings.checkpoint != BASELINE:
        read_checkpoint(settings.checkpoint)  # a missing or unreadable file fails before any env is built
    if settings.split is None:  # record the split actually used
        own_manifest = settings.objects is not None and settings.objects not in OBJECT_SETS
        settings = replace(settings, split="all" if own_manifest else "test")
    manifest, entries = select_objects(settings.objects, settings.split, settings.task)
    ids = [e.id for e in entries]
    controllers = [settings.checkpoint] + ([BASELINE] if settings.compare_baseline else [])
    labels = {
        BASELINE: BASELINE,
        settings.checkpoint: "policy" if settings.checkpoint != BASELINE else BASELINE,
    }
    grasp_types = tuple(GRASP_TYPES) if settings.grasp_types == "all" else (settings.grasp_types,)
    make = env_factory or make_env
    K, W = settings.episodes_per_object, settings.num_envs
    total = len(ids) * K * len(controllers)
    log(
        f"[d3grasp-eval] {len(ids)} objects x {K} episodes x {len(controllers)} controller(s) = {total} "
        f"episodes on {settings.task}, {W} worlds per batch"
    )
    runs: dict[str, list[dict[str, Any]]] = {labels[c]: [] for c in controllers}
    with tqdm(total=total, unit="ep", disable=not progress, dynamic_ncols=True) as bar:
        for controller in controllers:
            label = labels[controller]
            bar.set_description(label)
            for start in range(0, len(ids), W):
                chunk = tuple(ids[start : start + W])
                objects_cfg: dict[str, Any] = {"ids": chunk}
                if manifest is not None:
                    objects_cfg["manifest"] = str(manifest)
                for r in range(K):
                    seed_everything(settings.seed + r)
                    env = make(
                        settings.task,
                        num_envs=len(chunk),
                        device=settings.device,
                        seed=settings.seed + r,
                        eval_mode=True,
                        objects=objects_cfg,
                        grasp_types=grasp_types,
                        **settings.env_overrides,
                    )
                    try:
                        eps = _run_batch(env, controller, settings, lambda: bar.update(1))
                    finally:
                        close = getattr(env, "close", None)
                        if close is not None:
                            close()
                    for ep in eps:
                        runs[label].append({**ep, "repeat": r, "seed": settings.seed + r})
            # Object order, then repeat: independent of the batch layout's step order.
            order = {i: n for n, i in enumerate(ids)}
            runs[label].sort(key=lambda ep: (order[ep["object"]], ep["repeat"]))
    return EvalResult(
        settings=settings,
        objects=ids,
        manifest=str(manifest) if manifest is not None else None,
        runs=runs,
        wall_s=time.perf_counter() - t0,
    )


def summary_rows(episodes: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """One row per (column, metric): successes, trials, rate and 95% Wilson interval (None if no trials)."""
    summary = aggregate(episodes)
    rows = []
    for col in COLUMNS:
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


def _title(label: str, s: EvalSettings) -> str:
    who = "rule-based baseline" if label == BASELINE else f"policy {Path(s.checkpoint).name}"
    objects = s.objects or "task default"
    return (
        f"{who} on {s.task}: objects {objects}, split {s.split}, "
        f"{s.episodes_per_object} episode(s) per object, grasp types {s.grasp_types}, seed {s.seed}"
    )


def write_outputs(
    result: EvalResult, out_dir: str | os.PathLike[str], log: Callable[[str], None] = print
) -> dict[str, Path]:
    """Write results.json, summary.csv, table.md and (with matplotlib) plot.png; returns their paths."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"results": out / "results.json", "summary": out / "summary.csv", "table": out / "table.md"}
    paths["results"].write_text(json.dumps(result.to_json(), indent=1, sort_keys=True) + "\n")

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

    tables = [
        table_markdown(aggregate(eps), _title(label, result.settings)) for label, eps in result.runs.items()
    ]
    paths["table"].write_text("\n".join(tables))

    if importlib.util.find_spec("matplotlib") is None:
        log("[d3grasp-eval] note: matplotlib is not installed, plot.png skipped (pip install matplotlib)")
    else:
        paths["plot"] = out / "plot.png"
        _plot(result, paths["plot"])
    return paths


def _plot(result: EvalResult, path: Path) -> None:
    """Bars of s_lift and s_disturb per column, one colour per controller, with Wilson error bars."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
                vals.append(100 * v)
                err_lo.append(0.0 if math.isnan(lo) else 100 * (v - lo))
                err_hi.append(0.0 if math.isnan(hi) else 100 * (hi - v))
            xs = [i + (k - (len(labels) - 1) / 2) * width for i in range(len(COLUMNS))]
            ax.bar(xs, vals, width, yerr=[err_lo, err_hi], capsize=3, label=label)
        ax.set_xticks(range(len(COLUMNS)), COLUMNS)
        ax.set_title(metric)
        ax.set_ylim(0, 100)
    axes[0].set_ylabel("success (%, 95% CI)")
    axes[-1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
