"""Load: how many paced trainers one server (or several behind one router) holds before its
step latency's p99 doubles, and what happens past that point.

A trainer here steps ``--arenas`` remote arenas at ``--rate-hz`` vector steps a second, the
pace of a learner that spends the rest of each step on its network (the soak's DQN learners
manage about 10 on this machine), with random actions. The bench raises the number of trainers
level by level (``--levels``), each level for ``--seconds``: every trainer its own Zenoh
session (its own ``overtake/RemoteHighway`` environment), spread over ``--workers`` processes
as threads, so that the trainers' own CPU is not the limit. Per level: the steps asked for and
done, every trainer's steps per second (min / max: the share), the step latency's p50 / p99
/ max over all trainers, the servers' CPU and the most requests and actions queued at a server
(from ``overtake-status``'s numbers). The ladder stops two levels after the p99 first exceeds
twice the first level's.

Then past the server's capacity in arenas: open requests for more arenas than
``--max-arenas`` leaves are refused with the server's own "full" error, which is reported.

``--servers 2`` puts two servers behind one ``overtake-router``; the trainers connect to the
router and the client spreads them (the least-loaded server, ties at random).

    .venv/bin/python -m bench.reliability.bench_load [--servers 1] [--rate-hz 10] [--arenas 1] \\
        [--levels 1 2 4 8 16 32 64 96 128] [--seconds 20] [--json PATH]
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from bench.harness import (
    REMOTE_ENV_ID,
    free_port,
    latency_summary,
    make_env,
    process_usage,
    random_action,
    stop_process,
)


@dataclass(frozen=True)
class LoadConfig:
    servers: int = 1
    """servers; with more than one they sit behind one overtake-router"""
    rate_hz: float = 10.0
    """vector steps a second each trainer asks for"""
    arenas: int = 1
    """remote arenas per trainer"""
    levels: tuple[int, ...] = (4, 8, 16, 32, 64, 96, 128, 192, 256, 288)
    """trainer counts tried, in order; the first is the baseline, and should be at least
    --workers, so that every level runs the same trainer processes"""
    seconds: float = 20.0
    """steps measured per level (after every trainer has opened and reset its arenas)"""
    workers: int = 4
    """processes the trainers are spread over (threads in each)"""
    max_arenas: int = 256
    """each server's --max-arenas"""
    preset: str = "min2018"
    json: Path | None = None


def server_names(count: int) -> list[str]:
    return [f"load{i}" for i in range(count)]


# --- worker mode: a process stepping its share of the trainers ---------------------------------


