"""Benchmark: what stepping overtake through a server costs, against stepping it in-process and
against the bare Zenoh round trip it cannot beat.

What is measured, in one run on 127.0.0.1 (free ports), for 1, 8 and 64 arenas (N):

* in-process: ``gymnasium.make("overtake/Highway-v0")`` (N = 1) and
  ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`` (N = 8, 64), preset
  min2018, as in ``bench/speed/bench_sim.py``;
* remote: an ``overtake.server`` subprocess (``--listen tcp/127.0.0.1:<port> --name bench``) and
  ``overtake/RemoteHighway-v0`` made the same two ways, with ``RemoteConfig(connect=(ep,))``:
  "remote" with its rounds through the shared-memory channel (``transport="shm"``, what a
  trainer on the server's host gets), and the same over Zenoh alone (``transport="zenoh"``,
  what a trainer on another host pays, less the network), both in the same rounds; the report
  names the one the default (``auto``) picks for each N;
* the floor: a bare Zenoh ping-pong between this process and a child process (this script in
  echo mode), with a request exactly as long as the encoded ``Actions`` of N agents and a reply
  exactly as long as the encoded ``Steps`` of N agents (both measured by encoding the remote
  environment's real messages). Both sides use the transport settings overtake uses (client
  connected to a listening peer, no scouting, CongestionControl.BLOCK, priority DATA_HIGH) and
  wait for matching subscribers before the first put. Two receive shapes, used on both
  sides: a callback that puts ``payload.to_bytes()`` on a ``queue.SimpleQueue`` read by
  another thread (what the client and server do; used for the bar), and the default FIFO
  channel read with ``sub.recv()``;
* the bound: the callback ping-pong again, with the echo stepping an in-process environment
  of N arenas (same preset, seeded random actions) before it replies. A server doing nothing
  but the simulation would step this fast; what the remote step takes beyond it is the
  protocol, the validation, the group logic and the client's own work.

Every environment is stepped with uniformly random actions in [0, 5) from a generator seeded
alike, so the in-process and remote environment of one N drive the very same episodes (the
remote environment is bit-for-bit the in-process one); the report says whether their episode
ends and reward sums matched. The single environment is reset inside the timed loop when its
episode ends (in the throughput, not in the step latencies); vector environments autoreset.

After untimed warm-up steps, the timed steps of one N are split into rounds; each round times
a chunk of in-process steps, remote steps and ping-pongs of both shapes (rotating their order),
so slow drifts of this machine hit all of them alike. Step latency is ``time.perf_counter``
around ``step()``; throughput is agent-steps (N x steps) per wall second of the chunks.

Where the time goes: the report also times the codec on the real messages (the client's
``Actions`` build + encode and ``Steps`` decode, the server's ``Actions`` decode and ``Steps``
encode; medians of a tight loop, so with warm caches: inside a step they cost more), and the
CPU time and minor page faults per step of this process (``time.process_time``,
``getrusage``) and of the server (``/proc/<pid>/stat``; CPU in 10 ms ticks). Page faults
matter here: a fresh page costs about a microsecond on this kind of virtual machine, and
whether numpy's large temporaries come back as fresh pages each step depends on the state of
glibc's allocator in each process: so this process keeps freed memory as every overtake command
does (``overtake.cli.allocator``, the server through its door), unless glibc's own variables
are set, which every process here then inherits. It ends with the CPU time the rest of the
machine used meanwhile (``/proc/stat``), a warning sign for figures taken on a shared machine.

The bars: remote overhead per step (remote p50 - in-process p50) at most 2.0x the ping-pong
p50 (callback shape) for 1 arena; remote throughput at least 0.70x in-process for 64 arenas.
Beside the first, the report prints the bound's own overhead in the same units: the bar cannot
be met where even the bound misses it.
PASS/FAIL is printed as information; the exit status is non-zero only on an error.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import queue
import resource
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import tyro

from bench.harness import (
    REMOTE_ENV_ID,
    free_port,
    latency_summary,
    make_env,
    process_usage,
    report_head,
    start_server,
    stop_process,
    write_report,
)
from bench.speed.bench_sim import machine_description, machine_line, pin_threads

ENV_ID = "overtake/Highway-v0"
PRESET = "min2018"
ARENAS = (1, 8, 64)
QUICK_DIVISOR = 10
# arenas -> the least remote/in-process throughput ratio; arenas -> the most overhead/ping-pong.
THROUGHPUT_BARS: dict[int, float] = {64: 0.70}
OVERHEAD_BARS: dict[int, float] = {1: 2.0}
ROOT = Path(__file__).resolve().parents[2]
# Ping-pong keys: <shape>/req from this process to the echo, <shape>/rep back.
PING_SHAPES = ("callback", "channel", "simulated")
PING_ROOT = "overtake-bench/pingpong"
# A request starts with the reply's length and, for the simulated shape, the arenas to step
# (little-endian, HEADER_BYTES each).
HEADER_BYTES = 8
RECEIVE_TIMEOUT_S = 30.0
# A difference in page faults per step beyond which the report warns (about 0.1 ms of faults).
FAULTS_NOTE_PER_STEP = 100


@dataclass(frozen=True)
class BenchConfig:
    """Step counts, seed and threading of one benchmark run."""

    steps: tuple[int, int, int] = (4000, 4000, 1000)
    """Timed steps with 1, 8 and 64 arenas (each of in-process, remote and both ping-pongs)."""
    warmup_steps: int = 30
    """Untimed steps (and ping-pongs) of every environment and size before timing."""
    rounds: int = 4
    """The timed steps of one N are split into this many alternating rounds."""
    codec_repeats: int = 200
    """Timed repeats of each codec operation (the median is reported)."""
    quick: bool = False
    """Divide the timed counts by 10: a smoke run (< 1 min), with noisier figures."""
    seed: int = 0
    """Seed of the environments and of the random actions."""
    blas_threads: int | None = 1
    """Threads of numpy's BLAS/OpenMP pools (set before numpy is imported, inherited by the
    server and echo processes); None leaves the environment as it is."""
    start_timeout_s: float = 60.0
    """How long the server and the echo process may take to answer."""
    json: Path | None = None
    """Also write the results as JSON to this path."""

    def __post_init__(self) -> None:
        if min(self.steps) < 1:
            raise ValueError(f"steps must be at least 1, got {self.steps}")
        for name in ("rounds", "codec_repeats"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.warmup_steps < 0:
            raise ValueError(f"warmup_steps must be at least 0, got {self.warmup_steps}")
        if self.blas_threads is not None and self.blas_threads < 1:
            raise ValueError(f"blas_threads must be at least 1 or None, got {self.blas_threads}")

    def timed_steps(self, arenas: int) -> int:
        count = self.steps[ARENAS.index(arenas)]
        if self.quick:
            count = max(1, count // QUICK_DIVISOR)
        return max(count, self.rounds)

    def repeats(self) -> int:
        return max(5, self.codec_repeats // QUICK_DIVISOR) if self.quick else self.codec_repeats


# --- small helpers ----------------------------------------------------------------------------


def own_minor_faults() -> int:
    """Minor page faults of this process so far (all its threads)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def machine_busy_cpu_seconds() -> float:
    """CPU seconds all processes have used since boot (/proc/stat: all but idle and iowait)."""
    with open("/proc/stat", encoding="ascii") as stat:
        ticks = [int(v) for v in stat.readline().split()[1:]]
    return (sum(ticks[:8]) - ticks[3] - ticks[4]) / os.sysconf("SC_CLK_TCK")


