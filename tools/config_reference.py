"""Write docs/configuration.md: every ``--set`` key (the environment's config, ``d3grasp/envs/config.py``
and the dataclasses it nests) and every ``--agent`` key (the runner and PPO config,
``train/configs.py``) with its default and what it means, read from the code itself: the defaults
from the default task's configs, the meanings from the comment on or above each field or key. The
other tasks' differences from the default task follow.

    python tools/config_reference.py            # rewrite docs/configuration.md
    python tools/config_reference.py --check    # exit 1 if it is out of date (tests/test_docs.py)
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import io
import json
import sys
import tokenize
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "docs" / "configuration.md"


def _comments(source: str) -> tuple[dict[int, str], dict[int, str]]:
    """(trailing comments by line, whole-line comments by line) of a source text."""
    trailing: dict[int, str] = {}
    standalone: dict[int, str] = {}
    lines = source.splitlines()
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            continue
        row, col = tok.start
        text = tok.string.lstrip("#").strip()
        if lines[row - 1][:col].strip():
            trailing[row] = text
        else:
            standalone[row] = text
    return trailing, standalone


def _meaning(line: int, trailing: dict[int, str], standalone: dict[int, str]) -> str:
    """The comment on ``line``, else the block of whole-line comments right above it, as one line."""
    if line in trailing:
        return trailing[line]
    block = []
    row = line - 1
    while row in standalone:
        block.append(standalone[row])
        row -= 1
    return " ".join(reversed(block))


def _first_sentence(text: str) -> str:
    if ". " in text:
        text = text[: text.index(". ") + 1]
    return text.replace("|", "\\|")  # a table cell: an escaped bar, not a column


def _field_meanings(cls: type) -> dict[str, str]:
    source = inspect.getsource(sys.modules[cls.__module__])
    trailing, standalone = _comments(source)
    tree = ast.parse(source)
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls.__name__)
    out = {}
    for item in node.body:
        if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
            out[item.target.id] = _meaning(item.lineno, trailing, standalone)
    return out


def _value(v: Any) -> str:
    if isinstance(v, tuple):
        v = list(v)
    return "`" + json.dumps(v, default=str) + "`"


def env_rows(cfg: Any, prefix: str = "") -> list[tuple[str, str, str]]:
    """(``--set`` key, default, meaning) of every leaf of an environment config, depth first."""
    rows = []
    meanings = _field_meanings(type(cfg))
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            rows += env_rows(value, f"{key}.")
        else:
            rows.append((key, _value(value), _first_sentence(meanings.get(f.name, ""))))
    return rows


def _dict_meanings(source: str, name: str) -> dict[str, str]:
    """Dotted key -> comment of the module-level dict literal ``name`` in ``source``."""
    trailing, standalone = _comments(source)
    tree = ast.parse(source)
    target = next(
        n.value
        for n in tree.body
        if isinstance(n, ast.AnnAssign) and isinstance(n.target, ast.Name) and n.target.id == name
    )
    out: dict[str, str] = {}

    def walk(node: ast.Dict, prefix: str) -> None:
        for k, v in zip(node.keys, node.values, strict=True):
            if not isinstance(k, ast.Constant):
                continue
            key = f"{prefix}{k.value}"
            out[key] = _meaning(k.lineno, trailing, standalone)
            if isinstance(v, ast.Dict):
                walk(v, f"{key}.")

    assert isinstance(target, ast.Dict)
    walk(target, "")
    return out


def _flat(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for k, v in d.items():
        if isinstance(v, dict) and k != "obs_groups":
            out += _flat(v, f"{prefix}{k}.")
        else:
            out.append((f"{prefix}{k}", v))
    return out


def agent_rows(task: str) -> list[tuple[str, str, str]]:
    from d3grasp.train import configs

    meanings = _dict_meanings(Path(configs.__file__).read_text(encoding="utf-8"), "_BASE_CFG")
    return [
        (k, _value(v), _first_sentence(meanings.get(k, ""))) for k, v in _flat(configs.make_train_cfg(task))
    ]


def render() -> str:
    from d3grasp.train.configs import make_train_cfg

    from d3grasp.envs.registry import DEFAULT_TASK, TASKS, get_task

    base_env = dict((k, v) for k, v, _ in env_rows(get_task(DEFAULT_TASK).make_cfg()))
    base_agent = dict(_flat(make_train_cfg(DEFAULT_TASK)))
    lines = [
        "# Configuration reference",
        "",
        "Every setting a command takes, with the default task's value",
        f"(`{DEFAULT_TASK}`) and its meaning, read from the code by `tools/config_reference.py`",
        "(`tests/test_docs.py` fails when this page is out of date). `--set KEY=VALUE` (on",
        "`d3grasp-train`, `d3grasp-play` and `d3grasp-eval`; JSON values: `--set",
        "'objects.kinds=[\"rigid\"]'`) sets an environment setting; `--agent KEY=VALUE` (on",
        "`d3grasp-train`) a runner or PPO setting. In Python: `make_env(task, sim__substeps=8)`. The",
        "meaning is the first sentence of the comment in the code, which says why. The evaluation sets",
        "`num_envs`, `seed`, `device`, `eval_mode`, `objects`, `grasp_types` and `perception` itself.",
        "",
        "## Environment (`--set`)",
        "",
        "| key | default | meaning |",
        "|---|---|---|",
    ]
    lines += [f"| `{k}` | {v} | {m} |" for k, v, m in env_rows(get_task(DEFAULT_TASK).make_cfg())]
    lines += ["", "## Runner and PPO (`--agent`)", "", "| key | default | meaning |", "|---|---|---|"]
    lines += [f"| `{k}` | {v} | {m} |" for k, v, m in agent_rows(DEFAULT_TASK)]
    lines += [
        "",
        "## Tasks",
        "",
        "| task | objects | actor reads | critic reads | closing prior (`rule.stop_on`) | experiment name |",
        "|---|---|---|---|---|---|",
    ]
    for task in TASKS:
        cfg, agent = get_task(task).make_cfg(), make_train_cfg(task)
        actor = "touch, proprioception, clock" if cfg.tactile_obs else "proprioception, clock (no touch)"
        critic = " + ".join(agent["obs_groups"]["critic"])
        lines.append(
            f"| `{task}` | {', '.join(cfg.objects.kinds)} | {actor} | {critic} | {cfg.rule.stop_on} | "
            f"`{agent['experiment_name']}` |"
        )
    lines += ["", "## The other tasks' settings", ""]
    lines += ["What each task sets otherwise than the default task.", ""]
    for task in TASKS:
        if task == DEFAULT_TASK:
            continue
        env = {k: v for k, v, _ in env_rows(get_task(task).make_cfg())}
        agent = dict(_flat(make_train_cfg(task)))
        diffs = [f"`--set {k}`: {v}" for k, v in env.items() if base_env.get(k) != v]
        diffs += [f"`--agent {k}`: {_value(v)}" for k, v in agent.items() if base_agent.get(k) != v]
        lines.append(f"- **{task}**: " + ("; ".join(diffs) if diffs else "none") + ".")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="exit 1 if docs/configuration.md is out of date")
    args = p.parse_args(argv)
    text = render()
    if args.check:
        if OUT.read_text(encoding="utf-8") != text:
            print(f"{OUT} is out of date: python tools/config_reference.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    print(f"wrote {OUT}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