def worker_main(endpoint: str, trainers: int, arenas: int, preset: str, rate_hz: float) -> None:
    """Open ``trainers`` environments (each its own session), say ready, wait for the go line
    with the seconds to step, step them paced in threads, print one JSON line."""
    from overtake.client.wire.remote import RemoteConfig
    from overtake.protocol.errors import ServerFull

    remote = RemoteConfig(connect=(endpoint,), connect_timeout_s=60.0, request_timeout_s=60.0)
    envs = []
    refused: list[str] = []
    for index in range(trainers):
        try:
            env = make_env(REMOTE_ENV_ID, arenas, preset=preset, remote=remote)
        except ServerFull as error:  # past the servers' arenas: reported, not fatal
            refused.append(str(error))
            continue
        env.reset(seed=index)
        envs.append(env)
    print("ready", flush=True)
    seconds = float(sys.stdin.readline())
    times: list[list[float]] = [[] for _ in envs]
    errors: list[str] = []
    period = 1.0 / rate_hz
    start = time.perf_counter() + 0.05

    def pace(index: int) -> None:
        env, rng = envs[index], np.random.default_rng(index)
        # Staggered starts: trainers of a real run do not step in phase.
        next_t = start + period * rng.random()
        try:
            while True:
                now = time.perf_counter()
                if now - start >= seconds:
                    return
                if next_t > now:
                    time.sleep(next_t - now)
                t0 = time.perf_counter()
                _, _, terminated, truncated, _ = env.step(random_action(rng, arenas))
                times[index].append(time.perf_counter() - t0)
                if arenas == 1 and (terminated or truncated):
                    env.reset()
                # Late? Step at once, but never in a burst to catch up.
                next_t = max(next_t + period, time.perf_counter())
        except Exception as error:  # reported with the figures
            errors.append(f"trainer {index}: {error!r}")

    threads = [threading.Thread(target=pace, args=(i,)) for i in range(len(envs))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for env in envs:
        env.close()
    out = {"times": times, "seconds": seconds, "errors": errors, "refused": refused}
    print(json.dumps(out), flush=True)


# --- the ladder ------------------------------------------------------------------------------


def start_topology(config: LoadConfig) -> tuple[str, list[subprocess.Popen[bytes]]]:
    """The servers (and a router when there are several); the endpoint trainers use."""
    from overtake.client.wire.remote import Connection, RemoteConfig

    procs: list[subprocess.Popen[bytes]] = []
    server_args = ["--log-level", "warning", "--max-arenas", str(config.max_arenas)]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    if config.servers == 1:
        listen = [("--listen", endpoint)]  # trainers connect to the server itself
    else:
        procs.append(
            subprocess.Popen(
                [str(Path(sys.executable).with_name("overtake-router")), "--listen", endpoint],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        )
        # Listening nowhere ("--listen" with no endpoint), as docs/remote-hosts.md's router
        # recipe has it: everything goes through the router.
        listen = [("--listen", "--connect", endpoint)] * config.servers
    for name, where in zip(server_names(config.servers), listen, strict=True):
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "overtake.server", *where, "--name", name, *server_args],
                stdout=subprocess.DEVNULL,
            )
        )
    connection = Connection(RemoteConfig(connect=(endpoint,), connect_timeout_s=60.0))
    try:
        deadline = time.monotonic() + 60
        while {s.server for s in connection.discover()} != set(server_names(config.servers)):
            if time.monotonic() > deadline:
                raise TimeoutError(f"the servers did not all answer on {endpoint} within 60 s")
            time.sleep(0.1)  # polling for the servers' queryables to be declared
    finally:
        connection.close()
    return endpoint, procs


class StatusSampler:
    """The servers' queues, sampled in a thread while a level runs."""

    def __init__(self, endpoint: str) -> None:
        from overtake.client.wire.remote import Connection, RemoteConfig

        self.connection = Connection(RemoteConfig(connect=(endpoint,), request_timeout_s=5.0))
        self.most_actions = self.most_requests = 0
        self.dropped = 0
        # The most each server held at once (at a level's end the trainers are closing).
        self.most_arenas: dict[str, int] = {}
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.done.wait(0.5):
            for status in self.connection.discover():
                self.most_actions = max(self.most_actions, status.queued_actions)
                self.most_requests = max(self.most_requests, status.queued_requests)
                self.dropped = max(self.dropped, status.dropped_frames)
                self.most_arenas[status.server] = max(
                    self.most_arenas.get(status.server, 0), status.arenas_used
                )

    def close(self) -> None:
        self.done.set()
        self.thread.join(10)
        self.connection.close()


