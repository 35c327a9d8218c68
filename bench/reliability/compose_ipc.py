"""Trainer containers beside the server's container: can they take the shared-memory channel,
and what does it give there? (issue 47; docs/compose.md, "Trainers in containers beside the
server")

Two parts, on a running Docker engine, with the images ``bench/reliability/compose_e2e.py``
builds (the stack part builds them through the compose file, with the cache and the same
offline inputs; ``--parts measure`` alone needs them built already):

1. **The stack** (``stack``). The real ``docker-compose.yml`` under its own project name, with
   compose_e2e's router substitution and the two lines docs/compose.md tells a user to add:
   ``ipc: shareable`` on the server, ``ipc: "service:server"`` on trainer-ddqn. Checks, each
   with a failure that says what it saw: the three trainers step on the one server;
   trainer-ddqn's overtake-train maps the server's segment (its ``/proc/PID/maps`` names
   ``/dev/shm/overtake-...``); trainer-dqn and trainer-dueling, each in an IPC namespace of
   its own, map none and say why in one info line (``... rounds over Zenoh``); no trainer
   logs a warning, an error or a traceback.
2. **The measurement** (``measure``). A server container (``--ipc shareable``, listening on a
   Docker network of its own) and a stepper container of the trainer image that shares its
   IPC namespace (``--ipc container:SERVER``) and runs this file's ``stepper`` (this folder
   mounted read-only): for 1 and 64 arenas of min2018, in-process, remote through the segment
   and remote over Zenoh, in alternating rounds, each stepped with seeded random actions
   (bench_remote's ``Driver``); agent-steps per second, the step's median, and the ratios to
   in-process of the same run; which way ``auto`` takes. Then a second stepper in an IPC
   namespace of its own with the default transport: it must step over Zenoh, say so in one
   info line and log no warning.

It ends by removing its containers, network and volumes (not the images). The figures go to
``--run-dir``/summary.json; a busy machine makes them worthless, so pause other work first.

    .venv/bin/python -m bench.reliability.compose_ipc [--parts stack measure] \\
        [--run-dir runs/compose-ipc]
"""

from __future__ import annotations

import json
import logging
import shutil
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

from bench.reliability.compose_e2e import (
    ALGOS,
    ROOT,
    ROUTER_OVERRIDE,
    WHEEL_DIR,
    ComposeE2EConfig,
    E2EFailure,
    check_status,
    engine_version,
    make_stack,
    place_torch_wheel,
    resolve_base_image,
    run,
    wait_for,
)

SHARED_TRAINER = "trainer-ddqn"
# docs/compose.md's two lines, after compose_e2e's router substitution.
IPC_OVERRIDE = (
    ROUTER_OVERRIDE
    + f"""\
  server:
    ipc: shareable
  {SHARED_TRAINER}:
    ipc: "service:server"
"""
)
# The client's one line where auto falls back (client/wire/shm_channel.py).
FALLBACK_LINE = "rounds over Zenoh"
SEGMENT_MARK = "/dev/shm/overtake-"
BENCH_MOUNT = "/opt/overtake-bench"
STEPPER_SERVER = "bench"
Part = Literal["stack", "measure"]


@dataclass(frozen=True)
class ComposeIpcConfig:
    parts: tuple[Part, ...] = ("stack", "measure")
    """which parts to run, in this order"""
    run_dir: Path = Path("runs/compose-ipc")
    """summary.json and the containers' logs (emptied first)"""
    project: str = "overtake-ipc"
    """the compose project's name and the prefix of the measurement's containers and network"""
    image_tag: str = "e2e"
    """OVERTAKE_IMAGE_TAG of the images (compose_e2e's, so its build cache serves)"""
    base_image: str = ""
    """the Dockerfile's BASE_IMAGE; empty: as compose_e2e finds or makes one"""
    arenas: tuple[int, ...] = (1, 64)
    """arena counts the stepper measures"""
    steps: tuple[int, ...] = (3000, 600)
    """timed steps of each kind for each arena count"""
    rounds: int = 4
    """the timed steps are split into this many rounds, their order rotating"""
    warmup_steps: int = 30
    train_steps: int = 600
    """each stack trainer's --total-steps (the stack part only checks that they step)"""
    wait_s: float = 600.0
    """the longest any one wait may take (health, stepping)"""

    def __post_init__(self) -> None:
        if len(self.arenas) != len(self.steps):
            raise ValueError(f"one step count per arena count: {self.arenas} vs {self.steps}")
        if min(self.steps, default=1) < self.rounds or self.rounds < 1:
            raise ValueError(f"steps {self.steps} must be at least rounds {self.rounds} >= 1")


