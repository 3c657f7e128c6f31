"""Checkpoints are read as data: a file whose pickle names a function (here ``os.system``) is refused
by every command that reads checkpoints, before it could run, unless ``--trust-checkpoint`` is given;
the shipped policies, what d3grasp-train writes and records holding NumPy values or paths load."""

from __future__ import annotations

import datetime
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from d3grasp.train import play as play_mod
from d3grasp.train import train as train_mod

from d3grasp.eval import cli as eval_cli
from d3grasp.policies import SHIPPED_ABLATION
from d3grasp.policies.checkpoint import (
    TRUST_FLAG,
    CheckpointError,
    UnsafeCheckpointError,
    read_checkpoint,
)

_POLICIES = Path(__file__).resolve().parents[1] / "d3grasp" / "policies"


class _Payload:
    """Unpickling this object calls ``os.system(command)``: the attack of a shared policy file."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return (os.system, (self.command,))


def _evil(tmp_path: Path, *, actor: bool = True, legacy: bool = False) -> tuple[Path, Path]:
    """A checkpoint that creates ``marker`` when unpickled; ``(checkpoint, marker)``."""
    marker = tmp_path / "SOME_FILE"
    data: dict[str, Any] = {"x": _Payload(f"touch {marker}")}
    if actor:
        data["actor_state_dict"] = {}
    path = tmp_path / "evil.pt"
    torch.save(data, path, _use_new_zipfile_serialization=not legacy)
    assert not marker.exists()
    return path, marker


def _refused(code: int, err: str) -> None:
    line = err.strip().splitlines()[-1]
    assert code == 2, err
    assert TRUST_FLAG in line and "system" in line, line  # names the flag and the offending function


def test_eval_refuses_code(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, marker = _evil(tmp_path)
    code = eval_cli.main(["--checkpoint", str(path), "--out", str(tmp_path / "out"), "--no-progress"])
    _refused(code, capsys.readouterr().err)
    assert not marker.exists()


def test_eval_ablation_refuses_code(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, marker = _evil(tmp_path)
    shipped = _POLICIES / next(iter(SHIPPED_ABLATION.values())) / "model.pt"
    code = eval_cli.main(["--ablation", str(shipped), str(path), "--out", str(tmp_path / "out")])
    _refused(code, capsys.readouterr().err)
    assert not marker.exists()


def test_play_refuses_code(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, marker = _evil(tmp_path)
    code = play_mod.main(["--checkpoint", str(path), "--episodes", "1", "--num_envs", "1"])
    _refused(code, capsys.readouterr().err)
    assert not marker.exists()


def test_train_resume_refuses_code(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, marker = _evil(tmp_path)
    argv = ["--num_envs", "1", "--max_iterations", "1", "--log_root", str(tmp_path / "logs")]
    code = train_mod.main([*argv, "--resume", "--checkpoint", str(path)])
    _refused(code, capsys.readouterr().err)
    assert not marker.exists()


def test_legacy_format_refused(tmp_path: Path) -> None:
    """A file in torch's pre-zip format is judged by the weights-only unpickler itself."""
    path, marker = _evil(tmp_path, legacy=True)
    with pytest.raises(UnsafeCheckpointError, match="system"):
        read_checkpoint(path)
    assert not marker.exists()


def test_trust_flag_reads_the_old_kind(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """With the flag the file is unpickled as before (the payload runs): the flag is the only way."""
    path, marker = _evil(tmp_path, actor=False)
    code = eval_cli.main(["--checkpoint", str(path), "--out", str(tmp_path / "out"), TRUST_FLAG])
    assert code == 2 and "actor_state_dict" in capsys.readouterr().err  # loaded, then found no actor
    assert marker.exists()
    marker.unlink()
    code = play_mod.main(["--checkpoint", str(path), TRUST_FLAG])
    assert code == 2 and "actor_state_dict" in capsys.readouterr().err
    assert marker.exists()


def test_trust_reads_a_non_data_object(tmp_path: Path) -> None:
    """An object outside the allowed data types (a ``datetime``) needs the flag; with it, it loads."""
    when = datetime.datetime(2026, 12, 7, 12, 0)
    path = tmp_path / "old.pt"
    torch.save({"actor_state_dict": {"w": torch.ones(2)}, "infos": {"saved": when}}, path)
    with pytest.raises(UnsafeCheckpointError, match=r"datetime\.datetime.*--trust-checkpoint"):
        read_checkpoint(path)
    assert read_checkpoint(path, trust=True)["infos"]["saved"] == when


def test_allowed_data_types_load(tmp_path: Path) -> None:
    """NumPy scalars and arrays and paths are values: a record holding them loads without the flag."""
    infos = {"lr": np.float64(3e-4), "seen": np.arange(3, dtype=np.int32), "run": Path("logs/run")}
    path = tmp_path / "model_1.pt"
    torch.save({"actor_state_dict": {"w": torch.arange(4.0)}, "iter": 1, "infos": infos}, path)
    data = read_checkpoint(path)
    assert data["infos"]["lr"] == pytest.approx(3e-4) and isinstance(data["infos"]["lr"], np.floating)
    assert data["infos"]["seen"].tolist() == [0, 1, 2] and data["infos"]["seen"].dtype == np.int32
    assert data["infos"]["run"] == Path("logs/run")
    assert torch.equal(data["actor_state_dict"]["w"], torch.tensor([0.0, 1.0, 2.0, 3.0]))


@pytest.mark.parametrize("folder", sorted(p.name for p in _POLICIES.iterdir() if (p / "model.pt").is_file()))
def test_shipped_policies_load_as_data(folder: str) -> None:
    data = read_checkpoint(_POLICIES / folder / "model.pt")
    assert data["actor_state_dict"] and all(
        isinstance(v, torch.Tensor) for v in data["actor_state_dict"].values()
    )
    assert isinstance(data["infos"]["task"], str)


def test_refusal_is_a_checkpoint_error(tmp_path: Path) -> None:
    """Commands turn ``CheckpointError`` into one line and exit 2: the refusal is one of them."""
    path, _ = _evil(tmp_path)
    with pytest.raises(CheckpointError):
        read_checkpoint(path)