def wait_matching(publisher: Any, timeout_s: float, what: str) -> None:
    """Block until ``publisher`` has a matching subscriber (the notes' rule before a first put)."""
    matched = threading.Event()
    listener = publisher.declare_matching_listener(
        lambda status: matched.set() if status.matching else None
    )
    try:
        if not publisher.matching_status.matching and not matched.wait(timeout_s):
            raise TimeoutError(f"no subscriber matched {what} within {timeout_s:g} s")
    finally:
        listener.undeclare()


# --- the echo process of the ping-pong --------------------------------------------------------


def echo_main(endpoint: str) -> None:
    """Serve ping-pongs on ``endpoint`` until stdin closes (the parent's end) or SIGTERM.

    Listens as a peer, like the server. For each shape, requests on ``<shape>/req`` are
    answered on ``<shape>/rep`` with a reply as long as the request's header says, from a
    thread of its own as the server's loop does; the simulated shape first steps an in-process
    environment of as many arenas as the header says (what a server doing nothing but the
    simulation would cost).
    """
    import zenoh

    from overtake.ipc.transport import TransportConfig, open_session

    zenoh.init_log_from_env_or("error")
    session = open_session(TransportConfig(mode="peer", listen=(endpoint,)))
    replies: dict[int, bytes] = {}

    def reply_for(request: bytes) -> bytes:
        size = int.from_bytes(request[:HEADER_BYTES], "little")
        reply = replies.get(size)
        if reply is None:
            reply = replies[size] = bytes(size)
        return reply

    publishers = {
        shape: session.declare_publisher(
            f"{PING_ROOT}/{shape}/rep",
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.DATA_HIGH,
        )
        for shape in PING_SHAPES
    }
    inboxes: dict[str, queue.SimpleQueue[bytes]] = {}
    keep = []
    for shape in ("callback", "simulated"):
        inbox = inboxes[shape] = queue.SimpleQueue()
        keep.append(
            session.declare_subscriber(
                f"{PING_ROOT}/{shape}/req",
                lambda sample, inbox=inbox: inbox.put(sample.payload.to_bytes()),
            )
        )

    def serve_callback() -> None:
        pub, inbox = publishers["callback"], inboxes["callback"]
        while True:
            pub.put(reply_for(inbox.get()))

    def serve_simulated() -> None:
        pub, inbox = publishers["simulated"], inboxes["simulated"]
        simulations: dict[int, Driver] = {}
        while True:
            request = inbox.get()
            arenas = int.from_bytes(request[HEADER_BYTES : 2 * HEADER_BYTES], "little")
            driver = simulations.get(arenas)
            if driver is None:
                driver = simulations[arenas] = Driver(
                    make_env(ENV_ID, arenas, preset=PRESET), arenas, seed=0, vector=arenas > 1
                )
            driver.step_once()
            pub.put(reply_for(request))

    channel = session.declare_subscriber(f"{PING_ROOT}/channel/req")
    keep.append(channel)

    def serve_channel() -> None:
        pub = publishers["channel"]
        while True:
            pub.put(reply_for(channel.recv().payload.to_bytes()))

    for target in (serve_callback, serve_simulated, serve_channel):
        threading.Thread(target=target, daemon=True).start()
    signal.signal(signal.SIGTERM, lambda *_: os._exit(0))
    sys.stdin.read()  # returns when the parent closes our stdin or dies
    os._exit(0)  # the serving threads block in Zenoh; leave without joining them


