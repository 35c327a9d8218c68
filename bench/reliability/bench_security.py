"""What security costs per step: one trainer stepping remote arenas through a router, with the
link plain, usrpwd, usrpwd with trainers isolated (Zenoh access control), TLS and mutual TLS.

Every mode runs the same topology on 127.0.0.1 (free ports): an ``overtake-router``
subprocess with that mode's options, an ``overtake-server`` subprocess that listens nowhere and
joins the router (docs/remote-hosts.md's recipe), and this process as the trainer, stepping
``--arenas`` arenas of ``--preset`` with seeded random actions. The modes are measured in
rounds (each round runs every mode for ``--seconds`` in a rotating order, each on a fresh
router and server), so drifts of the machine hit them alike. Reported per mode: step latency
p50 / p99 and steps per second, and their ratio to the plain link's in the same run.
Certificates come from ``scripts/make-certs.sh``.

    .venv/bin/python -m bench.reliability.bench_security [--seconds 20] [--rounds 3] [--arenas 1]
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from bench.harness import REMOTE_ENV_ID, free_port, make_env, random_action, stop_process

ROOT = Path(__file__).resolve().parents[2]
MODES = ("plain", "usrpwd", "usrpwd+isolation", "tls", "mutual tls")


@dataclass(frozen=True)
class SecurityBenchConfig:
    seconds: float = 20.0
    """stepping time per mode and round"""
    rounds: int = 3
    arenas: int = 1
    preset: str = "min2018"
    json: Path | None = None


def mode_options(mode: str, where: Path) -> tuple[list[str], list[str], Any, str]:
    """(router options, server options, the trainer's SecurityConfig, scheme) for ``mode``."""
    from overtake.ipc.transport import SecurityConfig

    certs = where / "certs"
    ca, router_cert = (
        str(certs / "ca.pem"),
        [
            *("--tls-certificate", str(certs / "router.pem")),
            *("--tls-private-key", str(certs / "router.key")),
        ],
    )
    if mode == "plain":
        return [], [], SecurityConfig(), "tcp"
    if mode.startswith("usrpwd"):
        server = ["--user", "simserver", "--password-file", str(where / "simserver.pw")]
        router = ["--credentials-file", str(where / "credentials.txt")]
        if mode == "usrpwd+isolation":
            router += ["--isolate-trainers", "--server-users", "simserver"]
        trainer = SecurityConfig(user="alice", password_file=where / "alice.pw")
        return router, server, trainer, "tcp"
    if mode == "tls":
        return router_cert, ["--tls-root-ca", ca], SecurityConfig(tls_root_ca=Path(ca)), "tls"
    if mode == "mutual tls":
        client = [
            *("--tls-mtls", "--tls-root-ca", ca),
            *("--tls-certificate", str(certs / "client.pem")),
            *("--tls-private-key", str(certs / "client.key")),
        ]
        trainer = SecurityConfig(
            tls_root_ca=Path(ca),
            tls_mtls=True,
            tls_certificate=certs / "client.pem",
            tls_private_key=certs / "client.key",
        )
        return [*router_cert, "--tls-mtls", "--tls-root-ca", ca], client, trainer, "tls"
    raise ValueError(f"unknown mode {mode!r}; expected one of {MODES}")


def measure(mode: str, where: Path, config: SecurityBenchConfig, seed: int) -> dict[str, Any]:
    from overtake.client.wire.remote import RemoteConfig

    router_opts, server_opts, security, scheme = mode_options(mode, where)
    endpoint = f"{scheme}/127.0.0.1:{free_port()}"
    procs = []
    try:
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "overtake.server.router", "--listen", endpoint,
                 "--log-level", "warning", *router_opts],
                stdout=subprocess.DEVNULL,
            )
        )  # fmt: skip
        procs.append(
            subprocess.Popen(
                [sys.executable, "-m", "overtake.server", "--listen", "--connect", endpoint,
                 "--name", "bench-sec", "--log-level", "warning", *server_opts],
                stdout=subprocess.DEVNULL,
            )
        )  # fmt: skip
        remote = RemoteConfig(connect=(endpoint,), connect_timeout_s=30.0, security=security)
        env = make_env(REMOTE_ENV_ID, config.arenas, preset=config.preset, remote=remote)
        try:
            rng = np.random.default_rng(seed)
            env.reset(seed=seed)
            for _ in range(50):  # warm-up
                env.step(random_action(rng, config.arenas))
            times: list[float] = []
            started = time.perf_counter()
            while time.perf_counter() - started < config.seconds:
                actions = random_action(rng, config.arenas)
                t0 = time.perf_counter()
                _, _, terminated, truncated, _ = env.step(actions)
                times.append(time.perf_counter() - t0)
                if config.arenas == 1 and (terminated or truncated):
                    env.reset()
            elapsed = time.perf_counter() - started
        finally:
            env.close()
    finally:
        for proc in reversed(procs):
            stop_process(proc)
    ms = np.asarray(times) * 1e3
    return {
        "steps_per_s": len(times) / elapsed,
        "p50_ms": float(np.percentile(ms, 50)),
        "p99_ms": float(np.percentile(ms, 99)),
    }


def main(config: SecurityBenchConfig) -> dict[str, Any]:
    print(
        f"security cost: {config.arenas} arena(s) of {config.preset} through a router, "
        f"{config.rounds} round(s) x {config.seconds:g} s per mode "
        f"({platform.machine()}, {os.cpu_count()} cores)",
        flush=True,
    )
    results: dict[str, list[dict[str, Any]]] = {mode: [] for mode in MODES}
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(tmp)
        made = subprocess.run(
            ["bash", str(ROOT / "scripts" / "make-certs.sh"), str(where / "certs")],
            capture_output=True,
            text=True,
        )
        if made.returncode != 0:
            raise RuntimeError(f"scripts/make-certs.sh failed: {made.stderr}")
        (where / "credentials.txt").write_text("simserver:s3rver\nalice:al1ce\n")
        (where / "simserver.pw").write_text("s3rver\n")
        (where / "alice.pw").write_text("al1ce\n")
        for round_ in range(config.rounds):
            order = MODES[round_ % len(MODES) :] + MODES[: round_ % len(MODES)]
            for mode in order:
                result = measure(mode, where, config, seed=round_)
                results[mode].append(result)
                print(
                    f"round {round_ + 1} {mode}: {result['steps_per_s']:.1f} steps/s, "
                    f"p50 {result['p50_ms']:.3f} ms, p99 {result['p99_ms']:.3f} ms",
                    flush=True,
                )
    summary = {}
    for mode in MODES:
        runs = results[mode]
        summary[mode] = {
            key: float(np.median([r[key] for r in runs]))
            for key in ("steps_per_s", "p50_ms", "p99_ms")
        }
    plain = summary["plain"]
    print("| link | steps/s | p50 ms | p99 ms | steps/s / plain | p50 / plain |")
    print("|---|---:|---:|---:|---:|---:|")
    for mode, s in summary.items():
        print(
            f"| {mode} | {s['steps_per_s']:.1f} | {s['p50_ms']:.3f} | {s['p99_ms']:.3f} | "
            f"{s['steps_per_s'] / plain['steps_per_s']:.3f} | {s['p50_ms'] / plain['p50_ms']:.3f} |"
        )
    out = {"config": {**config.__dict__, "json": None}, "rounds": results, "median": summary}
    if config.json is not None:
        config.json.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main(tyro.cli(SecurityBenchConfig))