@dataclass(frozen=True)
class StepperConfig:
    """The stepper, run inside a container of the trainer image (the host part starts it)."""

    endpoint: str
    """the server's Zenoh endpoint, e.g. tcp/overtake-ipc-server:7447"""
    shared: bool = False
    """the container shares the server's IPC namespace: measure the segment too, and expect
    auto to take it"""
    arenas: tuple[int, ...] = (1, 64)
    steps: tuple[int, ...] = (3000, 600)
    rounds: int = 4
    warmup_steps: int = 30
    seed: int = 0


def say(message: str) -> None:
    print(f"compose-ipc: {message}", file=sys.stderr, flush=True)


# --- inside the stepper container -------------------------------------------------------------


class _Collect(logging.Handler):
    """Keeps every record at INFO and above of the overtake loggers."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def stepper_main(config: StepperConfig) -> dict[str, Any]:
    """For each arena count: in-process, remote through the segment (where shared) and over
    Zenoh, stepped in rotating rounds; the way auto takes. Returns the figures and what the
    client logged."""
    from bench.harness import REMOTE_ENV_ID, latency_summary, make_env
    from bench.speed.bench_remote import ENV_ID, PRESET, Driver, transport_auto_picks
    from overtake.client.wire.remote import RemoteConfig

    collect = _Collect()
    logger = logging.getLogger("overtake")
    logger.addHandler(collect)
    logger.setLevel(logging.INFO)
    results = []
    for arenas, total in zip(config.arenas, config.steps):
        vector = arenas > 1
        drivers: dict[str, Any] = {}
        try:
            drivers["in_process"] = Driver(
                make_env(ENV_ID, arenas, preset=PRESET), arenas, config.seed, vector
            )
            for transport in ("shm", "zenoh") if config.shared else ("zenoh",):
                settings = RemoteConfig(connect=(config.endpoint,), transport=transport)
                env = make_env(REMOTE_ENV_ID, arenas, preset=PRESET, remote=settings)
                drivers[transport] = Driver(env, arenas, config.seed, vector)
            auto_picks = transport_auto_picks(arenas, config.endpoint)
            for driver in drivers.values():
                driver.drive(config.warmup_steps, timed=False)
            kinds = list(drivers)
            for index in range(config.rounds):
                count = total // config.rounds + (1 if index < total % config.rounds else 0)
                for kind in kinds[index % len(kinds) :] + kinds[: index % len(kinds)]:
                    drivers[kind].drive(count)
            base = drivers["in_process"]
            row: dict[str, Any] = {"arenas": arenas, "auto_picks": auto_picks}
            for kind, driver in drivers.items():
                rate = driver.steps * arenas / driver.wall_seconds
                row[kind] = {
                    "agent_steps_per_second": round(rate, 1),
                    "step_p50_ms": round(latency_summary(driver.step_times)["p50_ms"], 4),
                    "ratio": round(rate / (base.steps * arenas / base.wall_seconds), 3),
                    "same_episodes": (
                        driver.episodes_ended == base.episodes_ended
                        and driver.reward_sum == base.reward_sum
                    ),
                }
            results.append(row)
        finally:
            for driver in drivers.values():
                driver.env.close()
    logger.removeHandler(collect)
    return {
        "shared_ipc": config.shared,
        "results": results,
        "fallback_lines": [
            r.getMessage() for r in collect.records if FALLBACK_LINE in r.getMessage()
        ],
        "warnings": [
            f"{r.levelname} {r.name}: {r.getMessage()}"
            for r in collect.records
            if r.levelno >= logging.WARNING
        ],
    }


# --- on the host ------------------------------------------------------------------------------


def segment_maps(container: str) -> int:
    """How many mappings of an overtake segment the container's processes hold."""
    done = run(
        ["docker", "exec", container, "sh", "-c", "cat /proc/[0-9]*/maps 2>/dev/null"],
        check=False,
    )
    return sum(1 for line in done.stdout.splitlines() if SEGMENT_MARK in line)