class PingPong:
    """This process's side of the ping-pong against an echo child process."""

    def __init__(self, endpoint: str, timeout_s: float) -> None:
        import zenoh

        from overtake.ipc.transport import TransportConfig, open_session

        self._zenoh = zenoh
        self.session = open_session(
            TransportConfig(mode="client", connect=(endpoint,), connect_timeout_s=timeout_s)
        )
        self._inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()
        self._reply_cb = [
            self.session.declare_subscriber(
                f"{PING_ROOT}/{shape}/rep",
                lambda sample: self._inbox.put(sample.payload.to_bytes()),
            )
            for shape in ("callback", "simulated")
        ]
        self._reply_ch = self.session.declare_subscriber(f"{PING_ROOT}/channel/rep")
        self._pubs = {
            shape: self.session.declare_publisher(
                f"{PING_ROOT}/{shape}/req",
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.DATA_HIGH,
            )
            for shape in PING_SHAPES
        }
        for shape, pub in self._pubs.items():
            wait_matching(pub, timeout_s, f"the echo's {shape} requests")
        # sub.recv() has no timeout: a watchdog wakes a stuck recv() with an empty sample.
        self._deadline = float("inf")
        self._stop = threading.Event()
        self._watchdog = threading.Thread(target=self._watch, daemon=True)
        self._watchdog.start()

    def _watch(self) -> None:
        while not self._stop.wait(0.5):
            if time.monotonic() > self._deadline:
                self._deadline = float("inf")
                self.session.put(f"{PING_ROOT}/channel/rep", b"")

    def round_trips(
        self, shape: str, request_bytes: int, reply_bytes: int, count: int, arenas: int = 1
    ) -> list[float]:
        """``count`` timed round trips; each must bring back ``reply_bytes`` bytes (the
        simulated shape steps ``arenas`` arenas in the echo first)."""
        if request_bytes < 2 * HEADER_BYTES:
            raise ValueError(f"a request needs at least {2 * HEADER_BYTES} bytes")
        request = (
            reply_bytes.to_bytes(HEADER_BYTES, "little")
            + arenas.to_bytes(HEADER_BYTES, "little")
            + bytes(request_bytes - 2 * HEADER_BYTES)
        )
        pub = self._pubs[shape]
        times: list[float] = []
        clock = time.perf_counter
        if shape != "channel":
            inbox = self._inbox
            for _ in range(count):
                start = clock()
                pub.put(request)
                try:
                    reply = inbox.get(timeout=RECEIVE_TIMEOUT_S)
                except queue.Empty:
                    raise TimeoutError(
                        f"no ping-pong reply within {RECEIVE_TIMEOUT_S:g} s"
                    ) from None
                times.append(clock() - start)
                if len(reply) != reply_bytes:
                    raise RuntimeError(
                        f"ping-pong reply of {len(reply)} bytes, expected {reply_bytes}"
                    )
        else:
            sub = self._reply_ch
            for _ in range(count):
                self._deadline = time.monotonic() + RECEIVE_TIMEOUT_S
                start = clock()
                pub.put(request)
                reply = sub.recv().payload.to_bytes()
                times.append(clock() - start)
                if len(reply) != reply_bytes:
                    raise (
                        TimeoutError(f"no ping-pong reply within {RECEIVE_TIMEOUT_S:g} s")
                        if not reply
                        else RuntimeError(
                            f"ping-pong reply of {len(reply)} bytes, expected {reply_bytes}"
                        )
                    )
            self._deadline = float("inf")
        return times

    def close(self) -> None:
        self._stop.set()
        self._watchdog.join(timeout=2.0)
        for obj in (*self._pubs.values(), *self._reply_cb):
            obj.undeclare()
        # The channel subscriber is closed with the session (nothing blocks in its recv now).
        self.session.close()


