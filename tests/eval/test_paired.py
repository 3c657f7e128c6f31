"""Paired comparison: twins matched by object and seed, discordant counts, the exact sign test."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest

from d3grasp.eval.paired import compare_pairs, load_pairs, main, sign_test_p


def _enumerated_sign_test(only_a: int, only_b: int) -> float:
    """Two-sided p by enumerating every assignment of the discordant pairs (each side with p = 1/2):
    the probability of a split at least as uneven as the observed one."""
    m = only_a + only_b
    observed = abs(only_a - only_b)
    extreme = sum(1 for signs in itertools.product((0, 1), repeat=m) if abs(2 * sum(signs) - m) >= observed)
    return extreme / 2**m


@pytest.mark.parametrize(("a", "b"), [(10, 0), (3, 1), (1, 17), (6, 2), (5, 5), (0, 1)])
def test_sign_test_matches_enumeration(a: int, b: int) -> None:
    assert sign_test_p(a, b) == pytest.approx(_enumerated_sign_test(a, b), rel=1e-12)


def test_sign_test_without_discordant_pairs() -> None:
    assert sign_test_p(0, 0) == 1.0


def _episode(obj: str, seed: int, kind: str, lift: bool, disturb: bool) -> dict:
    return {"object": obj, "seed": seed, "repeat": 0, "kind": kind, "s_grasp": lift, "s_lift": lift,
            "s_disturb": disturb}  # fmt: skip


def _results(
    path: Path, seed: int, policy: list[tuple[bool, bool]], baseline: list[tuple[bool, bool]]
) -> Path:
    runs = {
        name: {"episodes": [_episode(f"obj_{i}", seed, "rigid", *o) for i, o in enumerate(outcomes)]}
        for name, outcomes in (("policy", policy), ("baseline", baseline))
    }
    path.write_text(json.dumps({"runs": runs}))
    return path


def test_pairs_over_two_seeds(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Seed 0: the policy lifts objects 0-2, the baseline 0 and 3. Seed 1: both lift 0, only the policy 1.
    s0 = _results(
        tmp_path / "s0.json",
        0,
        [(True, True)] * 3 + [(False, False)],
        [(True, False), (False, False), (False, False), (True, True)],
    )
    s1 = _results(tmp_path / "s1.json", 1, [(True, False), (True, True)], [(True, False), (False, False)])
    pairs = load_pairs([s0, s1])
    assert len(pairs) == 6
    assert all(a["object"] == b["object"] and a["seed"] == b["seed"] for a, b in pairs)
    lift = next(r for r in compare_pairs(pairs) if r.metric == "s_lift")
    assert (lift.n, lift.only_a, lift.only_b) == (6, 3, 1)
    assert lift.rate_a == pytest.approx(5 / 6) and lift.rate_b == pytest.approx(3 / 6)
    assert lift.p_value == pytest.approx(0.625)  # 2 * (1 + 4) / 16
    lo, hi = lift.diff_ci
    assert lo < (5 - 3) / 6 < hi
    disturb = next(r for r in compare_pairs(pairs) if r.metric == "s_disturb")
    assert (disturb.only_a, disturb.only_b) == (4, 1)  # only the policy: 0-2 of seed 0, 1 of seed 1
    assert main([str(s0), str(s1)]) == 0
    assert "| Diverse s_lift | 6 | 83.3 | 50.0 |" in capsys.readouterr().out


def test_a_file_without_the_baseline_is_one_line_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"runs": {"policy": {"episodes": []}}}))
    assert main([str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no run ['baseline']" in err and "\n" not in err
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    assert main([str(bad)]) == 2
    assert "not a d3grasp-eval results.json" in capsys.readouterr().err


def test_against_pairs_the_runs_of_two_evaluations(tmp_path: Path) -> None:
    """Two grasp libraries, one evaluation each: the baseline of the new one against the old one's,
    episode by episode; objects the other lacks are not paired."""
    new = _results(tmp_path / "new.json", 0, [], [(True, True), (True, True), (True, False)])
    old = _results(tmp_path / "old.json", 0, [], [(True, False), (False, False)])
    pairs = load_pairs([new], "baseline", "baseline", against=[old])
    assert [(a["object"], b["object"]) for a, b in pairs] == [("obj_0", "obj_0"), ("obj_1", "obj_1")]
    disturb = next(r for r in compare_pairs(pairs) if r.metric == "s_disturb")
    assert (disturb.n, disturb.only_a, disturb.only_b) == (2, 2, 0)
    assert main([str(new), "--against", str(old), "--a", "baseline", "--b", "baseline"]) == 0
    assert main([str(new), "--against", str(old), "--a", "policy/camera", "--b", "baseline"]) == 2


def test_defaults_follow_the_main_commands_run_names(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The main command writes policy/camera, baseline/camera and baseline/oracle: compared by default."""
    runs = {
        name: {"episodes": [_episode("obj_0", 0, "rigid", *outcome)]}
        for name, outcome in (
            ("policy/camera", (True, True)),
            ("baseline/camera", (False, False)),
            ("baseline/oracle", (True, False)),
        )
    }
    path = tmp_path / "main.json"
    path.write_text(json.dumps({"runs": runs}))
    assert main([str(path)]) == 0
    assert "| Diverse s_lift | 1 | 100.0 | 0.0 |" in capsys.readouterr().out
    assert main([str(path), "--b", "baseline/oracle"]) == 0
    assert "| Diverse s_lift | 1 | 100.0 | 100.0 |" in capsys.readouterr().out