def check_stack(
    config: ComposeIpcConfig, base_image: str, wheel_dir: Path | None
) -> dict[str, Any]:
    """Part 1: docs/compose.md's two lines on the real compose file."""
    e2e = ComposeE2EConfig(
        run_dir=config.run_dir / "stack",
        project=config.project,
        image_tag=config.image_tag,
        train_steps=config.train_steps,
        checkpoint_every=config.train_steps,
        wait_s=config.wait_s,
    )
    stack = make_stack(e2e, base_image, wheel_dir, IPC_OVERRIDE)
    figures: dict[str, Any] = {}
    stack.compose("down", "-v", check=False)
    try:
        say("building the images through the compose file (with the cache)")
        start = time.monotonic()
        stack.compose("build", timeout_s=3600)
        figures["build_s"] = round(time.monotonic() - start, 1)
        say("docker compose up -d, trainer-ddqn in the server's IPC namespace")
        started = time.monotonic()
        stack.compose("up", "-d")
        check_status(stack, figures, started)
        figures["segment_maps"] = maps = {
            f"trainer-{algo}": segment_maps(stack.container(f"trainer-{algo}")) for algo in ALGOS
        }
        logs = {f"trainer-{a}": _logs(stack.container(f"trainer-{a}")) for a in ALGOS}
        (config.run_dir / "stack.log").write_text(
            "".join(f"=== {name}\n{text}\n" for name, text in logs.items())
        )
        problems = []
        for service, count in maps.items():
            shared = service == SHARED_TRAINER
            if shared and count == 0:
                problems.append(f"{service} shares the server's IPC namespace but maps no segment")
            if not shared and count:
                problems.append(f"{service} has an IPC namespace of its own but maps {count}")
            fallbacks = [line for line in logs[service].splitlines() if FALLBACK_LINE in line]
            if not shared and len(fallbacks) != 1:
                problems.append(f"{service}: expected one '{FALLBACK_LINE}' line, got {fallbacks}")
            if shared and fallbacks:
                problems.append(f"{service} fell back: {fallbacks}")
            bad = [
                line
                for line in logs[service].splitlines()
                if any(word in line for word in (" WARNING ", " ERROR ", "Traceback"))
            ]
            if bad:
                problems.append(f"{service} logged {bad[:3]}")
        if problems:
            raise E2EFailure("; ".join(problems))
        figures["result"] = "passed"
        say(f"stack: segments mapped {maps}; the other two fell back with one info line each")
    finally:
        stack.compose("down", "-v", "-t", "20", check=False)
    return figures


def _logs(container: str) -> str:
    done = run(["docker", "logs", container], check=False)
    return done.stdout + done.stderr


def _stepper(config: ComposeIpcConfig, network: str, server: str, shared: bool) -> dict[str, Any]:
    ipc = f"container:{server}" if shared else "private"
    arenas, steps = (config.arenas, config.steps) if shared else ((1,), (config.warmup_steps,))
    command = [
        "docker", "run", "--rm", "--init", "--network", network, "--ipc", ipc,
        "-e", "OMP_NUM_THREADS=1", "-e", "OPENBLAS_NUM_THREADS=1", "-e", "MKL_NUM_THREADS=1",
        "-e", f"PYTHONPATH={BENCH_MOUNT}",
        "-v", f"{ROOT / 'bench'}:{BENCH_MOUNT}/bench:ro",
        f"overtake-trainer:{config.image_tag}",
        "python", "-m", "bench.reliability.compose_ipc", "stepper",
        "--endpoint", f"tcp/{server}:7447",
        "--shared" if shared else "--no-shared",
        "--arenas", *map(str, arenas), "--steps", *map(str, steps),
        "--rounds", str(min(config.rounds, min(steps))),
        "--warmup-steps", str(config.warmup_steps),
    ]  # fmt: skip
    done = run(command, timeout_s=3600)
    name = "stepper-shared" if shared else "stepper-private"
    (config.run_dir / f"{name}.log").write_text(done.stderr)
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    if not lines:
        raise E2EFailure(f"{name} printed no figures: {done.stderr[-2000:]}")
    return dict(json.loads(lines[-1]))


