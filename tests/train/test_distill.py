"""DAgger from the privileged teacher (d3grasp.train.distill): the student's sequence pass against the
actor acting step by step, the masked loss by hand, and a short run whose checkpoint carries the
wrist in its contract and loads for evaluation."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from d3grasp.train import train as train_mod
from d3grasp.train.configs import make_train_cfg
from d3grasp.train.distill import STUDENT_OPTIMIZER_KEY, masked_mse, sequence_means
from d3grasp.train.runner import read_checkpoint
from rsl_rl.models import RNNModel
from tensordict import TensorDict

from d3grasp.envs import DEFAULT_TASK


@pytest.fixture(autouse=True)
def _one_process(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GIT_PYTHON_REFRESH", "quiet")
    for var in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE"):
        monkeypatch.delenv(var, raising=False)


def test_the_sequence_pass_is_the_actor_acting_step_by_step():
    """The LSTM over a whole rollout, its state zeroed after an episode's end, gives the actions the
    actor gave while acting (rsl-rl's rollout path: ``actor(obs)`` then ``actor.reset(dones)``)."""
    torch.manual_seed(0)
    T, W, D, A = 9, 3, 5, 4
    obs = TensorDict({"policy": torch.randn(T, W, D)}, batch_size=[T, W])
    dones = torch.zeros(T, W)
    dones[2, 0] = dones[5, 1] = dones[5, 2] = 1.0
    actor = RNNModel(
        obs[0], {"actor": ["policy"]}, "actor", A, hidden_dims=[8], rnn_hidden_dim=6,
        obs_normalization=True, distribution_cfg={"class_name": "GaussianDistribution", "init_std": 0.5},
    )  # fmt: skip
    actor.update_normalization(obs.flatten(0, 1))
    with torch.no_grad():
        for p in actor.parameters():
            p.add_(0.3 * torch.randn_like(p))  # away from the initialisation's near-zero outputs
        actor.reset()
        acted = []
        for t in range(T):
            acted.append(actor(obs[t]))
            actor.reset(dones[t])
        h0 = (torch.zeros(1, W, 6), torch.zeros(1, W, 6))
        replayed = sequence_means(actor, obs, dones, h0)
    torch.testing.assert_close(replayed, torch.stack(acted), atol=1e-6, rtol=0)
    assert torch.stack(acted).abs().mean() > 0.05


def test_masked_mse_by_hand():
    pred = torch.tensor([[[1.0, 0.0]], [[3.0, 1.0]], [[0.0, 0.0]]])  # (T=3, W=1, A=2)
    target = torch.tensor([[[0.0, 0.0]], [[1.0, 1.0]], [[5.0, 5.0]]])
    mask = torch.tensor([[True], [True], [False]])
    # steps 0 and 1: (1 + 0 + 4 + 0) / (2 steps x 2 dims) = 1.25; step 2 is masked out
    assert float(masked_mse(pred, target, mask)) == pytest.approx(1.25)
    assert float(masked_mse(pred, target, torch.zeros(3, 1, dtype=torch.bool))) == 0.0


def test_distillation_trains_a_student_whose_checkpoint_carries_the_wrist(tmp_path: Path, capsys):
    """Two DAgger iterations on the real environment with a wrist: the console reports the loss, the
    checkpoint records the wrist in its policy contract, and a wrist-less task refuses the teacher."""
    argv = [
        "--task", DEFAULT_TASK, "--num_envs", "2", "--max_iterations", "2", "--num_steps_per_env", "4",
        "--log_root", str(tmp_path / "logs"), "--torch_threads", "1", "--distill", "teacher",
        "--set", "palm_offset_limit=0.03", "--set", "palm_yaw_limit=0.5", "--set", "residual_start=approach",
    ]  # fmt: skip
    assert train_mod.main(argv) == 0
    out = capsys.readouterr().out
    assert "[distill] it 2 beta" in out and "loss" in out
    exp = tmp_path / "logs" / make_train_cfg(DEFAULT_TASK)["experiment_name"]
    (run,) = sorted(p for p in exp.iterdir() if p.is_dir())
    data = read_checkpoint(run / "model_2.pt")
    assert data["iter"] == 2
    interface = data["infos"]["policy_interface"]
    assert interface["palm_offset_limit"] == 0.03 and interface["palm_yaw_limit"] == 0.5
    assert data["infos"]["num_actions"] == 4 + 4
    # The student's Adam state is saved and continued on resume. Its step count by hand: an
    # iteration fits `epochs` passes over the buffered rollouts (1, then 2) in min(mini_batches, 2
    # worlds) mini-batches; a resumed run starts with an empty buffer (1 rollout).
    dcfg = make_train_cfg(DEFAULT_TASK)["distillation"]
    per_rollout = dcfg["epochs"] * min(dcfg["mini_batches"], 2)
    steps = {int(v["step"]) for v in data[STUDENT_OPTIMIZER_KEY]["state"].values()}
    assert steps == {per_rollout * (1 + 2)}
    resume = argv + ["--resume", "--checkpoint", str(run / "model_2.pt")]
    resume[resume.index("--max_iterations") + 1] = "1"
    lr = dcfg["learning_rate"] / 2  # a resumed run's own learning rate, not the saved one
    assert (
        train_mod.main(resume + ["--run_name", "resumed", "--agent", f"distillation.learning_rate={lr}"]) == 0
    )
    (resumed,) = sorted(exp.glob("*resumed"))
    after = read_checkpoint(resumed / "model_3.pt")[STUDENT_OPTIMIZER_KEY]
    assert {int(v["step"]) for v in after["state"].values()} == {per_rollout * (1 + 2 + 1)}
    assert [g["lr"] for g in after["param_groups"]] == [lr]
    # No wrist: the teacher cannot act, one line.
    bad = argv[:-6] + ["--run_name", "nowrist"]
    assert train_mod.main(bad) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "wrist" in err[0]
