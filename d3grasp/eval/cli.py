"""``d3grasp-eval``: the paper's evaluation table for a checkpoint or the rule-based baseline.

    d3grasp-eval --checkpoint logs/rsl_rl/<exp>/<run>/model_1000.pt --compare baseline
    d3grasp-eval --checkpoint baseline --objects deformable --split test --episodes-per-object 3
    d3grasp-eval --ablation <base run>/model_1000.pt <tactile run>/model_1000.pt <asym run>/model_1000.pt
    d3grasp-eval --ablation shipped --compare baseline     # the package's three ablation checkpoints

Writes ``results.json`` (settings and every episode), ``summary.csv``, ``table.md`` and ``plot.png``
to ``--out`` (default ``eval_out/``). ``--ablation`` evaluates several checkpoints (each on the task
it was trained on, or ``TASK=PATH``; ``shipped``: the package's three) into the paper's ablation
table. A stopped run continues with ``--resume`` (the same command and ``--out``): finished batches
are kept in ``OUT/.batches/``.
``--set KEY=VALUE`` overrides an environment config field (``phases.disturb_per_direction=0.1``); it
changes what is measured, so it is meant for debugging and quick checks, and is recorded in
results.json.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")

from d3grasp.cli.args import add_env_override_arg, add_trust_arg, parse_override, positive_int  # noqa: E402
from d3grasp.envs.registry import DEFAULT_TASK  # noqa: E402
from d3grasp.eval.specs import (  # noqa: E402
    BASELINE,
    GRASP_CHOICES,
    OBJECT_SETS,
    PERCEPTIONS,
    SPLITS,
    EvalSettings,
)

__all__ = ["main", "make_parser", "parse_override"]


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="d3grasp-eval",
        description="Evaluate a D3Grasp policy (or the rule-based baseline) in evaluation mode: success "
        "rates with 95%% Wilson intervals per size bin and for deformable objects.",
    )
    which = p.add_mutually_exclusive_group(required=True)
    which.add_argument(
        "--checkpoint",
        help="model_<N>.pt written by d3grasp-train, 'shipped' (the package's trained policy of --task) "
        "'baseline' (the rule-based controller) or 'teacher' (the privileged teacher: the rule's fingers, "
        "the wrist onto the grasp at the true pose)",
    )
    which.add_argument(
        "--ablation",
        nargs="+",
        metavar="[TASK=]CKPT",
        help="ablation mode: several checkpoints (e.g. the Base, BaseTactile and asymmetric runs) in one "
        "table, each on the task it was trained on (read from the checkpoint or its run folder, or TASK=); "
        "'shipped': the package's three ablation checkpoints",
    )
    p.add_argument("--task", default=DEFAULT_TASK, help=f"registered task (default {DEFAULT_TASK})")
    p.add_argument(
        "--objects",
        default=None,
        help=f"{' | '.join(OBJECT_SETS)} | a manifest.json path (default: the task's object kinds)",
    )
    p.add_argument(
        "--split",
        choices=SPLITS,
        default=None,
        help="library split (default: test for the shipped library, all for an own manifest)",
    )
    p.add_argument("--episodes-per-object", type=positive_int, default=1, help="repeats, seeds S..S+K-1")
    p.add_argument("--grasp-types", choices=GRASP_CHOICES, default="all", help="all: per-object rule")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="eval_out", help="output folder (default eval_out/)")
    p.add_argument("--num_envs", type=positive_int, default=16, help="worlds per batch (default 16)")
    p.add_argument("--compare", choices=(BASELINE,), default=None, help="also run the baseline")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="processes the batches run in (default: the machine's cores; results do not depend on it)",
    )
    p.add_argument("--torch_threads", type=positive_int, default=None, help="torch CPU threads (default 1)")
    add_env_override_arg(p, "debugging: override an env config field, e.g. phases.disturb_per_direction=0.1")
    p.add_argument(
        "--perception",
        choices=tuple(PERCEPTIONS),
        default="paper",
        help="object pose for the grasp planner: the paper's protocol (default: every controller under "
        "the RGB-D camera, and the rule-based baseline also under the true pose as the reference), "
        "simulator truth (oracle), the camera, or both for every controller side by side; camera runs "
        "add a localisation-error table",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="reuse the batches a stopped run into the same --out finished with the same settings and "
        "inputs (kept in OUT/.batches/ until the outputs are written); without it they are discarded",
    )
    add_trust_arg(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--verbose", action="store_true", help="also what Warp and rsl-rl report (module loads, models)"
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = make_parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    import torch

    from d3grasp.cli.args import resolve_torch_threads, run_command
    from d3grasp.eval.evaluate import evaluate
    from d3grasp.eval.report import write_outputs
    from d3grasp.eval.resume import BatchStore

    torch.set_num_threads(resolve_torch_threads(args.torch_threads))
    from d3grasp.console import set_verbosity

    set_verbosity(args.verbose)  # a line per cached kernel module would bury the progress bar
    settings = EvalSettings(
        checkpoint=args.checkpoint,  # None in the ablation mode
        ablation=tuple(args.ablation or ()),
        task=args.task,
        objects=args.objects,
        split=args.split,
        episodes_per_object=args.episodes_per_object,
        grasp_types=args.grasp_types,
        seed=args.seed,
        num_envs=args.num_envs,
        compare_baseline=args.compare == BASELINE,
        device=args.device,
        env_overrides=dict(args.overrides),
        perception=args.perception,
        trust_checkpoint=args.trust_checkpoint,
    )

    def body() -> None:
        from d3grasp.parallel import default_workers

        workers = args.workers or (default_workers() if args.device == "cpu" else 1)
        store = BatchStore(args.out)  # each finished batch is kept until the outputs are written
        if not args.resume:
            store.clear()
        result = evaluate(settings, progress=not args.no_progress, workers=workers, store=store)
        paths = write_outputs(result, args.out)
        store.clear()
        print(paths["table"].read_text())
        print(f"[d3grasp-eval] wrote {', '.join(str(p) for p in paths.values())} in {result.wall_s:.1f} s")

    return run_command("d3grasp-eval", body, one_line=True)


if __name__ == "__main__":
    raise SystemExit(main())
