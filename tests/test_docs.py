"""docs/configuration.md is what tools/config_reference.py reads from the code today: a setting
added, removed, renamed or given another default or comment without regenerating the page fails."""

from __future__ import annotations

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("config_reference", REPO / "tools" / "config_reference.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_configuration_reference_is_up_to_date() -> None:
    tool = _tool()
    page = (REPO / "docs" / "configuration.md").read_text(encoding="utf-8")
    assert page == tool.render(), "docs/configuration.md is out of date: python tools/config_reference.py"


def test_every_environment_setting_is_listed_with_its_default() -> None:
    """The page names every ``--set`` key of the default task with its value (checked against the
    config's own dataclass fields, not the tool's walk)."""
    import dataclasses
    import json

    from d3grasp.envs.registry import DEFAULT_TASK, get_task

    page = (REPO / "docs" / "configuration.md").read_text(encoding="utf-8")
    cfg = get_task(DEFAULT_TASK).make_cfg()
    for f in dataclasses.fields(cfg.phases):
        value = getattr(cfg.phases, f.name)
        assert f"| `phases.{f.name}` | `{json.dumps(value)}` |" in page
    assert "| `sim.substeps` | `10` |" in page and "| `algorithm.learning_rate` | `0.0001` |" in page
