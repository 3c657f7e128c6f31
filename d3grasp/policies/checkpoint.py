"""Checkpoints and their contract: written atomically, read as data (never as code) with one-line
errors, and checked against the environment they are loaded into (task, observation sizes, action
count and the settings that turn actions into joint targets) before any weights are touched.

A ``.pt`` file is a pickle, and unpickling may call any function the file names: a shared policy
file could run a shell command on load. Every checkpoint is therefore read with
``torch.load(weights_only=True)``, which rebuilds only tensors, containers and plain values, plus the
few data types of ``DATA_TYPES``. A file that names anything else is refused in one line naming
the type and ``--trust-checkpoint``, the flag that reads it the old, unsafe way.
"""

from __future__ import annotations

import os
import pathlib
import pickle
import re
from pathlib import Path
from typing import Any

import torch

from d3grasp.files import atomic_write

__all__ = [
    "DATA_TYPES",
    "TRUST_FLAG",
    "CheckpointError",
    "UnsafeCheckpointError",
    "atomic_torch_save",
    "check_fits",
    "checkpoint_iteration",
    "latest_checkpoint",
    "observation_sizes",
    "read_checkpoint",
    "refuse_code",
]

CHECKPOINT_RE = re.compile(r"^model_(\d+)\.pt$")


TRUST_FLAG = "--trust-checkpoint"
"""The commands' flag that reads a checkpoint with ``weights_only=False`` (it may run code)."""


class CheckpointError(ValueError):
    """A checkpoint that is missing, unreadable or trained for different observations."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint that names a function or class outside ``DATA_TYPES``: reading it could run code."""


def _numpy_data_types() -> list[Any]:
    """NumPy's scalars, arrays and numeric dtypes: how a ``np.float64`` or an array in a record
    pickles. Rebuilding them only copies bytes into memory."""
    import numpy as np

    try:  # NumPy 2 moved the module; 1.x still has it under np.core
        from numpy._core import multiarray
    except ImportError:  # pragma: no cover - NumPy 1.x
        from numpy.core import multiarray  # type: ignore[no-redef]
    dtype_classes = [
        getattr(np.dtypes, name)
        for name in dir(getattr(np, "dtypes", object()))
        if name.endswith("DType") and not name.startswith(("Object", "Void", "StringDType"))
    ]
    return [multiarray.scalar, multiarray._reconstruct, np.ndarray, np.dtype, *dtype_classes]


def _path_types() -> list[Any]:
    """File paths (a run folder recorded as a ``Path``): a path object holds strings only."""
    return [pathlib.PosixPath, pathlib.PurePosixPath, pathlib.WindowsPath, pathlib.PureWindowsPath]


DATA_TYPES: tuple[Any, ...] = (*_numpy_data_types(), *_path_types())
"""The non-tensor types a checkpoint may hold beside torch's own (tensors, dicts, lists, tuples,
strings, numbers, ``None``): values, none of which runs code when rebuilt. d3grasp-train writes
plain types only; these let a record that carries a NumPy value or a path load as data."""

_DATA_TYPE_NAMES = {f"{t.__module__}.{t.__qualname__}" for t in DATA_TYPES}


def _code_globals(path: Path) -> list[str]:
    """The functions and classes the checkpoint's pickle names outside torch's safe set and
    ``DATA_TYPES``, read from its opcodes without running any; [] for a legacy (non-zip) file,
    which ``torch.load(weights_only=True)`` then judges."""
    import torch

    try:
        names = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception:  # not a zip checkpoint: the weights-only unpickler decides below
        return []
    return [n for n in names if n not in _DATA_TYPE_NAMES]


def _refusal(path: Path, names: list[str]) -> UnsafeCheckpointError:
    what = ", ".join(names)
    return UnsafeCheckpointError(
        f"checkpoint {path} holds {what}, which is code, not data: loading it could run anything; "
        f"refused (read a file you trust the source of with {TRUST_FLAG})"
    )


def refuse_code(path: str | os.PathLike[str]) -> None:
    """Raise ``UnsafeCheckpointError`` if ``path`` names code (before an environment is built)."""
    names = _code_globals(Path(path))
    if names:
        raise _refusal(Path(path), names)


def atomic_torch_save(obj: Any, path: str | os.PathLike[str]) -> None:
    """``torch.save`` that never leaves a truncated file at ``path``: temp file, fsync, rename."""
    atomic_write(path, lambda f: torch.save(obj, f))


