"""Which checkpoint ``d3grasp-train --resume`` continues from, on hand-made run folders."""

from __future__ import annotations

from pathlib import Path

import pytest
from d3grasp.train.train import resume_checkpoint

from d3grasp.policies.checkpoint import CheckpointError


def _runs(tmp_path: Path) -> Path:
    exp = tmp_path / "logs" / "rsl_rl" / "d3grasp_dexhand13_mixed_v0"
    for run, iters in (("2026-12-01_10-00-00_first", (25, 50)), ("2026-12-02_10-00-00_second", (25,))):
        (exp / run).mkdir(parents=True)
        for it in iters:
            (exp / run / f"model_{it}.pt").write_bytes(b"")
    (exp / "2026-12-03_10-00-00_killed").mkdir()  # killed before its first save
    return exp


def test_the_latest_run_that_holds_a_checkpoint_and_its_highest_iteration(tmp_path: Path) -> None:
    exp = _runs(tmp_path)
    assert resume_checkpoint(exp, None, None) == exp / "2026-12-02_10-00-00_second" / "model_25.pt"


def test_a_run_by_its_name_a_regex_or_its_path(tmp_path: Path) -> None:
    exp = _runs(tmp_path)
    first = exp / "2026-12-01_10-00-00_first"
    assert resume_checkpoint(exp, "first", None) == first / "model_50.pt"
    assert resume_checkpoint(exp, "12-01", "model_25.pt") == first / "model_25.pt"
    assert resume_checkpoint(exp, str(first), None) == first / "model_50.pt"
    assert resume_checkpoint(tmp_path / "elsewhere", str(first), None) == first / "model_50.pt"


def test_one_line_errors(tmp_path: Path) -> None:
    exp = _runs(tmp_path)
    with pytest.raises(CheckpointError, match="no run named or matching 'third'"):
        resume_checkpoint(exp, "third", None)
    with pytest.raises(CheckpointError, match="run folder not found"):
        resume_checkpoint(exp, str(exp / "nope"), None)
    with pytest.raises(CheckpointError, match="nothing to resume"):
        resume_checkpoint(tmp_path / "empty", None, None)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        resume_checkpoint(exp, "killed", None)
