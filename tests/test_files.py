"""Atomic writes: the old file or the new one, never a truncated one, with a plain file's mode."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from d3grasp.authoring.manifest import read_manifest, write_manifest
from d3grasp.files import atomic_write, atomic_write_text


def test_plain_mode_and_no_leftovers(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        path = atomic_write_text(tmp_path / "state.json", '{"n": 1}\n')
        write_manifest(tmp_path / "manifest.json", [])
    finally:
        os.umask(old)
    assert path.read_text() == '{"n": 1}\n'
    for p in (path, tmp_path / "manifest.json"):
        assert stat.S_IMODE(p.stat().st_mode) == 0o640  # 0666 under umask 027, not mkstemp's 0600
    assert read_manifest(tmp_path / "manifest.json") == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["manifest.json", "state.json"]


def test_a_failed_write_keeps_the_old_file(tmp_path: Path) -> None:
    path = atomic_write_text(tmp_path / "state.json", "old\n")

    def broken(f) -> None:
        f.write(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError, match="disk full"):
        atomic_write(path, broken)
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["state.json"]
