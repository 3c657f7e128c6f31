"""Training and playing infrastructure: configs, runner, checkpoints, resume, export, multi-process.

The tests run on the real grasp environment when ``d3grasp.envs.grasp_env`` exists, else on
``StandInEnv`` below: a plumbing stand-in with the same VecEnv interface (observation groups of the
task's sizes, auto-reset, time-outs, ``extras["log"]`` / ``extras["episodes"]``) and a trivial
learnable reward. It checks the infrastructure only; it says nothing about grasping.

References are independent of the code under test: a NumPy transcription of the LSTM policy
(normaliser -> LSTM cell -> ELU MLP) for the export and hidden-state tests, counts from the config
arithmetic for optimizer steps, hand-counted outcome tables.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from d3grasp.train import train as train_mod
from d3grasp.train.cli_args import make_train_parser
from d3grasp.train.configs import fit_mini_batches, make_train_cfg, set_cfg_value
from d3grasp.train.play import main as play_main
from d3grasp.train.play import play
from d3grasp.train.run_log import EpisodeStats
from d3grasp.train.runner import (
    CheckpointError,
    D3GraspRunner,
    atomic_torch_save,
    latest_checkpoint,
    read_checkpoint,
)
from tensordict import TensorDict

from d3grasp.envs import DEFAULT_TASK, TASKS, get_task

TESTS_DIR = Path(__file__).resolve().parent
REAL_ENV = importlib.util.find_spec("d3grasp.envs.grasp_env") is not None
STANDIN_FACTORY = "test_train:make_standin_env"
ENV_FACTORY = "d3grasp.envs:make_env" if REAL_ENV else STANDIN_FACTORY
NUM_ACTIONS = 16  # the stand-in env's


def _task_actions(task: str) -> int:
    """Actions of the real task: 4 per-finger squeezes in synergy mode, else 16 joint targets."""
    return 4 if get_task(task).make_cfg().action_mode == "synergy" else 16


# --------------------------------------------------------------------------- stand-in environment
class StandInEnv:
    """rsl-rl VecEnv with the grasp task's interface and sizes; reward = closeness of the action to a
    per-episode target shown in the observation (so PPO has something to learn)."""

    def __init__(
        self,
        task: str,
        num_envs: int | None = None,
        device: str = "cpu",
        seed: int = 0,
        episode_length: int = 6,
    ) -> None:
        self.cfg = get_task(task).make_cfg()
        self.cfg.seed = seed
        self.num_envs = int(num_envs or self.cfg.num_envs)
        self.num_actions = NUM_ACTIONS
        self.max_episode_length = episode_length  # short, so episodes end within a 2-iteration test
        self.device = device
        self.gen = torch.Generator().manual_seed(seed)
        self.episode_length_buf = torch.zeros(self.num_envs, dtype=torch.long)
        # o_tac 11x3 (if tactile), joint pos/vel 16+16, 3 past actions 48, step + sin/cos 3
        self.policy_dim = (33 if self.cfg.tactile_obs else 0) + 16 + 16 + 48 + 3
        self.privileged_dim = 40
        self.target = self._sample((self.num_envs, NUM_ACTIONS))
        self.hist = torch.zeros(self.num_envs, 48)
        self.err = torch.zeros(self.num_envs)
        self.closed = False
        self.episode_count = 0

    def _sample(self, shape: tuple[int, ...]) -> torch.Tensor:
        return torch.rand(shape, generator=self.gen) * 1.6 - 0.8

    def get_observations(self) -> TensorDict:
        n = self.num_envs
        t = self.episode_length_buf.float().unsqueeze(1)
        parts = [self.target, torch.zeros(n, 16), self.hist, t, torch.sin(t), torch.cos(t)]
        if self.cfg.tactile_obs:
            parts.insert(0, torch.tanh(self.hist[:, :33]))
        policy = torch.cat(parts, dim=1)
        privileged = torch.cat(
            [self.target, self.err.unsqueeze(1), torch.zeros(n, self.privileged_dim - 17)], 1
        )
        return TensorDict({"policy": policy, "privileged": privileged}, batch_size=[n])

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict[str, Any]]:
        a = actions.clamp(-1.0, 1.0)
        sq = (a - self.target).square().mean(dim=1)
        self.err = sq
        reward = 1.0 - sq
        self.hist = torch.cat([a, self.hist[:, :32]], dim=1)
        self.episode_length_buf = self.episode_length_buf + 1
        time_outs = self.episode_length_buf >= self.max_episode_length
        dones = time_outs.clone()
        episodes = []
        for i in torch.nonzero(dones).flatten().tolist():
            kind = ("rigid", "deformable")[i % 2]
            episodes.append(
                {
                    "env": i,
                    "object": f"standin_{i}",
                    "kind": kind,
                    "size_bin": ("small", "medium", "large")[i % 3],
                    "grasp_type": ("top", "side", "pinch")[self.episode_count % 3],
                    "s_grasp": bool(sq[i] < 0.5),
                    "s_lift": bool(sq[i] < 0.3),
                    "s_disturb": bool(sq[i] < 0.2),
                    "failure": None if sq[i] < 0.2 else "standin",
                    "max_strain": 0.0 if kind == "rigid" else float(sq[i]),
                }
            )
            self.episode_count += 1
        if dones.any():
            self.target[dones] = self._sample((int(dones.sum()), NUM_ACTIONS))
            self.hist[dones] = 0.0
            self.episode_length_buf[dones] = 0
        extras = {
            "time_outs": time_outs,
            "log": {"Reward/closeness": reward.mean(), "Metrics/s_lift": float(sq.lt(0.3).float().mean())},
            "episodes": episodes,
        }
        return self.get_observations(), reward, dones.float(), extras

    def close(self) -> None:
        self.closed = True


BUILT_ENVS: list[tuple[int, tuple[str, ...]]] = []  # (seed, object ids) of each make_recording_env call


def make_recording_env(task: str, num_envs: int | None = None, device: str = "cpu", seed: int = 0, **kw: Any):
    """The real factory, recording which objects each build put in its worlds."""
    from d3grasp.envs import make_env

    env = make_env(task, num_envs=num_envs, device=device, seed=seed, **kw)
    BUILT_ENVS.append((seed, tuple(e.id for e in env.world_entries)))
    return env


def make_standin_env(
    task: str, num_envs: int | None = None, device: str = "cpu", seed: int = 0
) -> StandInEnv:
    return StandInEnv(task, num_envs=num_envs, device=device, seed=seed)


@pytest.fixture(autouse=True)
def _importable_standin(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(TESTS_DIR))
    monkeypatch.setenv("GIT_PYTHON_REFRESH", "quiet")
    for var in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "LOCAL_WORLD_SIZE"):
        monkeypatch.delenv(var, raising=False)


def _train_argv(
    tmp: Path, task: str = DEFAULT_TASK, iters: int = 2, extra: tuple[str, ...] = ()
) -> list[str]:
    # No critic-only warm-up (the default's 20 iterations): these runs are a few iterations long and
    # check that the actor learns.
    return [
        "--task", task, "--num_envs", "2", "--max_iterations", str(iters), "--num_steps_per_env", "4",
        "--log_root", str(tmp / "logs"), "--env_factory", ENV_FACTORY, "--torch_threads", "1",
        "--agent", "critic_warmup_iterations=0", *extra,
    ]  # fmt: skip


def _run_dirs(tmp: Path, task: str = DEFAULT_TASK) -> list[Path]:
    exp = tmp / "logs" / make_train_cfg(task)["experiment_name"]
    return sorted(p for p in exp.iterdir() if p.is_dir())


# --------------------------------------------------------------------------- NumPy reference policy
def _np_elu(x: np.ndarray) -> np.ndarray:
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def _np_sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


class NumpyLstmPolicy:
    """Independent transcription of the deterministic actor: (x - mean) / (std + 0.01) -> LSTM cell
    (PyTorch gate order i, f, g, o) -> Linear/ELU layers -> linear output = mean action."""

    def __init__(self, state_dict: dict[str, torch.Tensor]) -> None:
        sd = {k: v.detach().double().numpy() for k, v in state_dict.items()}
        self.mean = sd["obs_normalizer._mean"][0]
        self.std = sd["obs_normalizer._std"][0]
        self.w_ih, self.w_hh = sd["rnn.rnn.weight_ih_l0"], sd["rnn.rnn.weight_hh_l0"]
        self.b = sd["rnn.rnn.bias_ih_l0"] + sd["rnn.rnn.bias_hh_l0"]
        idx = sorted({int(k.split(".")[1]) for k in sd if k.startswith("mlp.") and k.endswith(".weight")})
        self.layers = [(sd[f"mlp.{i}.weight"], sd[f"mlp.{i}.bias"]) for i in idx]
        self.hidden = self.w_hh.shape[1]

    def zero_state(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros((n, self.hidden)), np.zeros((n, self.hidden))

    def step(
        self, obs: np.ndarray, h: np.ndarray, c: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = (obs - self.mean) / (self.std + 0.01)
        z = x @ self.w_ih.T + h @ self.w_hh.T + self.b
        i, f, g, o = np.split(z, 4, axis=1)
        c = _np_sigmoid(f) * c + _np_sigmoid(i) * np.tanh(g)
        h = _np_sigmoid(o) * np.tanh(c)
        y = h
        for k, (w, b) in enumerate(self.layers):
            y = y @ w.T + b
            if k < len(self.layers) - 1:
                y = _np_elu(y)
        return y, h, c


class ExportTwins:
    """A checkpoint's TorchScript and ONNX exports stepped beside its NumPy transcription, each
    carrying its own LSTM state; ``step`` asserts they agree."""

    def __init__(self, ref: NumpyLstmPolicy, jit_path: Path, onnx_path: Path) -> None:
        import onnxruntime as ort

        self.ref = ref
        self.jit = torch.jit.load(str(jit_path))
        self.jit.reset()
        self.sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
        self.h, self.c = ref.zero_state(1)
        self.hx = np.zeros((1, 1, ref.hidden), np.float32)
        self.cx = np.zeros((1, 1, ref.hidden), np.float32)

    def step(self, x: np.ndarray) -> np.ndarray:
        """Both exports' actions for the float32 observation ``x`` (1, obs_dim) against the reference's,
        which is returned."""
        want, self.h, self.c = self.ref.step(x.astype(np.float64), self.h, self.c)
        got_jit = self.jit(torch.from_numpy(x)).detach().numpy()
        got_onnx, self.hx, self.cx = self.sess.run(None, {"obs": x, "h_in": self.hx, "c_in": self.cx})
        np.testing.assert_allclose(got_jit, want, atol=2e-5)
        np.testing.assert_allclose(got_onnx, want, atol=2e-5)
        return want


# --------------------------------------------------------------------------- configs
def test_train_cfg_per_task() -> None:
    for name, spec in TASKS.items():
        cfg = make_train_cfg(name)
        assert cfg["obs_groups"]["actor"] == ["policy"]
        assert cfg["obs_groups"]["critic"] == list(spec.critic_groups)
        assert cfg["actor"]["class_name"] == "RNNModel" and cfg["actor"]["rnn_type"] == "lstm"
        assert cfg["actor"]["obs_normalization"] and cfg["critic"]["obs_normalization"]
        assert cfg["critic"]["class_name"] == "MLPModel"
        assert cfg["algorithm"]["schedule"] == "fixed"
    assert make_train_cfg("D3Grasp-DexHand13-Base-v0")["obs_groups"]["critic"] == ["policy"]
    assert make_train_cfg(DEFAULT_TASK)["obs_groups"]["critic"] == ["policy", "privileged"]
    cfg = make_train_cfg(DEFAULT_TASK, num_steps_per_env=8, algorithm={"learning_rate": 1e-3})
    assert cfg["num_steps_per_env"] == 8 and cfg["algorithm"]["learning_rate"] == 1e-3
    assert cfg["algorithm"]["gamma"] == 1.0  # merged, not replaced
    with pytest.raises(ValueError, match="unknown runner config key"):
        make_train_cfg(DEFAULT_TASK, num_step_per_env=8)
    with pytest.raises(ValueError, match="learning_rat"):
        make_train_cfg(DEFAULT_TASK, algorithm={"learning_rat": 1.0})


@pytest.mark.parametrize(
    ("req", "n", "want"), [(4, 2, 2), (4, 32, 4), (4, 6, 3), (4, 7, 1), (4, 1, 1), (4, 9, 3)]
)
def test_fit_mini_batches(req: int, n: int, want: int) -> None:
    assert fit_mini_batches(req, n) == want


def test_per_rank_worlds_and_overrides() -> None:
    parser = make_train_parser()
    args = parser.parse_args(
        ["--rank_num_envs", "48", "8", "--set", "objects.soft_fraction=0.5",
         "--rank_set", '1:objects.kinds=["deformable"]', "--rank_set", "1:sim.soft_iterations=10"]
    )  # fmt: skip
    n0, common, ov0 = train_mod.rank_env_settings(args, train_mod.DistInfo(rank=0, world_size=2))
    n1, _, ov1 = train_mod.rank_env_settings(args, train_mod.DistInfo(rank=1, world_size=2))
    assert (n0, n1, common) == (48, 8, 8)  # 4 mini-batches of 12 and of 2 worlds: equal counts
    assert ov0 == {"objects__soft_fraction": 0.5}
    want1 = {"objects__soft_fraction": 0.5, "objects__kinds": ("deformable",), "sim__soft_iterations": 10}
    assert ov1 == want1
    # One count per rank, a rank that exists, and not both world flags.
    with pytest.raises(ValueError, match="one per rank"):
        train_mod.rank_env_settings(args, train_mod.DistInfo(rank=0, world_size=3))
    bad_rank = parser.parse_args(["--rank_set", "2:sim.iterations=5"])
    with pytest.raises(ValueError, match=r"rank\(s\) \[2\]"):
        train_mod.rank_env_settings(bad_rank, train_mod.DistInfo(rank=0, world_size=2))
    meaning = parser.parse_args(["--rank_set", "1:residual_rate=0.03"])
    with pytest.raises(ValueError, match=r"cannot change \['residual_rate'\]"):
        train_mod.rank_env_settings(meaning, train_mod.DistInfo(rank=0, world_size=2))
    both = parser.parse_args(["--num_envs", "4", "--rank_num_envs", "4", "4"])
    with pytest.raises(ValueError, match="not both"):
        train_mod.rank_env_settings(both, train_mod.DistInfo(rank=0, world_size=2))
    with pytest.raises(SystemExit):
        parser.parse_args(["--rank_set", "objects.kinds=rigid"])  # no rank


def test_episode_stats_rates() -> None:
    stats = EpisodeStats()
    eps = [
        {
            "kind": "rigid",
            "size_bin": "small",
            "grasp_type": "top",
            "s_grasp": 1,
            "s_lift": 1,
            "s_disturb": 0,
        },
        {
            "kind": "rigid",
            "size_bin": "large",
            "grasp_type": "top",
            "s_grasp": 1,
            "s_lift": 0,
            "s_disturb": 0,
        },
        {"kind": "deformable", "size_bin": "small", "grasp_type": "pinch", "s_grasp": 0, "s_lift": 0},
        {
            "kind": "rigid",
            "size_bin": "small",
            "grasp_type": "side",
            "s_grasp": 1,
            "s_lift": 1,
            "s_disturb": 1,
        },
    ]
    stats.add(eps)
    r = stats.rates()
    assert r["Success/episodes"] == 4
    assert r["Success/s_grasp/all"] == pytest.approx(3 / 4)
    assert r["Success/s_lift/kind/rigid"] == pytest.approx(2 / 3)
    assert r["Success/s_disturb/size/small"] == pytest.approx(1 / 3)
    assert r["Success/s_grasp/kind/deformable"] == 0.0
    assert "Success/s_grasp/size/medium" not in r  # no medium episode
    assert r["Success/s_lift/grasp/top"] == pytest.approx(1 / 2)


# --------------------------------------------------------------------------- checkpoints
def test_atomic_save_keeps_old_file_on_failure(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "model_1.pt"
    old_mask = os.umask(0o027)
    try:
        atomic_torch_save({"actor_state_dict": {"w": torch.ones(3)}, "iter": 1}, path)
    finally:
        os.umask(old_mask)
    assert path.stat().st_mode & 0o777 == 0o640  # a plain file's mode under umask 027, not mkstemp's 0600
    real_save = torch.save

    def failing_save(obj: Any, f: Any, *a: Any, **k: Any) -> None:
        real_save({"partial": True}, f)
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", failing_save)
    with pytest.raises(OSError, match="disk full"):
        atomic_torch_save({"actor_state_dict": {"w": torch.zeros(3)}, "iter": 2}, path)
    monkeypatch.undo()
    data = read_checkpoint(path)
    assert data["iter"] == 1 and torch.equal(data["actor_state_dict"]["w"], torch.ones(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model_1.pt"]  # no temp file left behind


def test_checkpoint_discovery(tmp_path: Path) -> None:
    for n in (2, 10, 9):
        (tmp_path / f"model_{n}.pt").write_bytes(b"x")
    (tmp_path / ".model_11.pt.abc.tmp").write_bytes(b"x")  # a save interrupted by a kill
    assert latest_checkpoint(tmp_path).name == "model_10.pt"
    assert latest_checkpoint(tmp_path, r"model_[29]\.pt").name == "model_9.pt"
    with pytest.raises(CheckpointError, match="not found"):
        read_checkpoint(tmp_path / "missing.pt")
    with pytest.raises(CheckpointError, match="cannot read"):
        read_checkpoint(tmp_path / "model_2.pt")


# --------------------------------------------------------------------------- end to end
def test_train_resume_play_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """2 iterations -> checkpoint -> resume 2 more -> play loads it -> exports match the eager policy."""
    # The residual acts from the first step, so these 4-step rollouts (the approach) update the actor:
    # steps whose actions the environment ignores carry no policy gradient (d3grasp.train.ppo).
    acting = ("--set", "residual_start=approach")
    assert train_mod.main(_train_argv(tmp_path, extra=acting)) == 0
    (run1,) = _run_dirs(tmp_path)
    ckpt = run1 / "model_2.pt"
    data = read_checkpoint(ckpt)
    assert data["iter"] == 2
    infos = data["infos"]
    assert infos["task"] == DEFAULT_TASK and infos["num_actions"] == (
        _task_actions(DEFAULT_TASK) if REAL_ENV else NUM_ACTIONS
    )
    assert set(infos["obs_sizes"]) >= {"policy", "privileged"}
    assert (run1 / "params" / "agent.json").is_file() and (run1 / "params" / "env.json").is_file()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run1))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    # rsl-rl's own scalars, the environment's log terms, throughput and grasp outcomes by group
    assert {"Loss/surrogate", "Perf/env_steps_per_s", "Perf/simulation_share", "Success/episodes"} <= tags
    assert any(re.search(r"(^|/)reward/", t, re.IGNORECASE) for t in tags)  # the env's reward terms
    if not REAL_ENV:  # the stand-in's episodes end within these 8 steps; the grasp task's do not
        assert {"Train/mean_reward", "Success/s_lift/all", "Success/s_disturb/kind/rigid"} <= tags
    assert [e.step for e in events.Scalars("Perf/env_steps_per_s")] == [0, 1]
    # Cumulative progress: 2 worlds x 4 steps an iteration; the wall-clock grows.
    assert [e.value for e in events.Scalars("Progress/env_steps")] == [8, 16]
    wall = [e.value for e in events.Scalars("Progress/wall_clock_s")]
    assert 0 < wall[0] < wall[1]
    assert data["progress"]["env_steps"] == 16
    assert ckpt.stat().st_size < 10e6
    # Adam steps: epochs x mini-batches per iteration (2 worlds -> 2 mini-batches of one world).
    cfg = make_train_cfg(DEFAULT_TASK)["algorithm"]
    per_it = cfg["num_learning_epochs"] * fit_mini_batches(cfg["num_mini_batches"], 2)
    steps = {int(s["step"]) for s in data["optimizer_state_dict"]["state"].values()}
    assert steps == {2 * per_it}

    # Resume: a new run folder continues the count and the optimizer state; --set changes the
    # training env's config and params/env.json records it.
    more = ("--resume", "--run_name", "more", "--set", "phases.disturb_per_direction=0.5", *acting)
    assert train_mod.main(_train_argv(tmp_path, extra=more)) == 0
    run2 = _run_dirs(tmp_path)[-1]
    assert run2.name.endswith("_more")
    if REAL_ENV:
        import json

        env1 = json.loads((run1 / "params" / "env.json").read_text())
        env2 = json.loads((run2 / "params" / "env.json").read_text())
        assert env1["phases"]["disturb_per_direction"] == 2.0
        assert env2["phases"]["disturb_per_direction"] == 0.5
    data2 = read_checkpoint(run2 / "model_4.pt")
    assert data2["iter"] == 4
    # The resumed run continues the first one's env-steps and wall-clock.
    events2 = EventAccumulator(str(run2))
    events2.Reload()
    assert [(e.step, e.value) for e in events2.Scalars("Progress/env_steps")] == [(2, 24), (3, 32)]
    assert events2.Scalars("Progress/wall_clock_s")[0].value > wall[1]
    assert data2["progress"]["env_steps"] == 32
    assert {int(s["step"]) for s in data2["optimizer_state_dict"]["state"].values()} == {4 * per_it}
    assert not torch.equal(
        data2["actor_state_dict"]["rnn.rnn.weight_ih_l0"], data["actor_state_dict"]["rnn.rnn.weight_ih_l0"]
    )

    # Play loads it, reports outcomes and exports.
    result = play(
        DEFAULT_TASK, run2 / "model_4.pt", num_envs=2, episodes=3, env_factory=ENV_FACTORY, latency_steps=20
    )
    assert result.export is not None and result.export.jit == run2 / "exported" / "policy.pt"
    assert len(result.episodes) == 3
    assert result.rates["Success/episodes"] == 3
    assert result.export is not None and result.export.jit.is_file() and result.export.onnx is not None
    assert result.latency is not None and result.latency.jit_s > 0

    # Exports vs eager vs a NumPy transcription, over a sequence with the LSTM state carried.
    ref = NumpyLstmPolicy(data2["actor_state_dict"])
    obs_dim = ref.w_ih.shape[1]
    rng = np.random.default_rng(1)
    seq = rng.normal(size=(12, 1, obs_dim)).astype(np.float32) * 2.0
    exports = ExportTwins(ref, result.export.jit, result.export.onnx)
    for t in range(len(seq)):
        want = exports.step(seq[t])
    # The state matters: the last step with a zero state gives a different action.
    fresh, _, _ = ref.step(seq[-1].astype(np.float64), *ref.zero_state(1))
    assert np.abs(fresh - want).max() > 1e-3


def test_exports_go_next_to_the_checkpoint_and_the_shipped_policy_stays_as_installed(tmp_path: Path) -> None:
    from d3grasp.train.play import default_export_dir

    from d3grasp.policies import shipped_checkpoint

    ckpt = tmp_path / "run" / "model_4.pt"
    assert default_export_dir(str(ckpt), ckpt) == tmp_path / "run" / "exported"
    shipped = shipped_checkpoint(DEFAULT_TASK)
    assert default_export_dir("shipped", shipped) == Path("exported")  # the current folder


def test_critic_warmup_leaves_the_actor_unchanged() -> None:
    """In the warm-up iterations only the critic learns, its observation normaliser included, and
    the actor's normaliser stays as it was (the policy the critic fits does not move); after them
    the actor learns too."""
    env = StandInEnv(DEFAULT_TASK, num_envs=4, seed=2)
    cfg = make_train_cfg(DEFAULT_TASK, num_steps_per_env=4, critic_warmup_iterations=2)
    runner = D3GraspRunner(env, cfg, log_dir=None, task_name=DEFAULT_TASK)

    def snapshot(module: torch.nn.Module) -> dict[str, torch.Tensor]:
        return {k: v.clone() for k, v in module.state_dict().items()}

    actor0, critic0 = snapshot(runner.alg.actor), snapshot(runner.alg.critic)
    runner.learn(2)
    actor2, critic2 = snapshot(runner.alg.actor), snapshot(runner.alg.critic)
    assert all(torch.equal(actor0[k], actor2[k]) for k in actor0)
    assert any(not torch.equal(critic0[k], critic2[k]) for k in critic0)
    assert all(p.requires_grad for p in runner.alg.actor.parameters())  # unfrozen again
    runner.learn(1)  # iteration 2: past the warm-up
    actor3 = snapshot(runner.alg.actor)
    assert any(not torch.equal(actor2[k], actor3[k]) for k in actor2)


def test_gradient_probe_changes_nothing_and_reports(tmp_path: Path) -> None:
    """The gradient-noise probe collects rollouts at a checkpoint's weights and updates nothing
    (weights and normalisers of actor and critic); one row per world and rollout; the command writes
    its report."""
    import json

    from d3grasp.train import gradient_noise

    env = StandInEnv(DEFAULT_TASK, num_envs=4, seed=3)
    runner = D3GraspRunner(env, make_train_cfg(DEFAULT_TASK), log_dir=None, task_name=DEFAULT_TASK)
    runner.learn(1)  # normalisers and weights away from their initial values
    ckpt = tmp_path / "model_1.pt"
    runner.save(str(ckpt))
    state = {k: v.clone() for k, v in runner.alg.actor.state_dict().items()}
    state.update({f"critic.{k}": v.clone() for k, v in runner.alg.critic.state_dict().items()})
    runner.episode_stats.clear()
    rows = runner.probe_world_gradients(2)
    n_params = sum(p.numel() for p in runner.alg.actor.parameters())
    assert (
        rows.shape == (2 * 4, n_params) and bool(torch.isfinite(rows).all()) and float(rows.abs().sum()) > 0
    )
    after = dict(runner.alg.actor.state_dict())
    after.update({f"critic.{k}": v for k, v in runner.alg.critic.state_dict().items()})
    assert all(torch.equal(state[k], after[k]) for k in state)
    assert float(runner.episode_stats.counts[0, 0]) == 8  # 6-step episodes in 6-step rollouts
    out = tmp_path / "gn.json"
    argv = ["--task", DEFAULT_TASK, "--num_envs", "4", "--env_factory", STANDIN_FACTORY,
            "--checkpoint", str(ckpt), "--rollouts", "2", "--halves", "2", "--torch_threads", "1",
            "--out", str(out)]  # fmt: skip
    assert gradient_noise.main(argv) == 0
    rep = json.loads(out.read_text())
    assert rep["episodes"] == 8 and rep["parameters"] == n_params and rep["outcomes"]["episodes"] == 8
    assert [r["half"] for r in rep["splits"]] == [2] and set(rep["by_tensor"]) == {
        name for name, _ in runner.alg.actor.named_parameters()
    }
    assert out.with_suffix(".grams.pt").is_file()


def test_agent_overrides_set_nested_runner_values() -> None:
    args = make_train_parser().parse_args(
        ["--agent", "algorithm.learning_rate=1e-4", "--agent", "actor.distribution_cfg.init_std=0.15"]
    )
    cfg = make_train_cfg(DEFAULT_TASK)
    for key, value in args.agent_overrides:
        set_cfg_value(cfg, key, value)
    assert cfg["algorithm"]["learning_rate"] == pytest.approx(1e-4)
    assert cfg["actor"]["distribution_cfg"]["init_std"] == pytest.approx(0.15)
    with pytest.raises(ValueError, match="unknown key 'lr'"):
        set_cfg_value(cfg, "algorithm.lr", 1e-3)
    with pytest.raises(ValueError, match="no 'policy'"):
        set_cfg_value(cfg, "policy.init_std", 1.0)


def test_hidden_state_reset_for_finished_episodes(tmp_path: Path) -> None:
    """During the rollout, a world whose episode ended restarts its LSTM from zero; others carry on."""
    env = StandInEnv(DEFAULT_TASK, num_envs=3, seed=3, episode_length=12)
    cfg = make_train_cfg(DEFAULT_TASK, num_steps_per_env=6)
    cfg["algorithm"]["num_mini_batches"] = 1
    runner = D3GraspRunner(env, cfg, log_dir=None, task_name=DEFAULT_TASK)
    env.episode_length_buf = torch.tensor([env.max_episode_length - 3, 0, 5])  # world 0 ends at step 3
    ref = NumpyLstmPolicy(runner.alg.get_policy().state_dict())
    h, c = ref.zero_state(3)
    obs = env.get_observations()
    ended = np.zeros(3, dtype=bool)
    with torch.inference_mode():
        for _ in range(6):
            runner.alg.act(obs)
            mean = runner.alg.get_policy().output_mean.numpy()  # deterministic part of this step
            want, h, c = ref.step(obs["policy"].double().numpy(), h, c)
            np.testing.assert_allclose(mean, want, atol=1e-5)
            obs, rew, dones, extras = env.step(torch.as_tensor(want, dtype=torch.float32))
            runner.alg.process_env_step(obs, rew, dones, extras)
            d = dones.numpy() > 0
            ended |= d
            h[d] = 0.0
            c[d] = 0.0
    assert ended.tolist() == [True, False, False]


@pytest.mark.parametrize("scale", [0.01, None])
def test_fresh_policy_starts_at_the_zero_residual(scale: float | None) -> None:
    """With the output layer scaled (the default) a fresh policy's mean action is ~0, i.e. the rule-based
    controller in residual mode; rsl-rl's own init (None) gives O(0.1) actions that jitter."""
    env = StandInEnv(DEFAULT_TASK, num_envs=4, seed=0)
    cfg = make_train_cfg(DEFAULT_TASK, actor_output_init_scale=scale)
    cfg["algorithm"]["num_mini_batches"] = 1
    policy = D3GraspRunner(env, cfg, log_dir=None, task_name=DEFAULT_TASK).get_inference_policy("cpu")
    obs, largest = env.get_observations(), 0.0
    with torch.inference_mode():
        for _ in range(6):
            act = policy(obs)
            largest = max(largest, float(act.abs().max()))
            obs, *_ = env.step(act)
    if scale is None:
        assert largest > 0.05
    else:
        assert largest < 0.02