# --- the environments ----------------------------------------------------------------------


@dataclass
class Driver:
    """Steps one environment (single or vector) with seeded random actions, chunk by chunk."""

    env: Any
    arenas: int
    seed: int
    vector: bool
    step_times: list[float] = field(default_factory=list)
    wall_seconds: float = 0.0
    cpu_seconds: float = 0.0
    steps: int = 0
    minor_faults: int = 0
    episodes_ended: int = 0
    reward_sum: float = 0.0

    def __post_init__(self) -> None:
        import numpy as np

        self._np = np
        self.rng = np.random.default_rng(self.seed)
        self.env.reset(seed=self.seed)

    def step_once(self) -> None:
        """One untimed step with the next random action (resetting after an episode's end)."""
        if self.vector:
            self.env.step(self.rng.integers(5, size=self.arenas))
        else:
            _, _, terminated, truncated, _ = self.env.step(int(self.rng.integers(5)))
            if terminated or truncated:
                self.env.reset()

    def drive(self, count: int, timed: bool = True) -> None:
        np, env, rng, arenas = self._np, self.env, self.rng, self.arenas
        clock = time.perf_counter
        times: list[float] = []
        ended = 0
        reward_sum = 0.0
        faults, wall, cpu = own_minor_faults(), clock(), time.process_time()
        for _ in range(count):
            if self.vector:
                actions = rng.integers(5, size=arenas)
                start = clock()
                _, reward, terminated, truncated, _ = env.step(actions)
                times.append(clock() - start)
                ended += int(np.count_nonzero(terminated | truncated))
                reward_sum += float(np.sum(reward))
            else:
                action = int(rng.integers(5))
                start = clock()
                _, reward, terminated, truncated, _ = env.step(action)
                times.append(clock() - start)
                reward_sum += float(reward)
                if terminated or truncated:
                    ended += 1
                    env.reset()
        if timed:
            self.wall_seconds += clock() - wall
            self.cpu_seconds += time.process_time() - cpu
            self.minor_faults += own_minor_faults() - faults
            self.step_times.extend(times)
            self.steps += count
            self.episodes_ended += ended
            self.reward_sum += reward_sum

    def result(self) -> dict[str, Any]:
        return {
            "steps": self.steps,
            "agent_steps": self.steps * self.arenas,
            "wall_seconds": self.wall_seconds,
            "cpu_seconds": self.cpu_seconds,
            "agent_steps_per_second": self.steps * self.arenas / self.wall_seconds,
            "cpu_ms_per_step": 1e3 * self.cpu_seconds / self.steps,
            "minor_faults_per_step": self.minor_faults / self.steps,
            "episodes_ended": self.episodes_ended,
            "reward_sum": self.reward_sum,
            "step": latency_summary(self.step_times),
        }


def start_echo(endpoint: str) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "bench.speed.bench_remote", "echo", endpoint],
        stdin=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        cwd=ROOT,
    )


def stop_echo(proc: subprocess.Popen[bytes]) -> None:
    if proc.stdin is not None:
        with contextlib.suppress(OSError):
            proc.stdin.close()  # the echo leaves when its stdin closes
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        stop_process(proc)


def median_us(operation: Callable[[], Any], repeats: int) -> float:
    import numpy as np

    clock = time.perf_counter
    operation()
    times = []
    for _ in range(repeats):
        start = clock()
        operation()
        times.append(clock() - start)
    return float(np.median(times) * 1e6)