def measure(config: ComposeIpcConfig) -> dict[str, Any]:
    """Part 2: a server container and stepper containers, with and without its IPC namespace."""
    network, server = f"{config.project}-net", f"{config.project}-server"
    run(["docker", "rm", "-f", server], check=False)
    run(["docker", "network", "rm", network], check=False)
    run(["docker", "network", "create", network])
    try:
        run([
            "docker", "run", "-d", "--init", "--name", server, "--network", network,
            "--ipc", "shareable",
            "-e", "OMP_NUM_THREADS=1", "-e", "OPENBLAS_NUM_THREADS=1", "-e", "MKL_NUM_THREADS=1",
            f"overtake-server:{config.image_tag}",
            "overtake-server", "--listen", "tcp/0.0.0.0:7447", "--name", STEPPER_SERVER,
        ])  # fmt: skip
        status = ["overtake-status", "--connect", "tcp/127.0.0.1:7447", "--timeout-s", "5"]
        wait_for(
            lambda: run(["docker", "exec", server, *status], check=False).returncode == 0,
            config.wait_s,
            "the server container answering a status request",
        )
        say("stepping from a container in the server's IPC namespace")
        shared = _stepper(config, network, server, shared=True)
        say("stepping from a container with an IPC namespace of its own (transport auto)")
        private = _stepper(config, network, server, shared=False)
        problems = []
        for row in shared["results"]:
            if row["auto_picks"] != "shm":
                problems.append(f"{row['arenas']} arenas: auto took {row['auto_picks']}, not shm")
            if not all(row[k]["same_episodes"] for k in ("shm", "zenoh")):
                problems.append(f"{row['arenas']} arenas: remote episodes differ from in-process")
        if private["results"][0]["auto_picks"] != "zenoh" or len(private["fallback_lines"]) < 1:
            problems.append(f"the private stepper: {private}")
        for figures in (shared, private):
            if figures["warnings"]:
                problems.append(f"warnings logged: {figures['warnings']}")
        (config.run_dir / "server.log").write_text(_logs(server))
        if problems:
            raise E2EFailure("; ".join(problems))
        return {"shared": shared, "private": private}
    finally:
        run(["docker", "rm", "-f", server], check=False)
        run(["docker", "network", "rm", network], check=False)


def print_table(measured: dict[str, Any]) -> None:
    print("| arenas | auto takes | in-process agent-steps/s | shm (ratio) | zenoh (ratio) |")
    print("|---:|---|---:|---:|---:|")
    for row in measured["shared"]["results"]:
        print(
            f"| {row['arenas']} | {row['auto_picks']} "
            f"| {row['in_process']['agent_steps_per_second']:,.0f} "
            f"| {row['shm']['agent_steps_per_second']:,.0f} ({row['shm']['ratio']:.2f}x) "
            f"| {row['zenoh']['agent_steps_per_second']:,.0f} ({row['zenoh']['ratio']:.2f}x) |"
        )


def main(config: ComposeIpcConfig) -> dict[str, Any]:
    figures: dict[str, Any] = {"engine": engine_version()}
    if config.run_dir.exists():
        shutil.rmtree(config.run_dir)
    config.run_dir.mkdir(parents=True)
    e2e = ComposeE2EConfig(base_image=config.base_image, image_tag=config.image_tag)
    base_image, base_from = resolve_base_image(e2e)
    figures["base_image"] = f"{base_image} ({base_from})"
    wheel, placed = place_torch_wheel(e2e)
    try:
        if "stack" in config.parts:
            figures["stack"] = check_stack(config, base_image, WHEEL_DIR if wheel else None)
        if "measure" in config.parts:
            figures["measure"] = measure(config)
            print_table(figures["measure"])
        figures["result"] = "passed"
    except BaseException as error:
        figures["result"] = f"failed: {error}"
        raise
    finally:
        (config.run_dir / "summary.json").write_text(json.dumps(figures, indent=2) + "\n")
        if placed is not None:
            placed.unlink(missing_ok=True)
    return figures


def _interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def cli() -> None:
    if sys.argv[1:2] == ["stepper"]:  # inside the stepper container (started by measure)
        stepper = tyro.cli(StepperConfig, args=sys.argv[2:])
        print(json.dumps(stepper_main(stepper)), flush=True)
        return
    config = tyro.cli(ComposeIpcConfig, description=__doc__.split("\n\n")[0])
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    try:
        main(config)
    except E2EFailure as error:
        say(f"FAILED: {error}")
        sys.exit(1)


if __name__ == "__main__":
    cli()