@pytest.mark.skipif(not REAL_ENV, reason="needs the grasp environment")
def test_objects_are_resampled_during_training(tmp_path: Path) -> None:
    """--resample_objects_every 1: each iteration after the first runs on a fresh draw of objects."""
    BUILT_ENVS.clear()
    argv = _train_argv(tmp_path, extra=("--resample_objects_every", "1", "--seed", "5"))
    argv[argv.index("--env_factory") + 1] = "test_train:make_recording_env"
    assert train_mod.main(argv) == 0
    # The first build and one rebuild after iteration 1 (none after the last iteration).
    assert [seed for seed, _ in BUILT_ENVS] == [5, 1005]
    assert BUILT_ENVS[0][1] != BUILT_ENVS[1][1]
    assert read_checkpoint(_run_dirs(tmp_path)[-1] / "model_2.pt")["iter"] == 2


def test_bad_inputs_give_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert train_mod.main(_train_argv(tmp_path, task="D3Grasp-Nope-v0")) == 2
    err = capsys.readouterr().err
    assert "unknown task 'D3Grasp-Nope-v0'" in err and DEFAULT_TASK in err and "Traceback" not in err

    assert (
        play_main(
            ["--task", DEFAULT_TASK, "--checkpoint", str(tmp_path / "nope.pt"), "--env_factory", ENV_FACTORY]
        )
        == 2
    )
    assert "checkpoint not found" in capsys.readouterr().err

    assert train_mod.main(_train_argv(tmp_path, extra=("--resume",))) == 2
    assert "nothing to resume" in capsys.readouterr().err

    assert play_main(["--checkpoint", "x.pt", "--video", "out.avi"]) == 2
    assert "--video must end in .gif or .mp4" in capsys.readouterr().err

    with pytest.raises(SystemExit):  # argparse: usage line and the reason, exit code 2
        train_mod.main(_train_argv(tmp_path, extra=("--resample_objects_every", "-1")))
    assert "must be a non-negative integer, got -1" in capsys.readouterr().err