def wire_messages(remote_env: Any, arenas: int, seed: int) -> tuple[Any, Any]:
    """An ``Actions`` the remote env would send now, and the last ``Steps`` it received."""
    import numpy as np

    from overtake.protocol.messages import Actions

    group = remote_env.unwrapped.group
    actions = Actions(
        trainer=group.connection.trainer,
        ticket=group.ticket,
        group=group.group_id,
        round=group.round,
        agents=np.asarray(group.agents, dtype=np.int32),
        actions=np.random.default_rng(seed).integers(5, size=arenas),
    )
    return actions, group.last


def codec_times(actions: Any, steps: Any, repeats: int) -> dict[str, float]:
    from overtake.protocol import codec
    from overtake.protocol.messages import Actions, Steps

    actions_bytes, steps_bytes = codec.encode(actions), codec.encode(steps)
    fields_of = {f.name: getattr(actions, f.name) for f in dataclasses.fields(actions)}
    times = {
        "client_actions_build_encode_us": median_us(
            lambda: codec.encode(Actions(**fields_of)), repeats
        ),
        "server_actions_decode_us": median_us(
            lambda: codec.decode(actions_bytes, Actions), repeats
        ),
        "server_steps_encode_us": median_us(lambda: codec.encode(steps), repeats),
        "client_steps_decode_us": median_us(lambda: codec.decode(steps_bytes, Steps), repeats),
    }
    times["total_us"] = sum(times.values())
    return times


def transport_auto_picks(arenas: int, endpoint: str) -> str:
    """The way the default transport (``auto``) takes for N arenas on this host: ``shm`` or
    ``zenoh`` (its figures are that column's)."""
    from overtake.client.wire.remote import RemoteConfig

    env = make_env(REMOTE_ENV_ID, arenas, preset=PRESET, remote=RemoteConfig(connect=(endpoint,)))
    try:
        return env.unwrapped.group.transport
    finally:
        env.close()


def measure_arenas(
    arenas: int, config: BenchConfig, endpoint: str, server_pid: int, ping: PingPong
) -> dict[str, Any]:
    """All figures of one N: in-process, remote, ping-pongs and codec, in alternating rounds."""
    from overtake.client.wire.remote import RemoteConfig
    from overtake.protocol import codec

    vector = arenas > 1
    local = remote = remote_zenoh = None

    def remote_driver(transport: str) -> Driver:
        settings = RemoteConfig(connect=(endpoint,), transport=transport)
        env = make_env(REMOTE_ENV_ID, arenas, preset=PRESET, remote=settings)
        return Driver(env, arenas, config.seed, vector)

    try:
        local = Driver(make_env(ENV_ID, arenas, preset=PRESET), arenas, config.seed, vector)
        # The trainer on the server's host gets its Steps through shared memory (issue 36);
        # the same over Zenoh alone is what a trainer on another host pays (less the network).
        remote, remote_zenoh = remote_driver("shm"), remote_driver("zenoh")
        auto_picks = transport_auto_picks(arenas, endpoint)
        local.drive(config.warmup_steps, timed=False)
        remote.drive(config.warmup_steps, timed=False)
        remote_zenoh.drive(config.warmup_steps, timed=False)
        actions, steps = wire_messages(remote.env, arenas, config.seed)
        request_bytes, reply_bytes = len(codec.encode(actions)), len(codec.encode(steps))
        codec_us = codec_times(actions, steps, config.repeats())
        for shape in PING_SHAPES:
            ping.round_trips(shape, request_bytes, reply_bytes, config.warmup_steps, arenas)

        total = config.timed_steps(arenas)
        chunks = [
            total // config.rounds + (1 if r < total % config.rounds else 0)
            for r in range(config.rounds)
        ]
        ping_times: dict[str, list[float]] = {shape: [] for shape in PING_SHAPES}
        server_cpu, server_faults = 0.0, 0
        kinds = ["local", "remote", "remote_zenoh", *PING_SHAPES]
        for index, count in enumerate(chunks):
            for kind in kinds[index % len(kinds) :] + kinds[: index % len(kinds)]:
                if kind == "local":
                    local.drive(count)
                elif kind == "remote_zenoh":
                    remote_zenoh.drive(count)
                elif kind == "remote":
                    cpu_before, faults_before = process_usage(server_pid)
                    remote.drive(count)
                    cpu_after, faults_after = process_usage(server_pid)
                    server_cpu += cpu_after - cpu_before
                    server_faults += faults_after - faults_before
                else:
                    ping_times[kind].extend(
                        ping.round_trips(kind, request_bytes, reply_bytes, count, arenas)
                    )
        local_result, remote_result = local.result(), remote.result()
        zenoh_result = remote_zenoh.result()
        remote_result["server_cpu_ms_per_step"] = 1e3 * server_cpu / remote.steps
        remote_result["server_minor_faults_per_step"] = server_faults / remote.steps
        same = all(
            local.episodes_ended == other.episodes_ended and local.reward_sum == other.reward_sum
            for other in (remote, remote_zenoh)
        )
    finally:
        for driver in (local, remote, remote_zenoh):
            if driver is not None:
                driver.env.close()

    pings = {shape: latency_summary(times) for shape, times in ping_times.items()}
    overhead_ms = remote_result["step"]["p50_ms"] - local_result["step"]["p50_ms"]
    bound_ms = pings["simulated"]["p50_ms"] - local_result["step"]["p50_ms"]
    return {
        "arenas": arenas,
        "in_process": local_result,
        "remote": remote_result,
        "remote_zenoh": zenoh_result,
        "throughput_ratio_zenoh": (
            zenoh_result["agent_steps_per_second"] / local_result["agent_steps_per_second"]
        ),
        "auto_picks": auto_picks,
        "same_episodes": same,
        "wire": {"actions_bytes": request_bytes, "steps_bytes": reply_bytes},
        "ping_pong": pings,
        "codec": codec_us,
        "overhead_p50_ms": overhead_ms,
        "overhead_over_ping_pong": overhead_ms / pings["callback"]["p50_ms"],
        "unexplained_ms": (overhead_ms - pings["callback"]["p50_ms"] - codec_us["total_us"] / 1e3),
        "overhead_over_ping_pong_channel": overhead_ms / pings["channel"]["p50_ms"],
        # A server doing nothing but the simulation: its overhead over in-process, and what
        # the real server adds to that (protocol, validation, groups, the client's work).
        "bound_overhead_p50_ms": bound_ms,
        "bound_over_ping_pong": bound_ms / pings["callback"]["p50_ms"],
        "beyond_bound_ms": remote_result["step"]["p50_ms"] - pings["simulated"]["p50_ms"],
        "throughput_ratio": (
            remote_result["agent_steps_per_second"] / local_result["agent_steps_per_second"]
        ),
    }


