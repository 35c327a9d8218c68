"""Decision latency of an exported policy: ONNX Runtime against PyTorch, same observations.

For each paper's network (Min et al.'s camera + LIDAR network, Ho's grid network, Fayjie et
al.'s two-stream network) a few training steps make a checkpoint, ``overtake-export`` writes
its ONNX model, and one car of the preset is driven for ``--decisions`` decisions. At every
decision both policies (``overtake-eval``'s PyTorch ``GreedyPolicy`` and ``overtake-drive
--onnx``'s ``OnnxPolicy``: frame stacking, the network, the action mask) answer the same
observation, in alternating order, one thread each; their wall-clock times give p50 and p99
per decision and the ratio PyTorch / ONNX Runtime, measured in the same run.

    .venv/bin/python -m bench.speed.bench_onnx [--decisions 500] [--json PATH]
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import tyro

from overtake.client.episodes.scenario import Where
from overtake.client.policies.onnx_policy import OnnxPolicy
from overtake.trainers.evaluate import GreedyPolicy
from overtake.trainers.export import ExportConfig
from overtake.trainers.export import main as export
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import COMMAND as train_command

NETWORKS = {
    "min2018": "both",  # camera convolutions + LIDAR LSTM (Table II)
    "ho2018": "grid",  # the proposed network on the occupancy grid (Fig. 5)
    "fayjie2018": "camera-map",  # two convolution streams (Fig. 1)
}


@dataclass(frozen=True)
class OnnxBenchConfig:
    decisions: int = 500
    """decisions timed per network"""
    presets: tuple[str, ...] = tuple(NETWORKS)
    json: Path | None = None


def checkpoint_for(preset: str, work: Path) -> Path:
    run_dir = work / preset
    train_command.run(
        [
            "--preset", preset, "--inputs", NETWORKS[preset], "--run-dir", str(run_dir),
            "--total-steps", "64", "--num-envs", "2", "--learning-starts", "48",
            "--replay-size", "600", "--torch-threads", "1", "--no-progress", "--sink", "off",
        ]
    )  # fmt: skip
    return run_dir / CHECKPOINT_NAME


def measure(preset: str, decisions: int, work: Path) -> dict[str, Any]:
    path = checkpoint_for(preset, work)
    model = work / f"{preset}.onnx"
    export(ExportConfig(checkpoint=path, out=model, check_decisions=0))
    checkpoint = load_checkpoint(path)
    envs = Where().open(preset, {}, 1)
    try:
        space = envs.single_observation_space
        by_torch = GreedyPolicy(checkpoint, 1, space, preset)
        by_onnx = OnnxPolicy(model, 1, space, preset, threads=1)
        obs, info = envs.reset(seed=0)
        starting = np.ones(1, dtype=bool)
        resetting = np.zeros(1, dtype=bool)
        times: dict[str, list[float]] = {"torch": [], "onnx": []}
        agree = 0
        for i in range(decisions):
            order = ("torch", "onnx") if i % 2 == 0 else ("onnx", "torch")
            chosen = {}
            for name in order:
                policy = by_torch if name == "torch" else by_onnx
                began = time.perf_counter()
                with torch.no_grad():
                    chosen[name] = policy(obs, info, starting)
                times[name].append(time.perf_counter() - began)
            agree += int(chosen["torch"][0] == chosen["onnx"][0])
            obs, _, terminated, truncated, info = envs.step(chosen["torch"])
            starting, resetting = resetting, terminated | truncated
    finally:
        envs.close()
    out: dict[str, Any] = {"preset": preset, "inputs": NETWORKS[preset], "decisions": decisions}
    for name, values in times.items():
        ms = np.array(values) * 1e3
        out[f"{name}_p50_ms"] = float(np.percentile(ms, 50))
        out[f"{name}_p99_ms"] = float(np.percentile(ms, 99))
    out["p50_ratio_torch_over_onnx"] = out["torch_p50_ms"] / out["onnx_p50_ms"]
    out["p99_ratio_torch_over_onnx"] = out["torch_p99_ms"] / out["onnx_p99_ms"]
    out["same_actions"] = agree / decisions
    out["onnx_bytes"] = model.stat().st_size
    return out


def main(config: OnnxBenchConfig) -> list[dict[str, Any]]:
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-onnx-") as work:
        for preset in config.presets:
            rows.append(measure(preset, config.decisions, Path(work)))
    print(
        f"decision latency, one car, one thread ({platform.processor() or platform.machine()}, "
        f"{os.cpu_count()} cores), {config.decisions} decisions per network"
    )
    print(
        "| preset (network) | PyTorch p50 / p99 ms | ONNX Runtime p50 / p99 ms "
        "| PyTorch / ONNX p50 | same actions |"
    )
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['preset']} ({r['inputs']}) | {r['torch_p50_ms']:.2f} / {r['torch_p99_ms']:.2f} "
            f"| {r['onnx_p50_ms']:.2f} / {r['onnx_p99_ms']:.2f} "
            f"| {r['p50_ratio_torch_over_onnx']:.2f}x | {r['same_actions']:.0%} |"
        )
    if config.json is not None:
        config.json.write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    main(tyro.cli(OnnxBenchConfig))