def run_level(config: LoadConfig, endpoint: str, servers: list[int], trainers: int):
    shares = [
        trainers // config.workers + (i < trainers % config.workers) for i in range(config.workers)
    ]
    workers = [
        subprocess.Popen(
            [sys.executable, "-m", "bench.reliability.bench_load", "--worker", endpoint, str(n),
             str(config.arenas), config.preset, str(config.rate_hz)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
            cwd=Path(__file__).resolve().parents[2],
        )
        for n in shares
        if n
    ]  # fmt: skip
    sampler = None
    try:
        for worker in workers:
            line = worker.stdout.readline() if worker.stdout else ""
            if line.strip() != "ready":
                raise RuntimeError(f"worker {worker.pid} did not get ready: {line!r}")
        sampler = StatusSampler(endpoint)
        cpu_before = [process_usage(pid)[0] for pid in servers]
        t0 = time.monotonic()
        for worker in workers:
            assert worker.stdin is not None
            worker.stdin.write(f"{config.seconds}\n")
            worker.stdin.flush()
        outputs = [
            json.loads(w.communicate(timeout=config.seconds + 120)[0].splitlines()[-1])
            for w in workers
        ]
        wall = time.monotonic() - t0
        cpu = [
            process_usage(pid)[0] - before for pid, before in zip(servers, cpu_before, strict=True)
        ]
    finally:
        if sampler is not None:
            sampler.close()
        for worker in workers:
            stop_process(worker)
    assert sampler is not None  # made before the workers were told to go
    times = [t for out in outputs for t in out["times"]]
    latency = latency_summary([s for t in times for s in t])
    rates = [len(t) / config.seconds for t in times]
    return {
        "trainers": trainers,
        "stepping": len(times),
        "arenas": len(times) * config.arenas,
        "asked_steps_per_s": trainers * config.rate_hz,
        "done_steps_per_s": round(sum(rates), 1),
        "rate_min": round(min(rates), 2),
        "rate_max": round(max(rates), 2),
        "p50_ms": round(latency["p50_ms"], 2),
        "p99_ms": round(latency["p99_ms"], 2),
        "max_ms": round(latency["max_ms"], 1),
        "server_cpu": [round(c / wall, 2) for c in cpu],
        "most_arenas_per_server": dict(sorted(sampler.most_arenas.items())),
        "most_queued_actions": sampler.most_actions,
        "most_queued_requests": sampler.most_requests,
        "dropped_frames": sampler.dropped,
        "errors": [e for out in outputs for e in out["errors"]],
        "refused": [e for out in outputs for e in out["refused"]],
    }


def past_capacity(config: LoadConfig, endpoint: str) -> str:
    """Ask for more arenas than the servers hold: the refusal, in the servers' words."""
    from overtake.client.wire.remote import RemoteConfig

    remote = RemoteConfig(connect=(endpoint,), connect_timeout_s=30.0)
    try:
        env = make_env(REMOTE_ENV_ID, config.max_arenas + 1, preset=config.preset, remote=remote)
    except Exception as error:
        return f"{type(error).__name__}: {error}"
    env.close()
    return f"accepted {config.max_arenas + 1} arenas (no refusal)"


def main(config: LoadConfig) -> dict[str, Any]:
    print(
        f"load: {config.servers} server(s), trainers of {config.arenas} {config.preset} arena(s) "
        f"at {config.rate_hz:g} steps/s, {config.seconds:g} s a level "
        f"({platform.machine()}, {os.cpu_count()} cores)",
        flush=True,
    )
    print("| trainers | asked steps/s | done | each min-max | p50 ms | p99 ms | max ms | "
          "server CPU | queued (most) |")  # fmt: skip
    print("|---:|---:|---:|---|---:|---:|---:|---|---|")
    endpoint, procs = start_topology(config)
    servers = [p.pid for p in procs[-config.servers :]]
    levels: list[dict[str, Any]] = []
    past: str | None = None
    try:
        beyond = None
        for trainers in config.levels:
            level = run_level(config, endpoint, servers, trainers)
            levels.append(level)
            print(
                f"| {trainers} | {level['asked_steps_per_s']:g} | {level['done_steps_per_s']} | "
                f"{level['rate_min']}-{level['rate_max']} | {level['p50_ms']} | "
                f"{level['p99_ms']} | {level['max_ms']} | {level['server_cpu']} | "
                f"{level['most_queued_actions']} actions, {level['most_queued_requests']} "
                f"requests |"
                + (f" errors: {level['errors'][:2]}" if level["errors"] else "")
                + (
                    f" {len(level['refused'])} refused: {level['refused'][0]}"
                    if level["refused"]
                    else ""
                ),
                flush=True,
            )
            if beyond is None and level["p99_ms"] > 2 * levels[0]["p99_ms"]:
                beyond = 0
            elif beyond is not None:
                beyond += 1
                if beyond >= 2:
                    break
        past = past_capacity(config, endpoint)
        print(f"asking for {config.max_arenas + 1} arenas: {past}", flush=True)
    finally:
        for proc in reversed(procs):
            stop_process(proc)
    held = [lv["trainers"] for lv in levels if lv["p99_ms"] <= 2 * levels[0]["p99_ms"]]
    out = {
        "config": {**asdict(config), "json": None},
        "levels": levels,
        "most_trainers_before_p99_doubles": max(held) if held else None,
        "past_capacity": past,
    }
    print(f"most trainers before the p99 doubles: {out['most_trainers_before_p99_doubles']}")
    if config.json is not None:
        config.json.write_text(json.dumps(out, indent=2))
    return out


def cli() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        endpoint, trainers, arenas, preset, rate_hz = sys.argv[2:7]
        worker_main(endpoint, int(trainers), int(arenas), preset, float(rate_hz))
        return
    main(tyro.cli(LoadConfig))


if __name__ == "__main__":
    cli()
