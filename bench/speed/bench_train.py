"""Training throughput: environment steps per second with learning, in-process and remote.

One run measures, for each input configuration asked for, ``overtake-train``'s own loop
(``overtake.trainers.train.main``) three times on the same settings: with the simulator in
this process, and with it in an ``overtake.server`` subprocess on 127.0.0.1 (a free port),
with overlap in one part (the learner updates while the server simulates: overtake-train's
--overlap on) and in two (the arenas in halves, one simulated while the learner
acts and learns on the other), and in lock-step (--overlap off). Only
the steps after learning has started count (the loop then acts, steps, stores and updates, as
in a real run). Where the time goes comes from the loop's own clock (``metrics.jsonl``: act =
network forward for acting, env = the environment's step, or with overlap the wait for a
half's Steps, replay = storing, update = sampling and gradient steps); the lock-step run's env
share is simulation plus transport, and its transport part is estimated as remote env time
minus in-process env time per step.

    .venv/bin/python -m bench.speed.bench_train [--steps 2000] [--rounds 1] [--json PATH]
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

from bench.harness import free_port, start_server, stop_process, write_report
from bench.speed.bench_sim import machine_description

# overtake.trainers.learning.learner.Precision, written here: importing it loads PyTorch
# before main() has set its threads (main checks that the two agree).
Precision = Literal["fp32", "bf16", "fp16"]


@dataclass(frozen=True)
class TrainBenchConfig:
    steps: int = 2_000
    """environment steps timed per run, after learning_starts"""
    learning_starts: int = 400
    num_envs: int = 4
    algo: str = "ddqn"
    inputs: tuple[str, ...] = ("both", "lidar")
    torch_threads: int = 2
    parts: tuple[int, ...] = (1, 2, 0)
    """the remote runs: overlapped in that many parts, 0 for lock-step (none: --parts with no
    value)"""
    precisions: tuple[Precision, ...] = ("fp32",)
    """in-process runs in each of these precisions, in this order (overtake-train
    --precision; one may come again, to alternate: ratios use each one's mean); the remote
    runs in the first"""
    device: str = "cpu"
    """overtake-train --device"""
    spin_s: float = 0.002
    """the shared-memory channel's spin before sleeping, on both sides (overtake-server
    --spin-s, overtake-train --spin-s)"""
    rounds: int = 1
    """every run this many times, in-process and remote alternating which goes first, so that
    the machine's drift between runs falls on both alike; ratios are of the means, and each
    round's own ratios are printed too"""
    json: Path | None = None


def run_once(
    config: TrainBenchConfig,
    inputs: str,
    connect: str | None,
    run_dir: Path,
    recording: Any = None,
    overlap_parts: int = 1,
    precision: Precision = "fp32",
) -> dict[str, Any]:
    """One ``overtake-train`` run; ``recording``: its RecordingConfig (None: the default);
    ``overlap_parts``: remote arenas overlapped in that many parts (1, overtake-train's
    default: learning during the round trip), or 0 for lock-step; ``precision``:
    overtake-train's --precision."""
    from overtake.client.episodes.scenario import Where
    from overtake.client.wire.remote_config import RemoteConfig
    from overtake.trainers.learning.learner import DQNConfig
    from overtake.trainers.train import TrainConfig, main

    total = config.learning_starts + config.steps
    started = time.perf_counter()
    extra = {} if recording is None else {"recording": recording}
    main(
        TrainConfig(
            algo=config.algo,
            inputs=inputs,
            num_envs=config.num_envs,  # type: ignore
            total_steps=total,
            seed=0,
            run_dir=run_dir,
            where=Where(
                connect=() if connect is None else (connect,),
                link=RemoteConfig(spin_s=config.spin_s),
            ),
            overlap="on" if overlap_parts > 0 else "off",
            overlap_parts=max(overlap_parts, 1),
            progress=False,
            log_every=config.learning_starts,
            checkpoint_every=10 * total,
            torch_threads=config.torch_threads,
            device=config.device,
            precision=precision,
            dqn=DQNConfig(
                learning_starts=config.learning_starts, replay_size=max(10_000, 2 * total)
            ),
            **extra,
        )
    )
    wall = time.perf_counter() - started
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    timed = [
        r
        for r in records
        if r["kind"] == "train" and r["step"] > config.learning_starts and r["updates"] > 0
    ]
    steps = sum(config.learning_starts for _ in timed)
    seconds = sum(config.learning_starts / r["steps_per_s"] for r in timed)
    shares = {
        key: sum(r[key] * config.learning_starts / r["steps_per_s"] for r in timed) / seconds
        for key in ("time_env", "time_act", "time_replay", "time_update")
    }
    return {
        "inputs": inputs,
        "where": where_label(connect, overlap_parts, precision),
        "precision": precision,
        "steps_timed": steps,
        "steps_per_s": steps / seconds,
        "wall_s": wall,
        "shares": shares,
        "ms_per_step": {k: 1000 * v * seconds / steps for k, v in shares.items()},
    }


