"""Zenoh shared memory (SHM) against plain ``bytes`` for overtake's message sizes, on one host.

A ping-pong between two child processes on 127.0.0.1, with overtake's transport settings: the
echo listens as a peer (the server), the pinger connects as a client (the trainer), no
scouting, ``CongestionControl.BLOCK``, ``Priority.DATA_HIGH``. The pinger puts S bytes on
``bench/ping``; the echo's callback takes them with ``sample.payload.to_bytes()`` (a decoder
needs that copy: Zenoh's Python buffers have no buffer protocol) and answers at once on
``bench/pong`` with their length and last byte, which the pinger checks. The processes are
linked twice, ``transport/shared_memory/enabled`` false on one link and true on the other
(Zenoh's default). Modes: ``no-shm`` puts the ``bytes`` on the first link; ``bytes`` puts them
on the second (overtake's way; Zenoh's default ``transport_optimization`` copies puts over
3 KiB into its own SHM pool); ``shm`` copies them into ``ShmProvider.alloc(S)`` (msgpack cannot
pack into it) and puts that buffer on the second. The echo counts the pings whose
``sample.payload.as_shm()`` is not ``None``: those came through shared memory.

For each S (Steps of 1, 8 and 64 arenas), after a warm-up, the modes alternate in rounds
(ABCABC...) so that all see the same load. Reported: round trip p50 and p90, the CPU time per
round trip of each process (``time.process_time``, Zenoh's threads included; the echo reports
its own when asked by a one-byte ping) and the ratios between the modes.

    .venv/bin/python -m bench.speed.bench_shm [--sizes-bytes 8500 65000 513000] [--rounds 4] \
        [--json runs/perf/shm.json]
"""

from __future__ import annotations

import json
import os
import queue
import signal
import struct
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import tyro
import zenoh
from zenoh.shm import GarbageCollect, ShmProvider

from bench.harness import free_port, stop_process, write_report, zenoh_pools_removed
from bench.speed.bench_remote import wait_matching
from bench.speed.bench_sim import machine_description
from overtake.ipc.transport import TransportConfig, open_session

ROOT = Path(__file__).resolve().parents[2]
MODES = ("no-shm", "bytes", "shm")
CPU_QUERY = b"\xff"  # a one-byte ping: the echo answers with its CPU time and SHM count
CPU_REPLY = struct.Struct("<dq")
PONG = struct.Struct("<IB")  # the length of the ping received and its last byte
METRICS = {
    "rtt_p50_us": "rtt p50 (us)",
    "rtt_p90_us": "rtt p90 (us)",
    "pinger_cpu_us_per_round_trip": "CPU pinger (us)",
    "echo_cpu_us_per_round_trip": "CPU echo (us)",
}
RATIOS = ("shm/bytes", "bytes/no-shm", "shm/no-shm")


@dataclass(frozen=True)
class ShmBenchConfig:
    sizes_bytes: tuple[int, ...] = (8_500, 65_000, 513_000)
    """ping payloads: overtake's Steps of 1, 8 and 64 arenas"""
    round_trips: int = 500
    """timed round trips per round"""
    rounds: int = 4
    """timed rounds per mode and size, alternating"""
    warmup_round_trips: int = 100
    pool_bytes: int = 16 * 2**20
    """the ShmProvider's pool"""
    timeout_s: float = 30.0
    """longest wait for a connection or for one reply"""
    run_timeout_s: float = 300.0
    """longest wait for the pinger's report"""
    json: Path | None = None


def open_link(endpoint: str, listen: bool, shm: bool, timeout_s: float) -> zenoh.Session:
    return open_session(
        TransportConfig(
            mode="peer" if listen else "client",
            listen=(endpoint,) if listen else (),
            connect=() if listen else (endpoint,),
            connect_timeout_s=timeout_s,
            extra_json5=(("transport/shared_memory/enabled", json.dumps(shm)),),
        )
    )