def test_checkpoint_of_another_task_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Base (no touch, symmetric critic) has a smaller policy observation than Mixed."""
    base = "D3Grasp-DexHand13-Base-v0"
    assert train_mod.main(_train_argv(tmp_path, task=base, iters=1)) == 0
    ckpt = _run_dirs(tmp_path, base)[0] / "model_1.pt"
    code = play_main(
        ["--task", DEFAULT_TASK, "--checkpoint", str(ckpt), "--env_factory", ENV_FACTORY, "--no_export"]
    )
    err = capsys.readouterr().err
    assert code == 2 and "does not fit task" in err and "'policy'" in err and "Traceback" not in err


def test_checkpoint_records_and_checks_how_actions_become_targets(tmp_path: Path) -> None:
    """A residual_rate (or other action-to-target setting) leaves every size the same, so only the
    recorded values can tell a checkpoint of another meaning: it is refused, with the --set that fits."""
    from d3grasp.envs import make_env

    env = make_env(
        DEFAULT_TASK, num_envs=1, seed=0, residual_rate=0.05, action_smoothing=0.7, residual_start="approach"
    )
    cfg = make_train_cfg(DEFAULT_TASK)
    cfg["algorithm"]["num_mini_batches"] = 1
    runner = D3GraspRunner(env, cfg, log_dir=None, device="cpu", task_name=DEFAULT_TASK)
    ckpt = tmp_path / "model_0.pt"
    runner.save(str(ckpt))
    recorded = read_checkpoint(ckpt)["infos"]["policy_interface"]
    assert recorded == {
        "action_mode": "synergy",
        "residual_scale": 0.1,
        "residual_smoothing": 0.2,
        "residual_rate": 0.05,
        "residual_start": "approach",
        "action_smoothing": 0.7,
        "decision_steps": 10,  # the default: a decision held over 10 control steps (issue 42)
        "palm_offset_limit": 0.0,  # no wrist by default (issue 43)
        "palm_yaw_limit": 0.0,
        "palm_offset_rate": 0.02,
        "palm_yaw_rate": 0.3,
        "obs": asdict(env.cfg.obs),  # the observation scales (tests/test_policy_interface.py)
        "rule": {"stop_on": "touch"},  # the prior: the zero action is the touch rule
    }
    runner.load(str(ckpt), load_cfg={"actor": True})  # same settings: loads
    # Evaluation builds its environments as the checkpoint records, --set going over it.
    from d3grasp.eval.evaluate import EvalSettings, run_specs
    from d3grasp.policies.checkpoint import interface_overrides

    assert interface_overrides(read_checkpoint(ckpt)) == recorded
    policy, baseline = run_specs(EvalSettings(checkpoint=str(ckpt), compare_baseline=True))
    assert policy.env_overrides == recorded and baseline.env_overrides == {}
    env.cfg.residual_rate = 0.08
    refused = r"residual_rate=0\.05 \(environment: 0\.08\).*--set residual_rate=0\.05"
    with pytest.raises(CheckpointError, match=refused):
        runner.load(str(ckpt), load_cfg={"actor": True})
    # A checkpoint from before residual_start was recorded acted from t = 0 ("approach").
    env.cfg.residual_rate = 0.05
    data = read_checkpoint(ckpt)
    del data["infos"]["policy_interface"]["residual_start"]
    torch.save(data, ckpt)
    runner.load(str(ckpt), load_cfg={"actor": True})
    env.cfg.residual_start = "grasp"
    with pytest.raises(CheckpointError, match=r"--set residual_start=approach"):
        runner.load(str(ckpt), load_cfg={"actor": True})


@pytest.mark.slow
def test_every_task_trains_and_plays(tmp_path: Path) -> None:
    for task in TASKS:
        assert train_mod.main(_train_argv(tmp_path, task=task)) == 0
        ckpt = latest_checkpoint(_run_dirs(tmp_path, task)[-1])
        assert ckpt.name == "model_2.pt"
        result = play(task, ckpt, num_envs=2, episodes=2, env_factory=ENV_FACTORY, export=False)
        assert len(result.episodes) == 2


def _subprocess_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(TESTS_DIR), env.get("PYTHONPATH", "")])
    env["GIT_PYTHON_REFRESH"] = "quiet"
    return env


@pytest.mark.slow
def test_sigint_leaves_a_loadable_checkpoint(tmp_path: Path) -> None:
    argv = _train_argv(tmp_path, iters=100000)
    proc = subprocess.Popen(
        [sys.executable, "-m", "d3grasp.train.train", *argv],
        env=_subprocess_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert proc.stdout is not None
    deadline = time.time() + 240
    seen_iteration = False
    for line in proc.stdout:
        if "Learning iteration 2/" in line:  # the third iteration finished
            seen_iteration = True
            break
        if time.time() > deadline:
            break
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=120)
    assert seen_iteration, out[-2000:]
    assert proc.returncode == 0, out[-2000:]
    ckpt = latest_checkpoint(_run_dirs(tmp_path)[-1])
    data = read_checkpoint(ckpt)
    assert data["iter"] >= 3 and ckpt.name == f"model_{data['iter']}.pt"


_TORCHRUN_SCRIPT = """
import os, sys, torch
from d3grasp.train.cli_args import make_train_parser
from d3grasp.train.train import run_training
args = make_train_parser().parse_args(sys.argv[2:])
runner = run_training(args)
rank = int(os.environ["RANK"])
torch.save({"actor": runner.alg.get_policy().state_dict(), "critic": runner.alg.critic.state_dict(),
            "seed": runner.env.cfg.seed}, os.path.join(sys.argv[1], f"rank{rank}.pt"))
