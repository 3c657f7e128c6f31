"""Export a trained actor to TorchScript and ONNX, and time 200 policy steps (the paper's latency).

Both exports are the deterministic policy of one robot (batch 1): observation normaliser -> LSTM ->
MLP head -> mean action. The TorchScript module keeps the LSTM state in buffers (``forward(obs)``
advances it, ``reset()`` zeroes it); the ONNX graph takes and returns it explicitly
(inputs ``obs, h_in, c_in`` -> outputs ``actions, h_out, c_out``), as a deployment loop on another
runtime needs. Built on rsl-rl 5.5's ``as_jit()`` / ``as_onnx()`` model views.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import statistics
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["ExportPaths", "LatencyReport", "export_policy", "measure_latency"]


@dataclass(frozen=True)
class ExportPaths:
    jit: Path
    onnx: Path | None


@dataclass(frozen=True)
class LatencyReport:
    """Seconds for ``steps`` sequential single-robot policy steps (median over repeats)."""

    steps: int
    eager_s: float
    jit_s: float
    onnx_s: float | None  # None without onnxruntime

    def lines(self) -> list[str]:
        out = [
            f"policy latency for {self.steps} steps (batch 1, median): eager {self.eager_s:.4f} s, "
            f"TorchScript {self.jit_s:.4f} s"
            + (f", ONNX Runtime {self.onnx_s:.4f} s" if self.onnx_s is not None else ""),
            "(paper's figure for 200 steps: 0.36 s)",
        ]
        return out


def export_policy(
    actor: torch.nn.Module,
    out_dir: str | os.PathLike[str],
    metadata: dict[str, Any] | None = None,
    onnx: bool = True,
) -> ExportPaths:
    """Write ``policy.pt`` (TorchScript) and ``policy.onnx`` into ``out_dir``; returns their paths.

    ``actor`` is an rsl-rl 5.5 model (``RNNModel`` or ``MLPModel``). ``metadata`` (task, observation
    size, ...) is stored in the ONNX model's metadata properties and the TorchScript extra files.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta = {str(k): str(v) for k, v in (metadata or {}).items()}

    jit_model = actor.as_jit().to("cpu").eval()
    scripted = torch.jit.script(jit_model)
    jit_path = out / "policy.pt"
    tmp = out / ".policy.pt.tmp"
    torch.jit.save(scripted, str(tmp), _extra_files={f"{k}.txt": v for k, v in meta.items()})
    os.replace(tmp, jit_path)

    onnx_path = None
    if onnx:
        onnx_model = actor.as_onnx(verbose=False).to("cpu").eval()
        onnx_path = out / "policy.onnx"
        tmp = out / ".policy.onnx.tmp"
        # The dynamo exporter prints progress lines and warns about LSTM weight attributes: keep play quiet.
        onnx_log = logging.getLogger("torch.onnx")
        level = onnx_log.level
        with warnings.catch_warnings(), contextlib.redirect_stdout(io.StringIO()):
            warnings.simplefilter("ignore")
            onnx_log.setLevel(logging.ERROR)  # "torchvision is not installed" notes are irrelevant here
            torch.onnx.export(
                onnx_model,
                onnx_model.get_dummy_inputs(),
                str(tmp),
                export_params=True,
                opset_version=18,
                input_names=onnx_model.input_names,
                output_names=onnx_model.output_names,
                external_data=False,
            )
            onnx_log.setLevel(level)
        if meta:
            import onnx as onnx_lib

            proto = onnx_lib.load(str(tmp))
            for k, v in meta.items():
                entry = proto.metadata_props.add()
                entry.key, entry.value = k, v
            onnx_lib.save(proto, str(tmp))
        os.replace(tmp, onnx_path)
    return ExportPaths(jit=jit_path, onnx=onnx_path)


def _median_time(fn: Any, repeats: int) -> float:
    fn()  # warm-up (TorchScript profiling runs, allocator)
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return statistics.median(samples)


def measure_latency(
    actor: torch.nn.Module,
    paths: ExportPaths,
    obs_dim: int,
    steps: int = 200,
    repeats: int = 5,
    seed: int = 0,
) -> LatencyReport:
    """Time ``steps`` sequential batch-1 policy steps (state carried) for eager, TorchScript, ONNX."""
    gen = torch.Generator().manual_seed(seed)
    obs_seq = torch.randn(steps, 1, obs_dim, generator=gen)
    actor = actor.to("cpu").eval()

    group = actor.obs_groups[0] if len(actor.obs_groups) == 1 else None

    def eager() -> None:
        from tensordict import TensorDict

        actor.reset()
        with torch.inference_mode():
            for t in range(steps):
                if group is None:
                    raise ValueError("latency measurement needs an actor that reads one observation group")
                actor(TensorDict({group: obs_seq[t]}, batch_size=[1]))

    jit = torch.jit.load(str(paths.jit))

    def scripted() -> None:
        jit.reset()
        with torch.inference_mode():
            for t in range(steps):
                jit(obs_seq[t])

    eager_s = _median_time(eager, repeats)
    jit_s = _median_time(scripted, repeats)
    onnx_s = None
    if paths.onnx is not None:
        try:
            import onnxruntime as ort
        except ImportError:
            ort = None
        if ort is not None:
            opts = ort.SessionOptions()
            opts.intra_op_num_threads = 1
            sess = ort.InferenceSession(str(paths.onnx), opts, providers=["CPUExecutionProvider"])
            names = [i.name for i in sess.get_inputs()]
            obs_np = obs_seq.numpy().astype(np.float32)
            state_shapes = [i.shape for i in sess.get_inputs()[1:]]

            def run_onnx() -> None:
                state = [np.zeros(s, dtype=np.float32) for s in state_shapes]
                for t in range(steps):
                    out = sess.run(None, {names[0]: obs_np[t], **dict(zip(names[1:], state, strict=True))})
                    state = out[1 : 1 + len(state)]

            onnx_s = _median_time(run_onnx, repeats)
    return LatencyReport(steps=steps, eager_s=eager_s, jit_s=jit_s, onnx_s=onnx_s)