def where_label(connect: str | None, overlap_parts: int, precision: str = "fp32") -> str:
    """How a run's simulator was reached: in-process (in-process bf16 for a precision other
    than fp32), remote lock-step, remote overlap/k."""
    if connect is None:
        return "in-process" if precision == "fp32" else f"in-process {precision}"
    return f"remote overlap/{overlap_parts}" if overlap_parts else "remote lock-step"


def main(config: TrainBenchConfig) -> dict[str, Any]:
    os.environ.setdefault("OMP_NUM_THREADS", str(config.torch_threads))
    from overtake.trainers.learning import learner

    assert get_args(Precision) == get_args(learner.Precision), "Precision out of date"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = start_server(endpoint, 60.0, ("--spin-s", str(config.spin_s)))
    results = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for round_ in range(config.rounds):
                for inputs in config.inputs:
                    runs = [
                        (None, 0, index, precision)
                        for index, precision in enumerate(config.precisions)
                    ] + [(endpoint, parts, 0, config.precisions[0]) for parts in config.parts]
                    if round_ % 2:
                        runs.reverse()
                    for connect, parts, index, precision in runs:
                        if connect is None:
                            name = f"{inputs}-inproc-{index}-{precision}-{round_}"
                        else:
                            name = f"{inputs}-{f'overlap{parts}' if parts else 'lockstep'}-{round_}"
                        result = run_once(
                            config,
                            inputs,
                            connect,
                            Path(tmp) / name,
                            overlap_parts=parts,
                            precision=precision,
                        )
                        result["round"] = round_
                        results.append(result)
    finally:
        stop_process(server)
    print(
        f"{config.algo}, {config.num_envs} envs, torch threads {config.torch_threads}, "
        f"device {config.device}, "
        f"{config.steps} timed steps after {config.learning_starts} (one update per 4 steps)"
    )
    print(
        f"{'inputs':>6} {'where':>16} {'steps/s':>8}  ms/step: {'env':>6} {'act':>6} "
        f"{'replay':>6} {'update':>7}"
    )
    for r in results:
        ms = r["ms_per_step"]
        print(
            f"{r['inputs']:>6} {r['where']:>16} {r['steps_per_s']:8.1f}           "
            f"{ms['time_env']:6.2f} {ms['time_act']:6.2f} {ms['time_replay']:6.2f} "
            f"{ms['time_update']:7.2f}"
        )
    by = {(r["inputs"], r["where"]): r for r in results}
    by_round = {(r["inputs"], r["where"], r["round"]): r for r in results}
    rate: dict[tuple[str, str], float] = {
        key: statistics.fmean(r["steps_per_s"] for r in results if (r["inputs"], r["where"]) == key)
        for key in by
    }
    for inputs in config.inputs:
        local = by[(inputs, where_label(None, 0, config.precisions[0]))]
        base = rate[(inputs, local["where"])]
        ratios = ", ".join(
            f"{where} {rate[(inputs, where)] / base:.2f}x"
            for where in (
                *dict.fromkeys(
                    where_label(None, 0, p) for p in config.precisions if p != config.precisions[0]
                ),
                *(where_label("remote", k) for k in config.parts),
            )
        )
        print(f"{inputs}: steps/s against in-process: {ratios}")
        if config.rounds > 1:
            local_where = where_label(None, 0, config.precisions[0])
            for where in (where_label("remote", k) for k in config.parts):
                each = [
                    by_round[(inputs, where, r)]["steps_per_s"]
                    / by_round[(inputs, local_where, r)]["steps_per_s"]
                    for r in range(config.rounds)
                ]
                print(f"{inputs}: {where} each round: {', '.join(f'{x:.2f}x' for x in each)}")
        if (inputs, "remote lock-step") in by:
            lock = by[(inputs, "remote lock-step")]
            transport = lock["ms_per_step"]["time_env"] - local["ms_per_step"]["time_env"]
            print(f"{inputs}: lock-step transport and serving ~{transport:.2f} ms per step")
    report = {
        "config": {k: str(v) for k, v in vars(config).items()},
        "machine": machine_description(),
        "results": results,
    }
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    import tyro

    main(tyro.cli(TrainBenchConfig))