"""


def test_torchrun_two_cpu_ranks_hold_identical_weights(tmp_path: Path) -> None:
    """Two processes under torchrun on the stand-in environment (~20 s, most of it two interpreters
    importing torch): the ranks' gradients pooled by their worlds, the weights identical after."""
    script = tmp_path / "ddp_train.py"
    script.write_text(_TORCHRUN_SCRIPT)
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
        str(script), str(tmp_path), *_train_argv(tmp_path),
    ]  # fmt: skip
    # Unequal worlds per rank (3 and 1): the gradients are weighed by each rank's share of the worlds.
    i = cmd.index("--num_envs")
    cmd[i : i + 2] = ["--rank_num_envs", "3", "1"]
    res = subprocess.run(cmd, env=_subprocess_env(), capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    r0 = torch.load(tmp_path / "rank0.pt")
    r1 = torch.load(tmp_path / "rank1.pt")
    assert r0["seed"] != r1["seed"]  # each rank simulated different worlds
    for part in ("actor", "critic"):
        for key, value in r0[part].items():
            assert torch.equal(value, r1[part][key]), f"{part}.{key} differs between ranks"
    # Normaliser statistics were pooled over both ranks' samples: (3 + 1) worlds x 4 steps x 2 iterations.
    assert int(r0["actor"]["obs_normalizer.count"]) == (3 + 1) * 4 * 2
    (run,) = _run_dirs(tmp_path)  # only rank 0 writes a run folder
    data = read_checkpoint(run / "model_2.pt")
    assert torch.equal(data["actor_state_dict"]["mlp.0.weight"], r0["actor"]["mlp.0.weight"])
    timings = json.loads((run / "timings.json").read_text())
    assert [t["env_steps"] for t in timings] == [(3 + 1) * 4] * 2  # every rank's worlds counted


# --------------------------------------------------------------------------- the shipped policy
@pytest.mark.skipif(not REAL_ENV, reason="needs the grasp environment")
def test_shipped_policy_fits_its_task_and_its_exports_agree() -> None:
    """The package's trained policy loads on its task (observation and action sizes checked), is small,
    and its shipped TorchScript and ONNX exports act like a NumPy transcription of the checkpoint on
    real observations, LSTM state carried (stale exports would differ)."""
    from d3grasp.controllers import load_actor
    from d3grasp.envs import make_env
    from d3grasp.policies import shipped_checkpoint

    ckpt = shipped_checkpoint(DEFAULT_TASK)
    assert ckpt.stat().st_size < 10e6
    data = read_checkpoint(ckpt)
    assert data["infos"]["task"] == DEFAULT_TASK
    from d3grasp.policies.checkpoint import interface_overrides

    # Built as evaluation builds it: with the action interface the checkpoint records.
    env = make_env(DEFAULT_TASK, num_envs=1, seed=3, eval_mode=True, **interface_overrides(data))
    load_actor(env, DEFAULT_TASK, ckpt, "cpu")  # CheckpointError if sizes or action mapping differ
    exported = ckpt.parent / "exported"
    exports = ExportTwins(
        NumpyLstmPolicy(data["actor_state_dict"]), exported / "policy.pt", exported / "policy.onnx"
    )
    obs = env.get_observations()
    for _ in range(env.script.phase_start["lift"] + 5):  # into the lift, where the policy squeezes
        want = exports.step(obs["policy"].numpy().astype(np.float32))
        obs, *_ = env.step(torch.from_numpy(want.astype(np.float32)))
    assert np.abs(want).max() > 0.05  # a trained policy, not the zero residual of a fresh one


def test_play_passes_set_overrides_to_the_environment(capsys: pytest.CaptureFixture[str]) -> None:
    """``d3grasp-play --set KEY=VALUE`` reaches the environment's config: an unknown key is refused
    there in one line naming it (before any world is built)."""
    assert play_main(["--checkpoint", "baseline", "--set", "phases.no_such_setting=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no_such_setting" in err and "\n" not in err
