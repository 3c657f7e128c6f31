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

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from d3grasp.envs import close_env
from d3grasp.envs.config import GRASP_TYPES
from d3grasp.eval.metrics import (
    summary_rows,
)
from d3grasp.eval.resume import BatchStore, batch_keys
from d3grasp.eval.specs import (
    OBJECT_SETS,
    PAPER_REFERENCE,
    PERCEPTIONS,
    EvalSettings,
    RunSpec,
    checkpoint_task,
    run_specs,
    select_objects,
)
from d3grasp.policies import BASELINE
from d3grasp.vision.perception import localisation_summary

# A soft world's step against a rigid one's: ~6x at 5 solver iterations (bench env, 8 worlds: 307 / 55
# env-steps/s), and the soft objects' evaluation took 3.4x as long at their 20 (sim.soft_iterations).
SOFT_COST = 20.0

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
]


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
