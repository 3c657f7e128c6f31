"""``d3grasp-eval`` end to end on the real environment, kept small: two rigid test objects, one
episode each, the disturbance pushes shortened to 0.1 s per direction through ``--set``.

References are independent of the code under test: success counts recounted from the episode
records, Wilson intervals from SciPy's binomial test, the eval-mode episode length from the phase
durations by hand (six pushes), the forced grasp type against the rule's own choice.
"""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from scipy.stats import binomtest

from d3grasp.authoring.manifest import read_manifest, resolve_asset_path, write_manifest
from d3grasp.envs import DEFAULT_TASK
from d3grasp.envs.config import PhaseConfig
from d3grasp.eval.cli import main, parse_override
from d3grasp.eval.metrics import GROUPS, METRICS
from d3grasp.paths import default_manifest

OBJECTS = ("bottle_04", "box_04")  # rigid, medium, test split; the rule picks top and pinch for them
PUSH_S = 0.1
QUICK = ["--set", f"phases.disturb_per_direction={PUSH_S}", "--num_envs", "2", "--no-progress"]
ORACLE = ["--perception", "oracle"]  # the CLI's default is the paper's protocol (test_paper_protocol)


@pytest.fixture(scope="module")
def manifest(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A two-object manifest pointing at the shipped USD files (absolute paths)."""
    lib = default_manifest()
    by_id = {e.id: e for e in read_manifest(lib)}
    path = tmp_path_factory.mktemp("lib") / "manifest.json"
    write_manifest(path, [replace(by_id[i], path=str(resolve_asset_path(lib, by_id[i]))) for i in OBJECTS])
    return path


def _save_untrained_checkpoint(task: str, path: Path, manifest: Path) -> Path:
    """A checkpoint as d3grasp-train writes it (weights + infos with observation sizes), untrained."""
    from d3grasp.train.configs import fit_mini_batches, make_train_cfg
    from d3grasp.train.runner import D3GraspRunner

    from d3grasp.envs import make_env

    env = make_env(task, num_envs=1, objects={"manifest": str(manifest), "ids": OBJECTS[:1]})
    cfg = make_train_cfg(task)
    cfg["algorithm"]["num_mini_batches"] = fit_mini_batches(cfg["algorithm"]["num_mini_batches"], 1)
    D3GraspRunner(env, cfg, log_dir=None, device="cpu", task_name=task).save(str(path))
    env.close()
    return path


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory, manifest: Path) -> Path:
    return _save_untrained_checkpoint(DEFAULT_TASK, tmp_path_factory.mktemp("ckpt") / "model_0.pt", manifest)


@pytest.fixture(scope="module")
def compare_run(tmp_path_factory: pytest.TempPathFactory, manifest: Path, checkpoint: Path) -> Path:
    out = tmp_path_factory.mktemp("compare")
    argv = ["--checkpoint", str(checkpoint), "--objects", str(manifest), "--compare", "baseline"]
    # Two processes, one batch each (policy, baseline): test_same_seed_same_results checks that the
    # baseline's batch gives in its worker process what it gives run alone in this one.
    assert (
        main(
            [
                *argv,
                "--grasp-types",
                "top",
                "--seed",
                "3",
                "--out",
                str(out),
                "--workers",
                "2",
                *QUICK,
                *ORACLE,
            ]
        )
        == 0
    )
    return out


def _read(out: Path) -> dict[str, Any]:
    return json.loads((out / "results.json").read_text())


def test_policy_and_baseline_files(compare_run: Path) -> None:
    doc = _read(compare_run)
    assert doc["objects"] == list(OBJECTS)
    s = doc["settings"]
    assert (s["task"], s["grasp_types"], s["seed"], s["episodes_per_object"]) == (DEFAULT_TASK, "top", 3, 1)
    assert s["split"] == "all"  # an own manifest defaults to all of its objects
    assert s["env_overrides"] == {"phases__disturb_per_direction": PUSH_S}
    assert set(doc["runs"]) == {"policy", "baseline"}
    ph = PhaseConfig()
    steps = round(60 * (ph.approach + ph.grasp + ph.lift + ph.hold)) + 6 * round(60 * PUSH_S)  # six pushes
    keys = [(ep["object"], ep["repeat"], ep["seed"]) for ep in doc["runs"]["policy"]["episodes"]]
    assert keys == [(o, 0, 3) for o in OBJECTS]
    for label, run in doc["runs"].items():
        eps = run["episodes"]
        assert [(ep["object"], ep["repeat"], ep["seed"]) for ep in eps] == keys, label  # same episodes
        for ep in eps:
            assert ep["grasp_type"] == "top"  # forced: the rule alone would give box_04 a pinch
            assert ep["length"] == steps and ep["kind"] == "rigid" and ep["size_bin"] == "medium"
            assert isinstance(ep["s_lift"], bool) and (ep["s_disturb"] <= ep["s_lift"] <= ep["s_grasp"])

    rows = list(csv.DictReader((compare_run / "summary.csv").open()))
    assert list(rows[0]) == ["run", "column", "metric", "successes", "trials", "rate", "ci_low", "ci_high"]
    assert len(rows) == 2 * len(GROUPS) * len(METRICS)
    for row in rows:
        eps = doc["runs"][row["run"]]["episodes"]
        if row["column"] == "Diverse":  # every rigid object
            eps = [ep for ep in eps if ep["kind"] == "rigid"]
        elif row["column"] == "Deformable":
            eps = [ep for ep in eps if ep["kind"] == "deformable"]
        elif row["column"] != "Average":
            eps = [ep for ep in eps if ep["kind"] == "rigid" and ep["size_bin"] == row["column"].lower()]
        k, n = sum(ep[row["metric"]] for ep in eps), len(eps)
        assert (int(row["successes"]), int(row["trials"])) == (k, n), row
        if n == 0:
            assert row["rate"] == row["ci_low"] == row["ci_high"] == ""
            continue
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert float(row["rate"]) == pytest.approx(k / n, abs=1e-6)
        assert float(row["ci_low"]) == pytest.approx(ci.low, abs=1e-5)
        assert float(row["ci_high"]) == pytest.approx(ci.high, abs=1e-5)

    table = (compare_run / "table.md").read_text()
    policy_at, baseline_at = table.index("**policy model_0.pt"), table.index("**rule-based baseline")
    assert policy_at < baseline_at and table.count("| s_disturb |") == 2 and table.count("| episodes |") == 2
    assert "| episodes | 0 | 2 | 0 | 0 | 2 |" in table
    # The comparison table comes first: one row per controller, diverse (rigid) and deformable columns.
    assert table.index("**Comparison:") < policy_at
    for label in ("policy", "baseline"):
        eps = doc["runs"][label]["episodes"]
        cells = [_percent(sum(ep[m] for ep in eps), len(eps)) for m in ("s_lift", "s_disturb")]
        assert f"| {label} | {cells[0]} | {cells[1]} | – | – | 2 / 0 |" in table
    assert (compare_run / "plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _percent(k: int, n: int) -> str:
    """A table cell from SciPy's Wilson interval: "50.0 [9.5, 90.5]"."""
    ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    return f"{100 * k / n:.1f} [{100 * ci.low:.1f}, {100 * ci.high:.1f}]"


def test_same_seed_same_results(tmp_path: Path, manifest: Path, compare_run: Path) -> None:
    argv = ["--checkpoint", "baseline", "--objects", str(manifest), "--grasp-types", "top", "--seed", "3"]
    for name in ("a", "b"):
        assert main([*argv, "--out", str(tmp_path / name), "--workers", "1", *QUICK, *ORACLE]) == 0
    a, b = (tmp_path / "a" / "results.json").read_text(), (tmp_path / "b" / "results.json").read_text()
    assert a == b
    # The baseline of the comparison run saw the same objects, seeds and grasp types, in a worker
    # process of its own: same episodes.
    assert json.loads(a)["runs"]["baseline"]["episodes"] == _read(compare_run)["runs"]["baseline"]["episodes"]


def test_paper_protocol(tmp_path: Path, manifest: Path, compare_run: Path) -> None:
    """The default protocol: every controller under the camera, and the baseline also under the oracle
    pose as the reference, with the pair compared object by object."""
    argv = ["--checkpoint", "baseline", "--objects", str(manifest), "--grasp-types", "top", "--seed", "3"]
    assert main([*argv, "--out", str(tmp_path), "--workers", "1", *QUICK]) == 0
    doc = _read(tmp_path)
    assert doc["settings"]["perception"] == "paper"
    assert list(doc["runs"]) == ["baseline/camera", "baseline/oracle"]
    # The reference is the oracle baseline of the comparison run: same objects, seed and grasp type.
    assert doc["runs"]["baseline/oracle"]["episodes"] == _read(compare_run)["runs"]["baseline"]["episodes"]
    camera = doc["runs"]["baseline/camera"]
    assert "localisation" in camera and "localisation" not in doc["runs"]["baseline/oracle"]
    table = (tmp_path / "table.md").read_text()
    assert "oracle pose (the reference for perfect localisation)" in table
    assert "**Paired by object and seed: baseline/camera against baseline/oracle**" in table
    oracle = {ep["object"]: ep for ep in doc["runs"]["baseline/oracle"]["episodes"]}
    for metric in METRICS:
        only_cam = sum(ep[metric] and not oracle[ep["object"]][metric] for ep in camera["episodes"])
        only_oracle = sum(oracle[ep["object"]][metric] and not ep[metric] for ep in camera["episodes"])
        assert f"| {only_cam} | {only_oracle} |" in next(
            line for line in table.splitlines() if line.startswith(f"| Diverse {metric} |")
        )


def _error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("d3grasp-eval: error: ")
    return err[0]


def test_bad_inputs(tmp_path: Path, manifest: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    base = ["--out", str(out), *QUICK]
    assert main(["--checkpoint", "baseline", "--objects", str(tmp_path / "nope.json"), *base]) == 2
    assert "nope.json" in _error_line(capsys)
    assert main(["--checkpoint", str(tmp_path / "model_9.pt"), "--objects", str(manifest), *base]) == 2
    assert "checkpoint not found" in _error_line(capsys)
    assert main(["--checkpoint", "baseline", "--compare", "baseline", *base]) == 2
    _error_line(capsys)
    assert main(["--checkpoint", "baseline", "--task", "D3Grasp-Nope-v0", *base]) == 2
    assert "D3Grasp-Nope-v0" in _error_line(capsys)
    assert main(["--checkpoint", "baseline", "--set", "seed=4", *base]) == 2
    _error_line(capsys)
    assert not out.exists()  # nothing written on bad input


def test_checkpoint_of_another_task(
    tmp_path: Path, manifest: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = "D3Grasp-DexHand13-Base-v0"  # proprioception only: a smaller policy observation
    ckpt = _save_untrained_checkpoint(other, tmp_path / "model_0.pt", manifest)
    argv = ["--checkpoint", str(ckpt), "--objects", str(manifest), "--out", str(tmp_path / "out"), *QUICK]
    assert main(argv) == 2
    line = _error_line(capsys)
    assert other in line and "does not fit task" in line and DEFAULT_TASK in line


BASE, TACTILE = "D3Grasp-DexHand13-Base-v0", "D3Grasp-DexHand13-BaseTactile-v0"


def _drop_recorded_task(path: Path) -> None:
    """Make a checkpoint that does not record its task (as a foreign or older rsl-rl checkpoint)."""
    import torch
    from d3grasp.train.runner import read_checkpoint

    data = read_checkpoint(path)
    del data["infos"]["task"]
    torch.save(data, path)


def test_ablation_table(
    tmp_path: Path,
    manifest: Path,
    checkpoint: Path,
    compare_run: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Three checkpoints, three ways of knowing their task: the Base run's folder (a real 1-iteration
    d3grasp-train run whose checkpoint no longer records it), TASK=PATH for a bare BaseTactile file,
    the checkpoint itself for the asymmetric one."""
    from d3grasp.train.train import main as train_main

    logs = tmp_path / "logs"
    argv = ["--task", BASE, "--num_envs", "2", "--max_iterations", "1", "--num_steps_per_env", "4"]
    assert train_main([*argv, "--log_root", str(logs), "--torch_threads", "1"]) == 0
    (base_ckpt,) = logs.glob("*/*/model_1.pt")
    _drop_recorded_task(base_ckpt)
    tactile_ckpt = _save_untrained_checkpoint(TACTILE, tmp_path / "model_0.pt", manifest)
    _drop_recorded_task(tactile_ckpt)
    capsys.readouterr()

    # Bad input first: a task the file cannot tell, a given task the checkpoint contradicts, one entry.
    out = tmp_path / "out"
    common = [
        "--objects",
        str(manifest),
        "--grasp-types",
        "top",
        "--seed",
        "3",
        "--out",
        str(out),
        *QUICK,
        *ORACLE,
    ]
    assert main(["--ablation", str(base_ckpt), str(tactile_ckpt), *common]) == 2
    assert f"TASK={tactile_ckpt}" in _error_line(capsys)
    assert main(["--ablation", f"{BASE}={checkpoint}", str(base_ckpt), *common]) == 2
    assert f"trained on task '{DEFAULT_TASK}', not on '{BASE}'" in _error_line(capsys)
    assert main(["--ablation", str(checkpoint), *common]) == 2
    _error_line(capsys)
    with pytest.raises(SystemExit):  # argparse: --checkpoint and --ablation exclude each other
        main(["--checkpoint", "baseline", "--ablation", str(checkpoint), str(base_ckpt), *common])
    assert not out.exists()

    entries = [str(base_ckpt), f"{TACTILE}={tactile_ckpt}", str(checkpoint)]
    assert main(["--ablation", *entries, *common]) == 0
    doc = _read(out)
    assert doc["settings"]["checkpoint"] is None and doc["settings"]["ablation"] == entries
    runs = {name: doc["runs"][name] for name in ("Base", "Base+Tactile", "Asymmetric")}  # ablation order
    assert len(doc["runs"]) == 3  # results.json sorts its keys: the order is the settings' ablation list
    assert [(r["task"], r["checkpoint"]) for r in runs.values()] == [
        (BASE, str(base_ckpt)),
        (TACTILE, str(tactile_ckpt)),
        (DEFAULT_TASK, str(checkpoint)),
    ]
    # Same objects, seeds and grasp type for every variant; the asymmetric policy is the comparison
    # run's policy (same checkpoint, same settings), so its episodes are the same too.
    for run in runs.values():
        assert [(ep["object"], ep["seed"], ep["grasp_type"]) for ep in run["episodes"]] == [
            (o, 3, "top") for o in OBJECTS
        ]
    assert runs["Asymmetric"]["episodes"] == _read(compare_run)["runs"]["policy"]["episodes"]

    table = (out / "table.md").read_text()
    head, _, rest = table.partition("**Comparison:")
    header = next(line for line in head.splitlines() if line.startswith("| metric"))
    assert header == (
        "| metric (%, 95% CI) | Base (symmetric; actor: proprioception) | Base+Tactile (symmetric; actor: "
        "proprioception + tactile) | Asymmetric (asymmetric; actor: proprioception + tactile; critic: + "
        "privileged) |"
    )
    for m in METRICS:  # every episode of each variant, recounted
        cells = [_percent(sum(ep[m] for ep in r["episodes"]), len(OBJECTS)) for r in runs.values()]
        assert f"| {m} | " + " | ".join(cells) + " |" in head
    assert "| episodes | 2 | 2 | 2 |" in head
    assert rest.count("| s_disturb |") == 3  # each variant's own evaluation table follows
    assert (out / "plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_parse_override() -> None:
    assert parse_override("phases.disturb_per_direction=0.1") == ("phases__disturb_per_direction", 0.1)
    assert parse_override("sim.use_graph=false") == ("sim__use_graph", False)
    assert parse_override("randomization.friction=[0.5, 1.0]") == ("randomization__friction", (0.5, 1.0))
    assert parse_override("grasp_mode=sample") == ("grasp_mode", "sample")


def test_results_json_is_strict_json_with_null_for_non_finite(tmp_path: Path) -> None:
    """A blown-up episode's max strain (NaN) is written as null: strict parsers read the file."""
    from d3grasp.eval.evaluate import EvalResult, EvalSettings
    from d3grasp.eval.report import write_outputs

    def episode(obj: str, strain: float, failure: str | None) -> dict[str, Any]:
        return {
            "env": 0,
            "object": obj,
            "kind": "deformable",
            "family": "sponge",
            "size_bin": "small",
            "grasp_type": "side",
            "s_grasp": True,
            "s_lift": failure is None,
            "s_disturb": failure is None,
            "failure": failure,
            "max_strain": strain,
            "return": 1.5,
            "length": 300,
        }

    eps = [episode("sponge_a", float("nan"), "non-finite state"), episode("sponge_b", 0.21, None)]
    result = EvalResult(
        settings=EvalSettings(), objects=["sponge_a", "sponge_b"], manifest=None, runs={"baseline": eps}
    )
    write_outputs(result, tmp_path, log=lambda _: None)

    def refuse(name: str) -> None:
        raise ValueError(f"non-standard JSON constant {name}")

    doc = json.loads((tmp_path / "results.json").read_text(), parse_constant=refuse)
    written = doc["runs"]["baseline"]["episodes"]
    assert [e["max_strain"] for e in written] == [None, 0.21]
    assert eps[0]["max_strain"] != eps[0]["max_strain"]  # the records themselves are left as they were


def test_loading_a_policy_prints_nothing(
    manifest: Path, checkpoint: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """rsl-rl prints the resolved observation groups and the network while building them: behind
    --verbose (the debug log), not on the evaluation's console."""
    from d3grasp.controllers import make_controller
    from d3grasp.envs import make_env

    env = make_env(DEFAULT_TASK, num_envs=1, objects={"manifest": str(manifest), "ids": OBJECTS[:1]})
    capsys.readouterr()
    controller = make_controller(env, DEFAULT_TASK, checkpoint, "cpu")
    env.close()
    assert controller.actor is not None
    assert capsys.readouterr().out == ""


def test_batches_hold_one_kind_costliest_first() -> None:
    from d3grasp.eval.evaluate import RunSpec, plan_batches

    policy, base = RunSpec("policy", DEFAULT_TASK, "p.pt"), RunSpec("baseline", DEFAULT_TASK, "baseline")
    ids = ["r1", "s1", "r2", "r3", "s2", "s3", "r4"]
    kinds = {i: "deformable" if i.startswith("s") else "rigid" for i in ids}
    batches = plan_batches([(policy, "oracle"), (base, "oracle")], ids, kinds, num_envs=3, repeats=2)
    # By hand: rigid r1 r2 r3 | r4, soft s1 s2 s3; two controllers x two repeats each; the three-soft
    # batches (cost 3 x SOFT_COST) before the three-rigid ones (3) before the single rigid (1).
    chunks = [("s1", "s2", "s3"), ("r1", "r2", "r3"), ("r4",)]
    want = [(spec, "oracle", c, r) for c in chunks for spec in (policy, base) for r in (0, 1)]
    assert sorted(batches, key=str) == sorted(want, key=str)
    assert [b[2] for b in batches] == [c for c in chunks for _ in range(4)]


def test_a_stopped_run_resumes_where_it_was(
    tmp_path: Path, manifest: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Stopped after its first batch (Ctrl-C), the same command with --resume runs only the other
    one, and its results.json is byte for byte that of a run never stopped."""
    import d3grasp.eval.evaluate as evaluate_module
    from d3grasp.eval.resume import BATCH_DIR_NAME

    real_batch = evaluate_module._eval_batch
    ran: list[tuple[str, ...]] = []

    def counted(*args: Any, **kwargs: Any) -> list[dict[str, Any]]:
        ran.append(tuple(args[2]))  # the batch's object ids
        return real_batch(*args, **kwargs)

    def stop_at_second(*args: Any, **kwargs: Any) -> list[dict[str, Any]]:
        if ran:
            raise KeyboardInterrupt
        return counted(*args, **kwargs)

    argv = ["--checkpoint", "baseline", "--objects", str(manifest), "--grasp-types", "top", "--seed", "3"]
    one_per_batch = [*QUICK, *ORACLE, "--num_envs", "1", "--workers", "1"]  # two batches of one object each
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    assert main([*argv, "--out", str(whole), *one_per_batch]) == 0
    assert not (whole / BATCH_DIR_NAME).exists()  # removed once the outputs are written

    monkeypatch.setattr(evaluate_module, "_eval_batch", stop_at_second)
    assert main([*argv, "--out", str(stopped), *one_per_batch]) == 130
    assert "aborted" in capsys.readouterr().err
    assert not (stopped / "results.json").exists() and len(list((stopped / BATCH_DIR_NAME).iterdir())) == 1

    ran.clear()
    monkeypatch.setattr(evaluate_module, "_eval_batch", counted)
    assert main([*argv, "--out", str(stopped), *one_per_batch, "--resume"]) == 0
    assert ran == [(OBJECTS[1],)]  # the first object's batch was not run again
    assert "1 of them finished by an earlier run and reused" in capsys.readouterr().out
    assert (stopped / "results.json").read_bytes() == (whole / "results.json").read_bytes()
    assert not (stopped / BATCH_DIR_NAME).exists()


def test_stored_batches_are_reused_only_for_the_same_inputs(tmp_path: Path, manifest: Path) -> None:
    from d3grasp.eval.evaluate import EvalSettings, RunSpec
    from d3grasp.eval.resume import BATCH_DIR_NAME, BatchStore, batch_keys

    def batch_key(settings, spec, perception, chunk, repeat, manifest, grasp_types):  # one batch's key
        return batch_keys(settings, [(spec, perception, chunk, repeat)], manifest, grasp_types)[0]

    settings = EvalSettings(objects=str(manifest), split="all")
    spec = RunSpec("baseline", DEFAULT_TASK, "baseline")
    key = batch_key(settings, spec, "oracle", OBJECTS, 0, str(manifest), ("top",))
    store = BatchStore(tmp_path)
    episodes = [{"object": OBJECTS[0], "s_lift": True, "max_strain": float("nan"), "pads_at_lift": ["a"]}]
    store.save(key, episodes)
    got = store.load(key)
    assert got is not None and got[0]["pads_at_lift"] == ["a"]
    assert got[0]["max_strain"] != got[0]["max_strain"]  # NaN read back as NaN
    others = [
        batch_key(replace(settings, seed=1), spec, "oracle", OBJECTS, 0, str(manifest), ("top",)),
        batch_key(settings, spec, "oracle", OBJECTS, 1, str(manifest), ("top",)),  # another repeat
        batch_key(settings, spec, "camera", OBJECTS, 0, str(manifest), ("top",)),
        batch_key(settings, spec, "oracle", OBJECTS[:1], 0, str(manifest), ("top",)),
        batch_key(settings, spec, "oracle", OBJECTS, 0, str(manifest), ("pinch",)),
    ]
    assert all(store.load(k) is None for k in others)
    # The manifest's bytes are part of the key: an edited manifest runs the batch again.
    manifest_text = manifest.read_text()
    try:
        manifest.write_text(manifest_text + "\n")
        assert store.load(batch_key(settings, spec, "oracle", OBJECTS, 0, str(manifest), ("top",))) is None
    finally:
        manifest.write_text(manifest_text)
    # So are the object's USD file's: a copy of one, edited after its batch was stored.
    lib = default_manifest()
    entry = next(e for e in read_manifest(lib) if e.id == OBJECTS[1])
    usd = tmp_path / "assets" / Path(entry.path).name
    usd.parent.mkdir()
    shutil.copy(resolve_asset_path(lib, entry), usd)
    own = tmp_path / "assets" / "manifest.json"
    write_manifest(own, [replace(entry, path=usd.name)])
    own_settings = replace(settings, objects=str(own))
    own_key = batch_key(own_settings, spec, "oracle", OBJECTS[1:], 0, str(own), ("top",))
    store.save(own_key, episodes)
    assert store.load(own_key) is not None
    usd.write_text(usd.read_text() + "# edited\n")
    edited = batch_key(own_settings, spec, "oracle", OBJECTS[1:], 0, str(own), ("top",))
    assert store.load(edited) is None
    store.clear()
    store.save(key, episodes)
    (path,) = (tmp_path / BATCH_DIR_NAME).iterdir()
    path.write_text("{not json")  # a torn or foreign file is not reused
    assert store.load(key) is None
    store.clear()
    assert not (tmp_path / BATCH_DIR_NAME).exists()