# --- report ---------------------------------------------------------------------------------


def format_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    widths = [max(len(cells[i]) for cells in (header, *rows)) for i in range(len(header))]

    def join(cells: Sequence[str]) -> str:
        return "  ".join(cell.rjust(width) for cell, width in zip(cells, widths))

    return "\n".join([join(header), "  ".join("-" * w for w in widths), *map(join, rows)])


def print_report(results: list[dict[str, Any]]) -> None:
    def ms(value: float) -> str:
        return f"{value:.3f}"

    print("Step latency (ms, p50 / p99) and the remote overhead against the Zenoh floor")
    print(
        format_table(
            (
                "N",
                "in-process",
                "remote",
                "overhead p50",
                "ping-pong cb",
                "ping-pong recv",
                "overhead/ping-pong",
            ),
            [
                (
                    str(r["arenas"]),
                    f"{ms(r['in_process']['step']['p50_ms'])} / "
                    f"{ms(r['in_process']['step']['p99_ms'])}",
                    f"{ms(r['remote']['step']['p50_ms'])} / {ms(r['remote']['step']['p99_ms'])}",
                    ms(r["overhead_p50_ms"]),
                    (
                        f"{ms(r['ping_pong']['callback']['p50_ms'])} / "
                        f"{ms(r['ping_pong']['callback']['p99_ms'])}"
                    ),
                    (
                        f"{ms(r['ping_pong']['channel']['p50_ms'])} / "
                        f"{ms(r['ping_pong']['channel']['p99_ms'])}"
                    ),
                    f"{r['overhead_over_ping_pong']:.2f}x",
                )
                for r in results
            ],
        )
    )
    print()
    print(
        "The bound: a ping-pong whose echo steps the in-process environment before it replies "
        "(a server doing nothing but the simulation); beyond = remote p50 - its p50"
    )
    print(
        format_table(
            (
                "N",
                "simulated ping-pong",
                "its overhead p50",
                "its overhead/ping-pong",
                "remote beyond it ms",
            ),
            [
                (
                    str(r["arenas"]),
                    (
                        f"{ms(r['ping_pong']['simulated']['p50_ms'])} / "
                        f"{ms(r['ping_pong']['simulated']['p99_ms'])}"
                    ),
                    ms(r["bound_overhead_p50_ms"]),
                    f"{r['bound_over_ping_pong']:.2f}x",
                    ms(r["beyond_bound_ms"]),
                )
                for r in results
            ],
        )
    )
    print()
    print("Throughput (agent-steps per wall second), CPU ms and minor page faults per step")
    print(
        format_table(
            (
                "N",
                "in-process/s",
                "remote/s",
                "remote/in-process",
                "over Zenoh/in-process",
                "auto picks",
                "CPU in-proc",
                "CPU client",
                "CPU server",
                "faults in-proc",
                "faults client",
                "faults server",
                "same episodes",
            ),
            [
                (
                    str(r["arenas"]),
                    f"{r['in_process']['agent_steps_per_second']:,.0f}",
                    f"{r['remote']['agent_steps_per_second']:,.0f}",
                    f"{r['throughput_ratio']:.2f}x",
                    f"{r['throughput_ratio_zenoh']:.2f}x",
                    r["auto_picks"],
                    f"{r['in_process']['cpu_ms_per_step']:.3f}",
                    f"{r['remote']['cpu_ms_per_step']:.3f}",
                    f"{r['remote']['server_cpu_ms_per_step']:.3f}",
                    f"{r['in_process']['minor_faults_per_step']:,.0f}",
                    f"{r['remote']['minor_faults_per_step']:,.0f}",
                    f"{r['remote']['server_minor_faults_per_step']:,.0f}",
                    "yes" if r["same_episodes"] else "NO",
                )
                for r in results
            ],
        )
    )
    print()
    print(
        "Wire and codec per step (bytes; median microseconds of each codec call on the real "
        "messages, timed in a loop); rest = overhead p50 - ping-pong p50 - codec total"
    )
    print(
        format_table(
            (
                "N",
                "Actions B",
                "Steps B",
                "client Actions()+encode",
                "server decode Actions",
                "server encode Steps",
                "client decode Steps",
                "codec total",
                "rest ms",
            ),
            [
                (
                    str(r["arenas"]),
                    f"{r['wire']['actions_bytes']:,}",
                    f"{r['wire']['steps_bytes']:,}",
                    f"{r['codec']['client_actions_build_encode_us']:.1f}",
                    f"{r['codec']['server_actions_decode_us']:.1f}",
                    f"{r['codec']['server_steps_encode_us']:.1f}",
                    f"{r['codec']['client_steps_decode_us']:.1f}",
                    f"{r['codec']['total_us']:.1f}",
                    f"{r['unexplained_ms']:.3f}",
                )
                for r in results
            ],
        )
    )