def declare_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    return session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA_HIGH
    )


def echo_main(endpoints: list[str]) -> None:
    """Answer every ping (``endpoints``: without, with SHM) until SIGTERM or stdin closes."""
    shm_received = 0
    keep: list[Any] = []
    for endpoint, shm in zip(endpoints, (False, True), strict=True):
        session = open_link(endpoint, True, shm, 30.0)
        pub = declare_publisher(session, "bench/pong")

        def on_ping(sample: zenoh.Sample, pub: zenoh.Publisher = pub) -> None:
            nonlocal shm_received
            payload = sample.payload
            shm_received += payload.as_shm() is not None
            data = payload.to_bytes()
            if data == CPU_QUERY:
                pub.put(CPU_REPLY.pack(time.process_time(), shm_received))
            else:
                pub.put(PONG.pack(len(data), data[-1]))

        keep += [session, session.declare_subscriber("bench/ping", on_ping)]
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    sys.stdin.read()  # returns when the parent closes our stdin or dies
    os._exit(0)  # Zenoh's threads may be in a callback: leave without joining them


def ping_main(endpoints: list[str], config: ShmBenchConfig) -> None:
    """Run every round against the echo; print the results as JSON on stdout."""
    replies: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    sessions, subs, pubs = [], [], []
    for endpoint, shm in zip(endpoints, (False, True), strict=True):
        session = open_link(endpoint, False, shm, config.timeout_s)
        sessions.append(session)
        subs.append(
            session.declare_subscriber("bench/pong", lambda s: replies.put(s.payload.to_bytes()))
        )
        pubs.append(declare_publisher(session, "bench/ping"))
        wait_matching(pubs[-1], config.timeout_s, f"the echo's pings on {endpoint}")
    provider = ShmProvider.default_backend(config.pool_bytes)
    policy = GarbageCollect()  # reclaim the chunks the echo has let go of when the pool is full

    def reply() -> bytes:
        try:
            return replies.get(timeout=config.timeout_s)
        except queue.Empty:
            raise TimeoutError(f"no pong within {config.timeout_s:g} s") from None

    def echo_state() -> tuple[float, int]:
        pubs[1].put(CPU_QUERY)
        cpu_s, shm_received = CPU_REPLY.unpack(reply())
        return cpu_s, shm_received

    def run(mode: str, payload: bytes, count: int) -> dict[str, Any]:
        size, clock, pub = len(payload), time.perf_counter, pubs[mode != "no-shm"]
        expected = PONG.pack(size, payload[-1])
        times_s = np.empty(count)
        echo_cpu0_s, shm0 = echo_state()
        cpu0_s = time.process_time()
        for i in range(count):
            start = clock()
            if mode == "shm":
                buffer = provider.alloc(size, policy)
                buffer[0:size] = payload
                pub.put(buffer)
            else:
                pub.put(payload)
            if reply() != expected:
                raise RuntimeError(f"the echo did not receive the {size}-byte ping intact")
            times_s[i] = clock() - start
        cpu1_s = time.process_time()
        echo_cpu1_s, shm1 = echo_state()
        return {
            "rtt_us": (times_s * 1e6).tolist(),
            "pinger_cpu_s": cpu1_s - cpu0_s,
            "echo_cpu_s": echo_cpu1_s - echo_cpu0_s,
            "shm_received": shm1 - shm0,
        }

    results: dict[str, dict[str, list[Any]]] = {}
    rng = np.random.default_rng(0)
    for size in config.sizes_bytes:
        payload = rng.integers(0, 256, size, dtype=np.uint8).tobytes()
        for mode in MODES:
            run(mode, payload, config.warmup_round_trips)
        results[str(size)] = {mode: [] for mode in MODES}
        for _ in range(config.rounds):
            for mode in MODES:
                results[str(size)][mode].append(run(mode, payload, config.round_trips))
    for session in sessions:
        session.close()
    print(json.dumps(results))