def checkpoint_iteration(path: str | os.PathLike[str]) -> int | None:
    m = CHECKPOINT_RE.match(Path(path).name)
    return int(m.group(1)) if m else None


def latest_checkpoint(run_dir: str | os.PathLike[str], pattern: str | None = None) -> Path:
    """The checkpoint with the highest iteration in ``run_dir`` (optionally names matching a regex)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise CheckpointError(f"run folder not found: {run_dir}")
    rx = re.compile(pattern) if pattern else None
    found = [
        p
        for p in run_dir.iterdir()
        if p.is_file() and CHECKPOINT_RE.match(p.name) and (rx is None or rx.fullmatch(p.name))
    ]
    if not found:
        what = f"matching '{pattern}' " if pattern else ""
        raise CheckpointError(f"no checkpoint model_<N>.pt {what}in {run_dir}")
    return max(found, key=lambda p: checkpoint_iteration(p) or 0)


def read_checkpoint(
    path: str | os.PathLike[str], map_location: str = "cpu", *, trust: bool = False
) -> dict[str, Any]:
    """Load a checkpoint dict as data, turning a missing or unreadable file into a one-line
    ``CheckpointError`` and a file that names code into an ``UnsafeCheckpointError``.

    ``trust``: read it with ``weights_only=False`` (``--trust-checkpoint``), which runs whatever the
    file names: only for a file from a source the user trusts (old checkpoints that pickled objects).
    """
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    if not trust:
        refuse_code(path)
    try:
        if trust:
            data = torch.load(path, map_location=map_location, weights_only=False)
        else:
            # The weights-only unpickler is the guard; the scan above only names what it would refuse.
            with torch.serialization.safe_globals(list(DATA_TYPES)):
                data = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # A legacy-format file the scan could not read: name the global the unpickler refused. Any
        # other unpickling error is a broken file.
        found = sorted(set(re.findall(r"GLOBAL ([\w.]+)", str(exc)))) if not trust else []
        if found:
            raise _refusal(path, found) from None
        raise CheckpointError(f"cannot read checkpoint {path}: {type(exc).__name__}: {exc}") from None
    except Exception as exc:  # pickle / zip errors have many types
        raise CheckpointError(f"cannot read checkpoint {path}: {type(exc).__name__}: {exc}") from None
    if not isinstance(data, dict) or "actor_state_dict" not in data:
        raise CheckpointError(f"{path} is not an rsl-rl 5.x checkpoint (no 'actor_state_dict')")
    return data


def interface_overrides(data: dict[str, Any]) -> dict[str, Any]:
    """The environment settings under which a checkpoint's actions mean what they meant in training
    (its recorded ``policy_interface``, ``d3grasp.envs.config.POLICY_INTERFACE``) as ``make_env``
    overrides; {} for a checkpoint without the record. Evaluation and play build the environment with
    them, so a policy trained with another action mode runs as trained without flags."""
    interface = (data.get("infos") or {}).get("policy_interface")
    if not interface:
        return {}
    return as_trained(interface, known_only=True)


def as_trained(interface: dict[str, Any], known_only: bool = False) -> dict[str, Any]:
    """A checkpoint's recorded ``policy_interface`` completed with ``POLICY_INTERFACE_BEFORE``: a
    setting it does not record did not exist yet, so it was trained with the behaviour from before
    it (observation and rule settings field by field). ``known_only``: of those assumed values, only
    the fields this version's config sections have (they become ``make_env`` overrides)."""
    from dataclasses import fields

    from d3grasp.envs.config import (
        OBSERVATION_INTERFACE,
        POLICY_INTERFACE_BEFORE,
        RULE_INTERFACE,
        BaselineConfig,
        ObservationConfig,
    )

    out = {**POLICY_INTERFACE_BEFORE, **interface}
    for key, section in ((OBSERVATION_INTERFACE, ObservationConfig), (RULE_INTERFACE, BaselineConfig)):
        before = POLICY_INTERFACE_BEFORE[key]
        assert isinstance(before, dict)
        if known_only:
            known = {f.name for f in fields(section)}
            before = {k: v for k, v in before.items() if k in known}
        out[key] = {**before, **(interface.get(key) or {})}
    return out


