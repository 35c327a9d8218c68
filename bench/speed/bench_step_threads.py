"""How a server's stepping threads scale: one trainer's arenas in several groups, stepped by a
server with ``--step-threads 1`` and with more, against the same arenas in this process.

Each server (``overtake.server`` subprocess on 127.0.0.1, free ports, started side by side, idle
when not measured) gets a remote vector environment of ``--arenas`` arenas split into
``--parts`` groups (``RemoteHighwayVectorEnv``'s parts: one group each on the server), its
Steps through ``--transport`` (shared memory by default: what a trainer on the server's host
gets). A step sends every part's actions (uniformly random, seeded) before it takes any part's
Steps, so the server has every group ready at once and may step them together. The in-process
column steps the same arenas in one vector environment, on this process's one thread.

After warm-up, the variants alternate in ``--rounds`` rounds of ``--steps`` steps each, so that
drifts of the machine hit all alike. Reported per variant: agent-steps per second (median over
the rounds), the ratio to one stepping thread and to in-process, and the CPU seconds the server
used per step (``/proc``; above the wall time per step means it ran on more than one core).

    .venv/bin/python -m bench.speed.bench_step_threads [--arenas 64] [--parts 2] [--threads 1 2] \
        [--json PATH]
"""

from __future__ import annotations

import os
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

from bench.harness import free_port, process_usage, start_server, stop_process, write_report
from bench.speed.bench_sim import machine_description, pin_threads

PRESET = "min2018"


@dataclass(frozen=True)
class StepThreadsConfig:
    arenas: int = 64
    """arenas of the trainer, split evenly into the parts"""
    parts: int = 2
    """groups the arenas are split into (one group each on the server)"""
    threads: tuple[int, ...] = (1, 2)
    """the servers' --step-threads, one server each"""
    steps: int = 150
    """timed steps per variant and round"""
    rounds: int = 4
    warmup_steps: int = 20
    transport: Literal["shm", "zenoh"] = "shm"
    seed: int = 0
    blas_threads: int | None = 1
    """numpy's BLAS threads (set before numpy is imported; inherited by the servers)"""
    json: Path | None = None


def _remote(endpoint: str, config: StepThreadsConfig) -> Any:
    import gymnasium as gym

    import overtake.client  # noqa: F401 - registers the environments
    from overtake.client.wire.remote import RemoteConfig

    return gym.make_vec(
        "overtake/RemoteHighway-v0",
        num_envs=config.arenas,
        vectorization_mode="vector_entry_point",
        preset=PRESET,
        remote=RemoteConfig(connect=(endpoint,), transport=config.transport),
        parts=config.parts,
    )


def _in_process(config: StepThreadsConfig) -> Any:
    import gymnasium as gym

    import overtake.client  # noqa: F401 - registers the environments

    return gym.make_vec(
        "overtake/Highway-v0",
        num_envs=config.arenas,
        vectorization_mode="vector_entry_point",
        preset=PRESET,
    )


def _stepper(envs: Any, rng: Any, arenas: int) -> Any:
    """One step of ``envs``: every part's actions out before any part's Steps are taken."""
    inner = envs.unwrapped
    slices = getattr(inner, "part_slices", None)
    if slices is None:
        return lambda: envs.step(rng.integers(0, 5, size=arenas))

    def step() -> None:
        actions = rng.integers(0, 5, size=arenas)
        for part, part_slice in enumerate(slices):
            inner.send(part, actions[part_slice])
        for part in range(len(slices)):
            inner.recv(part)

    return step


def main(config: StepThreadsConfig) -> dict[str, Any]:
    threads_note = pin_threads(config.blas_threads)
    import numpy as np

    servers: dict[str, Any] = {}
    envs: dict[str, Any] = {}
    try:
        for threads in config.threads:
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            name = f"{threads} thread(s)"
            servers[name] = start_server(endpoint, 60.0, ("--step-threads", str(threads)))
            envs[name] = _remote(endpoint, config)
        envs["in-process"] = _in_process(config)
        rngs = {name: np.random.default_rng(config.seed) for name in envs}
        steppers = {name: _stepper(env, rngs[name], config.arenas) for name, env in envs.items()}
        for name, env in envs.items():
            env.reset(seed=config.seed)
            for _ in range(config.warmup_steps):
                steppers[name]()
        rates: dict[str, list[float]] = {name: [] for name in envs}
        server_cpu: dict[str, list[float]] = {name: [] for name in servers}
        for round_ in range(config.rounds):
            names = list(envs)
            names = names[round_ % len(names) :] + names[: round_ % len(names)]
            for name in names:
                before = process_usage(servers[name].pid)[0] if name in servers else 0.0
                started = time.perf_counter()
                for _ in range(config.steps):
                    steppers[name]()
                elapsed = time.perf_counter() - started
                rates[name].append(config.arenas * config.steps / elapsed)
                if name in servers:
                    used = process_usage(servers[name].pid)[0] - before
                    server_cpu[name].append(used / elapsed)
    finally:
        for env in envs.values():
            env.close()
        for server in servers.values():
            stop_process(server)
    medians = {name: statistics.median(values) for name, values in rates.items()}
    first = f"{config.threads[0]} thread(s)"
    report: dict[str, Any] = {
        "config": {**config.__dict__, "json": str(config.json) if config.json else None},
        "machine": machine_description(),
        "blas_threads": threads_note,
        "cpu_count": os.cpu_count(),
        "agent_steps_per_s": medians,
        "rounds": rates,
        "server_cores_busy": {n: statistics.median(v) for n, v in server_cpu.items()},
        "ratio_to_one_thread": {n: medians[n] / medians[first] for n in medians},
        "ratio_to_in_process": {n: medians[n] / medians["in-process"] for n in medians},
    }
    print(
        f"{config.arenas} arenas in {config.parts} parts, transport {config.transport}, "
        f"{os.cpu_count()} cores"
    )
    print(
        f"{'variant':<14} {'agent-steps/s':>14} {'vs 1 thread':>12} {'vs in-process':>14} "
        f"{'server cores busy':>18}"
    )
    for name in medians:
        busy = report["server_cores_busy"].get(name)
        print(
            f"{name:<14} {medians[name]:>14.0f} {report['ratio_to_one_thread'][name]:>12.2f} "
            f"{report['ratio_to_in_process'][name]:>14.2f} "
            f"{'-' if busy is None else f'{busy:.2f}':>18}"
        )
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    main(tyro.cli(StepThreadsConfig))