def summarise(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    rtt_us = np.concatenate([r["rtt_us"] for r in rounds])
    per_trip = 1e6 / rtt_us.size
    return {
        "rtt_p50_us": float(np.percentile(rtt_us, 50)),
        "rtt_p90_us": float(np.percentile(rtt_us, 90)),
        "round_p50s_us": [round(float(np.median(r["rtt_us"])), 1) for r in rounds],
        "pinger_cpu_us_per_round_trip": sum(r["pinger_cpu_s"] for r in rounds) * per_trip,
        "echo_cpu_us_per_round_trip": sum(r["echo_cpu_s"] for r in rounds) * per_trip,
        "round_trips": int(rtt_us.size),
        "received_as_shm": sum(r["shm_received"] for r in rounds),
    }


def print_table(config: ShmBenchConfig, sizes: dict[str, dict[str, Any]]) -> None:
    print(
        f"ping-pong on 127.0.0.1, {config.rounds} rounds x {config.round_trips} round trips "
        "per mode and size, alternating; CPU time per round trip"
    )
    print(f"{'size (B)':>9}  {'metric':<16}" + "".join(f"{n:>13}" for n in MODES + RATIOS))
    for size, modes in sizes.items():
        for key, label in METRICS.items():
            cells = [f"{modes[m][key]:>13.1f}" for m in MODES]
            cells += [f"{modes['ratios'][n][key]:>13.2f}" for n in RATIOS]
            print(f"{size:>9}  {label:<16}" + "".join(cells))
        seen = [f"{m} {modes[m]['received_as_shm']}/{modes[m]['round_trips']}" for m in MODES]
        print(f"{'':>9}  received as SHM: {', '.join(seen)}")


def child(role: str, *args: str, stdout: int | None = None) -> subprocess.Popen[bytes]:
    command = [sys.executable, "-m", "bench.speed.bench_shm", role, *args]
    return subprocess.Popen(command, stdin=subprocess.PIPE, stdout=stdout, cwd=ROOT)


def main(config: ShmBenchConfig) -> dict[str, Any]:
    endpoints = json.dumps([f"tcp/127.0.0.1:{free_port()}" for _ in range(2)])
    # The echo leaves with os._exit (Zenoh's threads may be in a callback): its pools stay.
    with zenoh_pools_removed():
        procs = [child("echo", endpoints)]
        try:
            arguments = json.dumps({k: v for k, v in asdict(config).items() if k != "json"})
            procs.append(child("ping", endpoints, arguments, stdout=subprocess.PIPE))
            out, _ = procs[1].communicate(timeout=config.run_timeout_s)
            if procs[1].returncode != 0:
                raise RuntimeError(f"the pinger failed (exit status {procs[1].returncode})")
            raw = json.loads(out)
        finally:
            for proc in procs:
                stop_process(proc)
    sizes = {size: {m: summarise(r) for m, r in modes.items()} for size, modes in raw.items()}
    for modes in sizes.values():
        modes["ratios"] = {
            n: {k: modes[n.split("/")[0]][k] / modes[n.split("/")[1]][k] for k in METRICS}
            for n in RATIOS
        }
    print_table(config, sizes)
    report = {
        "config": {k: str(v) for k, v in vars(config).items()},
        "machine": machine_description(),
        "zenoh": metadata.version("eclipse-zenoh"),
        "sizes": sizes,
    }
    write_report(config.json, report)
    return report


def cli() -> None:
    role = sys.argv[1] if len(sys.argv) > 1 else ""
    if role == "echo":  # the child processes, started by main
        echo_main(json.loads(sys.argv[2]))
    elif role == "ping":
        fields = json.loads(sys.argv[3])
        fields["sizes_bytes"] = tuple(fields["sizes_bytes"])
        ping_main(json.loads(sys.argv[2]), ShmBenchConfig(**fields))
    else:
        main(tyro.cli(ShmBenchConfig, description=__doc__))


if __name__ == "__main__":
    cli()
