"""A checkpoint's recorded policy interface covers the observation settings: a changed scale leaves
every size the same, so the record is what refuses it. Checked on configs and the checkpoint's own
record, without building an environment."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

import pytest

from d3grasp.envs.config import (
    POLICY_INTERFACE_BEFORE,
    BaselineConfig,
    GraspEnvConfig,
    ObservationConfig,
    policy_interface,
)
from d3grasp.envs.registry import DEFAULT_TASK, apply_overrides, get_task
from d3grasp.policies.checkpoint import CheckpointError, check_fits, interface_overrides, read_checkpoint


def _check(infos: dict[str, Any], cfg: GraspEnvConfig, path: str = "model_0.pt") -> None:
    """check_fits as evaluation and training call it, with the checkpoint's own sizes (no env)."""
    check_fits(
        infos,
        path,
        task=infos.get("task"),
        obs_sizes=dict(infos["obs_sizes"]),
        obs_groups=dict(infos.get("obs_groups", {})),
        num_actions=int(infos.get("num_actions", 5)),
        policy_interface=policy_interface(cfg),
        models=("actor",),
    )


def _infos(recorded: dict[str, Any]) -> dict[str, Any]:
    return {"task": DEFAULT_TASK, "obs_sizes": {"policy": 10}, "num_actions": 5, "policy_interface": recorded}


def test_observation_scales_are_recorded_and_a_mismatch_refused() -> None:
    cfg = get_task(DEFAULT_TASK).make_cfg()
    recorded = policy_interface(cfg)
    assert recorded["obs"] == asdict(cfg.obs)
    infos = _infos(recorded)
    _check(infos, cfg)
    other = get_task(DEFAULT_TASK).make_cfg()
    other.obs.joint_vel_scale = 0.2
    with pytest.raises(CheckpointError) as err:
        _check(infos, other)
    msg = str(err.value)
    assert "\n" not in msg
    assert "obs.joint_vel_scale=0.1 (environment: 0.2)" in msg and "--set obs.joint_vel_scale=0.1" in msg
    assert "other observations" in msg and "actions mean" not in msg
    # Evaluation builds the environment as recorded: the scale comes back, the check passes.
    rebuilt = apply_overrides(other, interface_overrides({"infos": infos}))
    assert rebuilt.obs.joint_vel_scale == 0.1
    _check(infos, rebuilt)


def test_a_record_without_an_observation_setting_has_the_values_of_before() -> None:
    """A setting a checkpoint does not record did not exist when it was trained: it is compared with
    the value of then (POLICY_INTERFACE_BEFORE), not with whatever the default is now."""
    cfg = get_task(DEFAULT_TASK).make_cfg()
    recorded = policy_interface(cfg)
    del recorded["obs"]["pad_force_per_unit"]
    infos = _infos(recorded)
    _check(infos, cfg)
    cfg.obs.pad_force_per_unit = 20.0
    with pytest.raises(CheckpointError, match=r"obs\.pad_force_per_unit=10\.0 \(environment: 20\.0\)"):
        _check(infos, cfg)


def test_the_values_of_before_are_todays_defaults() -> None:
    """Written out in config.py so that a later change of a default refuses the old checkpoints; the
    day the record began they are the defaults (change this test with the default, not the record)."""
    assert POLICY_INTERFACE_BEFORE["obs"] == asdict(ObservationConfig())
    assert POLICY_INTERFACE_BEFORE["rule"] == {"stop_on": BaselineConfig().stop_on}


def test_shipped_checkpoint_predates_the_record_and_still_fits() -> None:
    from d3grasp.policies import shipped_checkpoint

    path = shipped_checkpoint(DEFAULT_TASK)
    infos = read_checkpoint(path)["infos"]
    cfg = get_task(DEFAULT_TASK).make_cfg()
    # It acted every step, before decisions were held (decision_steps, default 10): today's defaults
    # refuse it with the flag that fits, and the build from its record fits.
    with pytest.raises(CheckpointError, match=r"decision_steps=1 \(environment: 10\)"):
        _check(infos, cfg, str(path))
    cfg.decision_steps = 1
    _check(infos, cfg, str(path))
    built = apply_overrides(get_task(DEFAULT_TASK).make_cfg(), interface_overrides({"infos": infos}))
    _check(infos, built, str(path))  # as evaluation and play build it
    cfg.obs.palm_offset_scale = 5.0
    with pytest.raises(CheckpointError, match=r"obs\.palm_offset_scale=10\.0 \(environment: 5\.0\)"):
        _check(infos, cfg, str(path))


def test_the_shipped_ablation_checkpoints_fit_their_tasks() -> None:
    """``d3grasp-eval --ablation shipped``: the three checkpoints in the paper's order, each on the task
    it records, each fitting the environment its record builds; Base's prior reads no touch."""
    from d3grasp.eval.evaluate import EvalSettings, run_specs
    from d3grasp.policies import SHIPPED_ABLATION

    settings = EvalSettings(checkpoint=None, ablation=("shipped",), perception="paper")
    settings.validate()
    specs = run_specs(settings)
    assert [s.task for s in specs] == list(SHIPPED_ABLATION)
    assert [s.label for s in specs] == ["Base", "Base+Tactile", "Asymmetric"]
    for spec in specs:
        data = read_checkpoint(spec.checkpoint)
        assert data["infos"]["task"] == spec.task
        built = apply_overrides(get_task(spec.task).make_cfg(), interface_overrides(data))
        _check(data["infos"], built, str(spec.checkpoint))
        # The prior it was trained on comes back with the build, whatever the task's default.
        assert built.rule.stop_on == ("stall" if spec.label == "Base" else "touch")
    assert get_task("D3Grasp-DexHand13-Base-v0").make_cfg().rule.stop_on == "stall"
    assert get_task("D3Grasp-DexHand13-BaseTactile-v0").make_cfg().rule.stop_on == "touch"


def test_the_prior_is_recorded_and_another_refused() -> None:
    """A residual's zero action is the rule: Base's stall-prior checkpoint on the touch rule would read
    the pads through its prior, so the record refuses it; a record without the prior (every checkpoint
    from before it) was trained on the touch rule."""
    from d3grasp.policies import _ROOT, SHIPPED_ABLATION

    base_task = "D3Grasp-DexHand13-Base-v0"
    infos = read_checkpoint(_ROOT / SHIPPED_ABLATION[base_task] / "model.pt")["infos"]
    assert infos["policy_interface"]["rule"] == {"stop_on": "stall"}
    touch = apply_overrides(get_task(base_task).make_cfg(), interface_overrides({"infos": infos}))
    touch.rule.stop_on = "touch"
    with pytest.raises(CheckpointError) as err:
        _check(infos, touch)
    msg = str(err.value)
    assert "\n" not in msg and "--set rule.stop_on=stall" in msg and "another rule" in msg
    cfg = get_task(DEFAULT_TASK).make_cfg()
    recorded = policy_interface(cfg)
    assert recorded["rule"] == {"stop_on": "touch"}
    del recorded["rule"]
    _check(_infos(recorded), cfg)
    cfg.rule.stop_on = "stall"
    with pytest.raises(CheckpointError, match=r"rule\.stop_on='touch' \(environment: 'stall'\)"):
        _check(_infos(recorded), cfg)