def _flat(interface: dict[str, Any]) -> dict[str, Any]:
    """``{"obs": {"joint_vel_scale": 0.1}}`` -> ``{"obs.joint_vel_scale": 0.1}`` (``--set`` names)."""
    out: dict[str, Any] = {}
    for key, value in interface.items():
        if isinstance(value, dict):
            out |= {f"{key}.{k}": v for k, v in value.items()}
        else:
            out[key] = value
    return out


def observation_sizes(obs: Any) -> dict[str, int]:
    """Width of every observation group of a TensorDict (what a checkpoint records and is checked by)."""
    # TensorDict iterates over its batch dimension, not its keys: .keys() is needed.
    return {str(k): int(obs[k].shape[-1]) for k in obs.keys()}  # noqa: SIM118


def check_fits(
    infos: dict[str, Any] | None,
    path: str,
    *,
    task: str | None,
    obs_sizes: dict[str, int],
    obs_groups: dict[str, list[str]],
    num_actions: int,
    policy_interface: dict[str, Any] | None,
    models: tuple[str, ...],
) -> None:
    """Raise ``CheckpointError`` if a checkpoint's ``models`` read observations of other sizes, act
    with another action count, or were trained with other action-to-target, observation-scale or
    prior (``rule.stop_on``) settings.

    ``obs_sizes``, ``obs_groups``, ``num_actions``, ``policy_interface`` and ``task`` describe the
    environment it is loaded into; a checkpoint without the record (a foreign rsl-rl one) is left to
    ``load_state_dict``.
    """
    if not infos or "obs_sizes" not in infos:
        return
    theirs = infos["obs_sizes"]
    groups = {g for m in models for g in infos.get("obs_groups", {}).get(m, theirs)}
    for model in models:
        groups |= set(obs_groups.get(model, []))
    diff = {g: (theirs.get(g), obs_sizes.get(g)) for g in sorted(groups) if theirs.get(g) != obs_sizes.get(g)}
    ckpt_actions = infos.get("num_actions", num_actions)
    if diff or ckpt_actions != num_actions:
        sizes = ", ".join(f"'{g}' {a} vs {b}" for g, (a, b) in diff.items())
        if ckpt_actions != num_actions:
            sizes += f"{', ' if sizes else ''}actions {ckpt_actions} vs {num_actions}"
        raise CheckpointError(
            f"checkpoint {path} was trained on task '{infos.get('task')}' and does not fit task "
            f"'{task}' (checkpoint vs environment sizes: {sizes})"
        )
    _check_policy_interface(infos.get("policy_interface"), policy_interface, path)
    if infos.get("task") and task and infos["task"] != task:
        print(f"[d3grasp] note: checkpoint trained on '{infos['task']}', running it on '{task}'")


def _check_policy_interface(theirs: dict[str, Any] | None, mine: dict[str, Any] | None, path: str) -> None:
    """Refuse a checkpoint trained with other action-to-target settings, observation scales or prior
    (same sizes, other meaning)."""
    if not theirs or mine is None:
        return  # checkpoints from before the record, or an env without a GraspEnvConfig
    from d3grasp.envs.config import OBSERVATION_INTERFACE, RULE_INTERFACE

    # A setting the checkpoint does not record did not exist yet: it was trained with the old behaviour.
    # One that this environment does not have is not compared (a newer checkpoint's setting).
    theirs, mine = _flat(as_trained(theirs)), _flat(mine)
    diff = {k: (v, mine[k]) for k, v in theirs.items() if k in mine and mine[k] != v}
    if diff:
        given = ", ".join(f"{k}={a!r} (environment: {b!r})" for k, (a, b) in diff.items())
        fix = " ".join(f"--set {k}={a}" for k, (a, _) in diff.items())
        seen = any(k.startswith(f"{OBSERVATION_INTERFACE}.") for k in diff)
        prior = any(k.startswith(f"{RULE_INTERFACE}.") for k in diff)
        acted = any(not k.startswith((f"{OBSERVATION_INTERFACE}.", f"{RULE_INTERFACE}.")) for k in diff)
        what = " and ".join(
            (["its actions mean something else"] if acted else [])
            + (["its zero action would be another rule"] if prior else [])
            + (["it would see other observations"] if seen else [])
        )
        raise CheckpointError(
            f"checkpoint {path} was trained with {given}: {what} in this environment; build it as "
            f"trained ({fix})"
        )