def _bar(
    arenas: int, figure: str, sense: str, bar: float, value: float, **more: float
) -> dict[str, Any]:
    """One bar of the report: ``figure`` at ``arenas`` must be ``sense`` (<= or >=) ``bar``."""
    passed = value <= bar if sense == "<=" else value >= bar
    return {
        "arenas": arenas,
        "figure": figure,
        "bar": f"{sense} {bar}",
        "value": value,
        "passed": passed,
        **more,
    }


def _verdict(bar: dict[str, Any]) -> str:
    return "PASS" if bar["passed"] else "FAIL"


def main(config: BenchConfig) -> dict[str, Any]:
    """Run every measurement, print the report and return it as a JSON-able dict."""
    threads = pin_threads(config.blas_threads)
    machine = machine_description()
    print("overtake remote stepping benchmark")
    print(machine_line(machine))
    print(
        f"overtake {machine['overtake']} (source {machine['overtake_source']}), preset "
        f"{PRESET}; numpy BLAS/OpenMP threads: {threads}"
    )
    allocator = {
        name: value for name, value in sorted(os.environ.items()) if name.startswith("MALLOC_")
    }
    # The in-process side as a trainer's process has it: every overtake command keeps freed
    # memory (overtake.cli.allocator, at the door: the server too), unless the user set
    # glibc's variables, which then hold in every process here.
    # Imported after pin_threads: the overtake.cli package loads numpy.
    from overtake.cli.allocator import keep_freed_memory

    kept = keep_freed_memory()
    print(
        "glibc malloc settings (inherited by the server and echo): "
        + (", ".join(f"{k}={v}" for k, v in allocator.items()) or "defaults")
        + ("; freed memory kept, as every overtake command keeps it" if kept else "")
    )
    if config.quick:
        print(f"quick mode: timed counts divided by {QUICK_DIVISOR}; figures are noisier")

    server_endpoint = f"tcp/127.0.0.1:{free_port()}"
    echo_endpoint = f"tcp/127.0.0.1:{free_port()}"
    print(f"server: {server_endpoint}; ping-pong echo: {echo_endpoint}")
    started = time.perf_counter()
    busy_before, own_before = machine_busy_cpu_seconds(), time.process_time()
    results: list[dict[str, Any]] = []
    echo = start_echo(echo_endpoint)
    ping = None
    server = None
    children_cpu = 0.0
    try:
        ping = PingPong(echo_endpoint, config.start_timeout_s)
        server = start_server(server_endpoint, config.start_timeout_s)
        for arenas in ARENAS:
            results.append(measure_arenas(arenas, config, server_endpoint, server.pid, ping))
            result = results[-1]
            print(
                f"  N={arenas}: {result['remote']['steps']} timed steps each, "
                f"{time.perf_counter() - started:.1f} s so far",
                flush=True,
            )
        children_cpu = process_usage(server.pid)[0] + process_usage(echo.pid)[0]
        busy = machine_busy_cpu_seconds() - busy_before
        own = time.process_time() - own_before + children_cpu
    finally:
        if server is not None:
            server_status = stop_process(server)
            if server_status not in (0, None):
                print(f"note: the server exited with status {server_status}", file=sys.stderr)
        if ping is not None:
            ping.close()
        stop_echo(echo)

    print()
    print_report(results)
    print()
    by_arenas = {r["arenas"]: r for r in results}
    bars = []
    for arenas, bar in OVERHEAD_BARS.items():
        value = by_arenas[arenas]["overhead_over_ping_pong"]
        bound = by_arenas[arenas]["bound_over_ping_pong"]
        bars.append(_bar(arenas, "overhead_over_ping_pong", "<=", bar, value, bound=bound))
        print(
            f"bar: {arenas} arena(s), remote overhead per step <= {bar:g}x the ping-pong p50: "
            f"{value:.2f}x -> {_verdict(bars[-1])} (a server doing nothing but the "
            f"simulation: {bound:.2f}x)"
        )
    for arenas, bar in THROUGHPUT_BARS.items():
        value = by_arenas[arenas]["throughput_ratio"]
        bars.append(_bar(arenas, "throughput_ratio", ">=", bar, value))
        print(
            f"bar: {arenas} arenas, remote throughput >= {bar:g}x in-process: {value:.2f}x "
            f"-> {_verdict(bars[-1])}"
        )
    for r in results:
        local_faults = r["in_process"]["minor_faults_per_step"]
        remote_faults = (
            r["remote"]["minor_faults_per_step"] + r["remote"]["server_minor_faults_per_step"]
        )
        if abs(local_faults - remote_faults) > FAULTS_NOTE_PER_STEP:
            print(
                f"note: with {r['arenas']} arena(s) the in-process steps took "
                f"{local_faults:,.0f} minor page faults each and the remote ones "
                f"{remote_faults:,.0f} (client + server): the comparison is skewed by the "
                "state of glibc's allocator in each process; rerun with e.g. "
                "MALLOC_TRIM_THRESHOLD_=1000000000 MALLOC_MMAP_THRESHOLD_=1000000000 in the "
                "environment to compare without them"
            )
    wall = time.perf_counter() - started
    # Whatever else ran on the machine meanwhile (other processes, the kernel's own work).
    others = max(busy - own, 0.0)
    print(
        f"measured in {wall:.1f} s; CPU used by this benchmark's 3 processes: {own:.1f} s, "
        f"by everything else on the machine: {others:.1f} s "
        f"({100 * others / wall:.0f}% of one core)"
    )

    report = {
        **report_head(config, machine, threads),
        "malloc_environment": allocator,
        "preset": PRESET,
        "env_ids": {"in_process": ENV_ID, "remote": REMOTE_ENV_ID},
        "endpoints": {"server": server_endpoint, "echo": echo_endpoint},
        "results": results,
        "bars": bars,
        "wall_seconds": wall,
        "cpu_seconds": {"benchmark_processes": own, "everything_else": others},
    }
    write_report(config.json, report)
    return report


def cli() -> None:
    if sys.argv[1:2] == ["echo"]:  # the ping-pong's child process (started by main)
        if len(sys.argv) != 3:
            raise SystemExit("usage: python -m bench.speed.bench_remote echo ENDPOINT")
        echo_main(sys.argv[2])
        return
    main(tyro.cli(BenchConfig, description=__doc__))


if __name__ == "__main__":
    cli()
