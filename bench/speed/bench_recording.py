"""What Rerun recording costs training: steps per second with recording on, against off.

One run trains the same ``overtake-train`` configuration (Double DQN, 4 environments, learning
on) several ways, interleaved and repeated so that a drift of the machine touches every way
alike, and compares the median steps per second of each with its baseline measured in the same
run (only steps after learning started count; see ``bench.speed.bench_train``):

- in-process, the trainer's recording off, against on at the default decimation
  (``--record-every 10``: summaries plus environment 0's view every 10th step) and at every
  step (``--record-every 1``);
- remote, against ``overtake.server`` subprocesses that record every arena at the server's
  default rate (``--sink file``: one round in 10) and every round (``--record-every 1``),
  against one that does not (the trainer's own recording off in all three).

It also reports the .rrd bytes written per 1,000 environment steps.

    .venv/bin/python -m bench.speed.bench_recording [--steps 2000] [--repeats 3] [--json PATH]
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bench.harness import free_port, start_server, stop_process, write_report
from bench.speed.bench_sim import machine_description
from bench.speed.bench_train import TrainBenchConfig, run_once


@dataclass(frozen=True)
class RecordingBenchConfig:
    steps: int = 2_000
    """environment steps timed per run, after learning_starts"""
    learning_starts: int = 400
    num_envs: int = 4
    inputs: tuple[str, ...] = ("both", "lidar")
    repeats: int = 3
    """runs of each way, interleaved, each repeat starting at another way"""
    torch_threads: int = 2
    json: Path | None = None


def main(config: RecordingBenchConfig) -> dict[str, Any]:
    from overtake.server.service.server_config import SERVER_RECORD_EVERY
    from overtake.trainers.config.train_config import TRAINER_RECORD_EVERY
    from overtake.viz.recording import RecordingConfig

    os.environ.setdefault("OMP_NUM_THREADS", str(config.torch_threads))
    train = TrainBenchConfig(
        steps=config.steps,
        learning_starts=config.learning_starts,
        num_envs=config.num_envs,
        torch_threads=config.torch_threads,
    )
    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        plain_ep = f"tcp/127.0.0.1:{free_port()}"
        default_ep = f"tcp/127.0.0.1:{free_port()}"
        every_ep = f"tcp/127.0.0.1:{free_port()}"
        default_rrd, every_rrd = tmp / "server-default.rrd", tmp / "server-every.rrd"
        servers = [
            start_server(plain_ep, 60.0),
            start_server(default_ep, 60.0, extra=("--sink", "file", "--rrd", str(default_rrd))),
            start_server(
                every_ep,
                60.0,
                extra=("--sink", "file", "--rrd", str(every_rrd), "--record-every", "1"),
            ),
        ]
        off = RecordingConfig(sink="off")
        ways = {
            "in-process, recording off": (None, off),
            f"in-process, recording every {TRAINER_RECORD_EVERY} (default)": (
                None,
                RecordingConfig(record_every=TRAINER_RECORD_EVERY),
            ),
            "in-process, recording every step": (None, RecordingConfig(record_every=1)),
            "remote, server not recording": (plain_ep, off),
            f"remote, server recording every {SERVER_RECORD_EVERY} (default)": (default_ep, off),
            "remote, server recording every round": (every_ep, off),
        }
        try:
            for inputs in config.inputs:
                for repeat in range(config.repeats):
                    # Each repeat starts at another way: no way is always the first (cold) run.
                    names = list(ways)
                    order = names[repeat % len(names) :] + names[: repeat % len(names)]
                    for way in order:
                        connect, recording = ways[way]
                        run_dir = tmp / f"{inputs}-{repeat}-{len(results)}"
                        result = run_once(train, inputs, connect, run_dir, recording)
                        rrd = run_dir / "trainer.rrd"
                        result.update(
                            way=way,
                            repeat=repeat,
                            rrd_bytes=rrd.stat().st_size if rrd.exists() else 0,
                        )
                        results.append(result)
                        print(
                            f"{inputs:>6} {way:<48} {result['steps_per_s']:7.1f} steps/s",
                            file=sys.stderr,
                        )
        finally:
            for server in servers:
                stop_process(server)
        server_rrd_bytes = {
            path.name: path.stat().st_size if path.exists() else 0
            for path in (default_rrd, every_rrd)
        }

    baselines = {
        "in-process": "in-process, recording off",
        "remote": "remote, server not recording",
    }
    summary = []
    print(
        f"Double DQN, {config.num_envs} envs, torch threads {config.torch_threads}, "
        f"{config.steps} timed steps after {config.learning_starts}, median of "
        f"{config.repeats} interleaved runs"
    )
    print(f"{'inputs':>6} {'way':<48} {'steps/s':>8} {'vs off':>7} {'rrd MB/1k steps':>16}")
    for inputs in config.inputs:
        medians = {
            way: statistics.median(
                r["steps_per_s"] for r in results if r["inputs"] == inputs and r["way"] == way
            )
            for way in ways
        }
        for way in ways:
            base = medians[baselines[way.split(",")[0]]]
            runs = [r for r in results if r["inputs"] == inputs and r["way"] == way]
            total_steps = config.learning_starts + config.steps
            mb = statistics.median(r["rrd_bytes"] for r in runs) / 1e6 / total_steps * 1000
            row = {
                "inputs": inputs,
                "way": way,
                "steps_per_s": medians[way],
                "ratio_to_off": medians[way] / base,
                "rrd_mb_per_1k_steps": mb,
            }
            summary.append(row)
            print(
                f"{inputs:>6} {way:<48} {medians[way]:8.1f} {row['ratio_to_off']:6.3f}x {mb:16.2f}"
            )
    for name, size in server_rrd_bytes.items():
        print(f"{name}: {size / 1e6:.1f} MB over all its remote runs")
    report = {
        "config": {k: str(v) for k, v in vars(config).items()},
        "machine": machine_description(),
        "summary": summary,
        "results": results,
        "server_rrd_bytes": server_rrd_bytes,
    }
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    import tyro

    main(tyro.cli(RecordingBenchConfig))
