"""Fault matrix: a router, a server and two learning trainers; one of the three kinds of
process is killed, frozen or cut off the network at a random point, and the bench measures
how the rest comes through.

Each case starts the whole topology afresh in a network namespace of its own making (root
only): the faulted process (the *target*) runs inside the namespace, joined to this host by a
veth pair, and everything else runs on the host. ``overtake-router`` relays; the server
(``overtake.server``, recording to an .rrd) and both ``overtake-train`` processes (DQN on the
LIDAR, checkpointing every ``--checkpoint-every`` steps, recording ``trainer.rrd``) connect to
it. An observer polls the server's status every ``--poll-s`` (through the router, or, when
the router is the target, at the server's own listening endpoint) and keeps each trainer's
round count over time.

Faults (``--faults``), each at a random moment ``--before-s`` after both trainers have written
a checkpoint:

- ``kill``: SIGKILL; the bench starts the same command again at once (a trainer with
  ``--resume-if-found``, a server or router on the same endpoint);
- ``kill-checkpoint`` (trainer only): SIGKILL the moment the trainer's next checkpoint write
  has begun (``checkpoint.pt.tmp`` exists), then the same restart;
- ``stop``: SIGSTOP, ``--hold-s`` later SIGCONT;
- ``cut``: every packet into and out of the namespace dropped (nftables) for ``--hold-s``;
- ``loss``: ``--loss-percent`` of the packets dropped at random, both ways, for ``--hold-s``;
- ``delay``: every packet delayed ``--delay-ms`` each way for ``--hold-s`` (``tc netem``; where
  the kernel has no netem, as on the machine of RELIABILITY.md, the case is skipped with
  that reason);
- ``none``: the baseline (nothing happens).

Figures per case (``summary.json`` in ``--run-dir``, one line each printed):

- ``back_after_s``: for each trainer, from the end of the fault (SIGCONT, the restart, the
  link restored) to its first new round on the server;
- ``status_answered_after_s``: from the end of the fault to the server's first status
  answer (a restarted server's start-up, a router's sessions re-established);
- ``others_max_gap_s``: the longest pause between rounds of the trainers that were not the
  target, around the fault (a killed trainer must not stall the others; meaningful only
  when the target is a trainer);
- ``arenas``: arenas in use after the run settled (2 expected: one per trainer; more is a
  leak) and after the trainers stopped (0 expected);
- ``steps``: for each trainer life that ended by itself, the steps it counted against the
  rounds the server counted for it (from the server's log; a killed server's rounds died
  with it, so those cases have none): ``unmatched`` is 0 when no step was lost or doubled,
  and may be -1 per server loss the trainer lived through (``server_losses``): the round whose
  actions reached the server but whose Steps did not reach the trainer, in the episode that
  the loss ended as truncated;
- ``segments_left``: files the case made that are still in ``/dev/shm`` once everything has
  stopped, whoever named them: overtake's segments (``--transport shm``), Zenoh's (none since
  its shared memory is off, TransportConfig.zenoh_shared_memory) and any other (none expected;
  run the matrix alone, since another program's new files would count too);
- ``checkpoints``: each trainer's checkpoint loads right after a kill (before the restart
  reads it) and at the end;
- ``recordings``: every .rrd passes ``rerun rrd verify --check-footers false`` (the server's
  and the trainers' are written without a footer; a killed writer's file has everything
  flushed before the kill); one that does not is read with ``rerun rrd print`` and repaired on
  a copy with ``rerun rrd migrate``, which must then verify.

    .venv/bin/python -m bench.reliability.faults [--targets trainer server router] [--rounds 1]
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import tyro

from bench.harness import free_port
from bench.reliability.soak import checkpoint_step, rerun_rrd, stop_all, verify_rrd

TARGETS = ("trainer", "server", "router")
FAULTS = ("none", "kill", "kill-checkpoint", "stop", "cut", "loss", "delay")
SERVER_NAME = "faults"
NAMESPACE = f"ovt-faults-{os.getpid()}"
HOST_IP, NS_IP = "10.213.77.1", "10.213.77.2"
Sample = tuple[float, int, dict[str, tuple[int, int]]]
"""An observer's sample: (monotonic time, arenas in use, {trainer: (group, rounds)})."""
LEAVE_LINE = re.compile(
    r"trainer (\S+) left group (\d+) \((.*)\); arenas \S+ freed after (\d+) rounds"
)


@dataclass(frozen=True)
class FaultConfig:
    targets: tuple[str, ...] = TARGETS
    """the kinds of process faulted: trainer, server, router"""
    faults: tuple[str, ...] = FAULTS
    """none, kill, kill-checkpoint (trainer only), stop, cut, loss, delay (where tc netem is)"""
    rounds: int = 1
    """each case this many times (a fresh random moment each time)"""
    hold_s: float = 5.0
    """how long a SIGSTOP, a cut or a loss lasts: longer than the 3 s lease on purpose"""
    loss_percent: int = 20
    delay_ms: int = 200
    before_s: tuple[float, float] = (1.0, 6.0)
    """the fault comes this long (uniform, seconds) after both trainers have a checkpoint"""
    after_s: float = 20.0
    """how long everything runs after the fault ends"""
    checkpoint_every: int = 100
    poll_s: float = 0.05
    seed: int = 0
    transport: Literal["auto", "shm", "zenoh"] = "auto"
    """how the trainers' Steps travel (shm: through shared memory, the trainer in the
    namespace too, since the namespace has the host's /dev/shm)"""
    run_dir: Path = Path("runs/faults")


# --- the namespace ---------------------------------------------------------------------------


def _sh(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(args), check=check, capture_output=True, text=True)


class Namespace:
    """A network namespace joined to the host by a veth pair, and the nftables faults on it."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.host_if, self.ns_if = host_if, ns_if = "ovtfh0", "ovtfn0"
        _sh("ip", "netns", "del", name, check=False)
        _sh("ip", "link", "del", host_if, check=False)
        _sh("ip", "netns", "add", name)
        _sh("ip", "link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        _sh("ip", "link", "set", ns_if, "netns", name)
        _sh("ip", "addr", "add", f"{HOST_IP}/30", "dev", host_if)
        _sh("ip", "link", "set", host_if, "up")
        self.exec("ip", "addr", "add", f"{NS_IP}/30", "dev", ns_if)
        self.exec("ip", "link", "set", ns_if, "up")
        self.exec("ip", "link", "set", "lo", "up")

    def prefix(self) -> list[str]:
        return ["ip", "netns", "exec", self.name]

    def exec(self, *args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
        return _sh(*self.prefix(), *args, check=check)

    def drop(self, percent: int) -> None:
        """Drop ``percent`` of the packets into and out of the namespace (100: a cut). The
        loopback inside stays up: only the link to the host is faulted."""
        rule = "drop" if percent >= 100 else f"numgen random mod 100 < {percent} drop"
        self.exec("nft", "add", "table", "inet", "fault")
        for chain, hook in (("in", "input"), ("out", "output")):
            self.exec(
                "nft", "add", "chain", "inet", "fault", chain,
                f"{{ type filter hook {hook} priority 0; }}",
            )  # fmt: skip
            where = "iif" if chain == "in" else "oif"
            self.exec(
                "nft", "add", "rule", "inet", "fault", chain, where, "!=", "lo", *rule.split()
            )

    def delay(self, ms: int) -> None:
        """Delay every packet by ``ms`` each way (tc netem on both ends of the pair)."""
        _sh("tc", "qdisc", "add", "dev", self.host_if, "root", "netem", "delay", f"{ms}ms")
        self.exec("tc", "qdisc", "add", "dev", self.ns_if, "root", "netem", "delay", f"{ms}ms")

    def heal(self) -> None:
        self.exec("nft", "delete", "table", "inet", "fault", check=False)
        _sh("tc", "qdisc", "del", "dev", self.host_if, "root", check=False)
        self.exec("tc", "qdisc", "del", "dev", self.ns_if, "root", check=False)

    def close(self) -> None:
        _sh("ip", "netns", "del", self.name, check=False)  # takes its end of the pair along


def netem_missing() -> str | None:
    """Why a delay cannot be made here (``tc netem``), or None."""
    if os.geteuid() != 0 or shutil.which("tc") is None:
        return "tc and root are needed"
    probe = f"ovt-probe-{os.getpid()}"
    _sh("ip", "netns", "add", probe)
    try:
        made = _sh(*("ip", "netns", "exec", probe, "tc", "qdisc", "add", "dev", "lo", "root"),
                   *("netem", "delay", "1ms"), check=False)  # fmt: skip
    finally:
        _sh("ip", "netns", "del", probe, check=False)
    if made.returncode != 0:
        return f"tc cannot make a netem qdisc here ({made.stderr.strip()}): the kernel lacks it"
    return None


def link_faults_missing() -> str | None:
    """Why cut and loss cannot run here, or None."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    if shutil.which("nft") is None:
        return "nft (nftables) is not installed: apt-get install nftables"
    return None


# --- processes -------------------------------------------------------------------------------


@dataclass
class Proc:
    """One process of the topology: its command (to start it again) and its lives."""

    name: str
    argv: list[str]
    log_dir: Path
    popen: subprocess.Popen[bytes] | None = None
    lives: list[Path] = field(default_factory=list)

    def start(self) -> None:
        log_path = self.log_dir / f"{self.name}-{len(self.lives)}.log"
        argv = [a.replace("{life}", str(len(self.lives))) for a in self.argv]
        with open(log_path, "wb") as log:
            self.popen = subprocess.Popen(
                argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        self.lives.append(log_path)

    @property
    def pid(self) -> int:
        assert self.popen is not None
        return self.popen.pid

    def signal(self, sig: int) -> None:
        os.kill(self.pid, sig)

    def kill(self) -> None:
        self.signal(signal.SIGKILL)
        assert self.popen is not None
        self.popen.wait()

    def stop(self, timeout_s: float) -> dict[str, Any]:
        """SIGTERM; SIGKILL only past ``timeout_s``: its exit status and whether it was killed."""
        assert self.popen is not None
        return stop_all({self.name: self.popen}, timeout_s)[self.name]


class Observer:
    """Polls the server's status in a thread: (time, arenas used, {trainer: (group, rounds)})."""

    def __init__(self, endpoint: str, poll_s: float) -> None:
        from overtake.client.wire.remote import Connection, RemoteConfig

        self.connection = Connection(
            RemoteConfig(connect=(endpoint,), connect_timeout_s=30.0, request_timeout_s=1.0)
        )
        self.poll_s = poll_s
        self.samples: list[Sample] = []
        self.lock = threading.Lock()
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        from overtake.protocol.messages import StatusReply, StatusRequest

        while not self.done.is_set():
            try:
                status = self.connection.request(SERVER_NAME, StatusRequest(), StatusReply)
            except Exception:  # the server or the router is down: a gap in the samples
                self.done.wait(self.poll_s)
                continue
            sample = (
                time.monotonic(),
                status.arenas_used,
                {g.trainers[0]: (g.group, g.rounds) for g in status.groups if g.trainers},
            )
            with self.lock:
                self.samples.append(sample)
            self.done.wait(self.poll_s)

    def latest(self) -> Sample | None:
        with self.lock:
            return self.samples[-1] if self.samples else None

    def wait(self, condition: Any, timeout_s: float, what: str) -> Sample:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            sample = self.latest()
            if sample is not None and condition(sample):
                return sample
            time.sleep(self.poll_s)
        raise TimeoutError(f"{what} within {timeout_s:g} s (last status: {self.latest()})")

    def close(self) -> None:
        self.done.set()
        self.thread.join(5)
        self.connection.close()


# --- one case --------------------------------------------------------------------------------


def trainer_names(run_dir: Path) -> list[str]:
    """The network names of a trainer's lives (run.json, run-resume-N.json), in order."""
    names = []
    for path in sorted(run_dir.glob("run*.json"), key=lambda p: (len(p.name), p.name)):
        name = json.loads(path.read_text()).get("trainer")
        if name:
            names.append(name)
    return names


def last_json(log_path: Path) -> dict[str, Any] | None:
    """The summary a process printed last (an indented JSON object), if any."""
    text = log_path.read_text(errors="replace")
    start = text.rfind("\n{\n")
    if start < 0:
        return None
    try:
        return json.loads(text[start:])
    except json.JSONDecodeError:
        return None


def leave_rounds(server: Proc) -> dict[str, int]:
    """Rounds per trainer name over the server's lives that said so on leaving."""
    rounds: dict[str, int] = {}
    for log_path in server.lives:
        for match in LEAVE_LINE.finditer(log_path.read_text(errors="replace")):
            rounds[match[1]] = rounds.get(match[1], 0) + int(match[4])
    return rounds


def check_recording(path: Path) -> dict[str, Any]:
    """The server's and the trainers' recordings are written without Rerun's footer
    (overtake.viz.recording, on footers): verified without one."""
    out: dict[str, Any] = {"mib": round(path.stat().st_size / 2**20, 2)}
    verify = verify_rrd(path, footer=False)
    if verify.returncode == 0:
        return {**out, "verified": True}
    printed = rerun_rrd("print", str(path))
    copy = path.with_name(path.stem + ".repaired.rrd")
    shutil.copy(path, copy)
    migrate = rerun_rrd("migrate", str(copy))
    verified_copy = verify_rrd(copy, footer=True)
    for leftover in (copy, copy.with_name(copy.stem + ".backup.rrd")):
        leftover.unlink(missing_ok=True)
    return {
        **out,
        "verified": False,
        "why": verify.stderr.strip().splitlines()[0] if verify.stderr.strip() else "",
        "reads": printed.returncode == 0,
        "chunks": printed.stdout.count("Chunk("),
        "repaired": migrate.returncode == 0 and verified_copy.returncode == 0,
    }


def stepped(now: dict[str, tuple[int, int]], then: dict[str, tuple[int, int]], name: str) -> bool:
    """Has ``name`` stepped between two samples: more rounds in the same group, or a group
    it opened since (a reopened group counts its rounds from 0) with a round played?"""
    if name not in now:
        return False
    group, rounds = now[name]
    old_group, old_rounds = then.get(name, (None, 0))
    return rounds > (old_rounds if group == old_group else 0)


def longest_gap(samples: list[Sample], names: set[str], t0: float, t1: float) -> float:
    """The longest time in [t0, t1] during which none of ``names``' groups stepped."""
    last: dict[str, tuple[int, int]] | None = None
    last_t: float | None = None
    gap = 0.0
    for t, _, groups in samples:
        if t < t0 or t > t1:
            continue
        if last is None or last_t is None:
            last_t, last = t, groups
        elif any(stepped(groups, last, name) for name in names):
            gap = max(gap, t - last_t)
            last_t, last = t, groups
    if last_t is not None:
        gap = max(gap, t1 - last_t)
    return round(gap, 3)


def back_after(samples: list[Sample], names: set[str], t_heal: float) -> float | None:
    """Seconds from ``t_heal`` to the first sample in which one of ``names`` (a trainer's
    lives) has stepped since ``t_heal``."""
    before: dict[str, tuple[int, int]] = {}
    for t, _, groups in samples:
        if t <= t_heal:
            before = groups
    for t, _, groups in samples:
        if t > t_heal and any(stepped(groups, before, name) for name in names):
            return round(t - t_heal, 3)
    return None


def run_case(config: FaultConfig, target: str, fault: str, index: int, rng: random.Random):
    from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, partial_path

    case_dir = config.run_dir / f"{target}-{fault}-{index}"
    case_dir.mkdir(parents=True)
    namespace = Namespace(NAMESPACE)
    python = sys.executable
    bin_dir = Path(python).parent
    in_ns = namespace.prefix()
    router_port, direct_port = free_port(), free_port()
    router_ip = NS_IP if target == "router" else HOST_IP
    router_ep = f"tcp/{router_ip}:{router_port}"
    server_ip = NS_IP if target == "server" else "127.0.0.1"
    direct_ep = f"tcp/{server_ip}:{direct_port}"
    router = Proc(
        "router",
        [*(in_ns if target == "router" else []), str(bin_dir / "overtake-router"),
         "--listen", router_ep],
        case_dir,
    )  # fmt: skip
    server = Proc(
        "server",
        [*(in_ns if target == "server" else []), python, "-m", "overtake.server",
         "--name", SERVER_NAME, "--connect", router_ep, "--listen", direct_ep,
         "--sink", "file", "--rrd", str(case_dir / "server-{life}.rrd")],
        case_dir,
    )  # fmt: skip
    trainers = [
        Proc(
            f"trainer{i}",
            [*(in_ns if target == "trainer" and i == 0 else []), str(bin_dir / "overtake-train"),
             "--connect", router_ep, "--preset", "min2018", "--inputs", "lidar", "--algo", "dqn",
             "--seed", str(i), "--total-steps", "1000000000", "--run-dir",
             str(case_dir / f"trainer{i}"), "--resume-if-found", "--replay-size", "2000",
             "--learning-starts", "200", "--checkpoint-every", str(config.checkpoint_every),
             "--log-every", str(config.checkpoint_every), "--no-progress",
             "--torch-threads", "1", "--transport", config.transport],
            case_dir,
        )
        for i in range(2)
    ]  # fmt: skip
    victim = {"router": router, "server": server, "trainer": trainers[0]}[target]
    from overtake.ipc.shared_memory import shm_dir

    def segments() -> set[str]:
        # Every file, whoever named it (overtake's segments, Zenoh's segments and pools, a
        # library's): what is new after the case is what the case left.
        return {p.name for p in shm_dir().iterdir()}

    segments_before = segments()
    observer = None
    result: dict[str, Any] = {"target": target, "fault": fault}
    try:
        router.start()
        server.start()
        observer = Observer(direct_ep if target == "router" else router_ep, config.poll_s)
        observer.wait(lambda s: True, 60, "the server did not answer")
        for trainer in trainers:
            trainer.start()
        checkpoints = [case_dir / f"trainer{i}" / CHECKPOINT_NAME for i in range(2)]
        observer.wait(
            lambda s: len(s[2]) == 2 and all(c.exists() for c in checkpoints),
            180,
            "both trainers stepping, each with a checkpoint,",
        )
        time.sleep(rng.uniform(*config.before_s))  # the random moment of the fault

        t_fault = time.monotonic()
        partial = partial_path(checkpoints[0])
        if fault == "kill-checkpoint":
            deadline = time.monotonic() + 120
            while not partial.exists() and time.monotonic() < deadline:
                time.sleep(0.0005)
            result["killed_during_write"] = partial.exists()
            t_fault = time.monotonic()
        if fault in ("kill", "kill-checkpoint"):
            victim.kill()
            if victim is trainers[0]:
                result["checkpoint_after_kill"] = checkpoint_step(checkpoints[0])
                result["tmp_left_behind"] = partial.exists()
            victim.start()
        elif fault == "stop":
            victim.signal(signal.SIGSTOP)
            time.sleep(config.hold_s)
            victim.signal(signal.SIGCONT)
        elif fault in ("cut", "loss", "delay"):
            if fault == "delay":
                namespace.delay(config.delay_ms)
            else:
                namespace.drop(100 if fault == "cut" else config.loss_percent)
            time.sleep(config.hold_s)
            namespace.heal()
        t_heal = time.monotonic()
        time.sleep(config.after_s)
        t_end = time.monotonic()

        samples = list(observer.samples)
        names = {f"trainer{i}": set(trainer_names(case_dir / f"trainer{i}")) for i in range(2)}
        others = [i for i in range(2) if not (target == "trainer" and i == 0)]
        result["fault_s"] = round(t_heal - t_fault, 3)
        result["back_after_s"] = {
            t: back_after(samples, n, t_heal if fault != "none" else t_fault)
            for t, n in names.items()
        }
        answered = [t for t, _, _ in samples if t > t_heal]
        result["status_answered_after_s"] = round(answered[0] - t_heal, 3) if answered else None
        result["others_max_gap_s"] = longest_gap(
            samples, set().union(*(names[f"trainer{i}"] for i in others)), t_fault - 2, t_end
        )
        last = observer.latest()
        result["arenas_settled"] = last[1] if last else None
        result["groups_settled"] = sorted(last[2]) if last else None
        stopped = {t.name: t.stop(60) for t in trainers}
        with contextlib.suppress(TimeoutError):
            observer.wait(lambda s: s[1] == 0, 10, "the trainers' arenas to be freed")
        last = observer.latest()
        result["arenas_after_stop"] = last[1] if last else None
        stopped["server"] = server.stop(30)
        stopped["router"] = router.stop(30)
        result["stopped"] = stopped
        # Shared-memory segments the case made and left behind (none may be: every life's
        # segment goes with its trainer, its server, or the next server's sweep).
        result["segments_left"] = sorted(segments() - segments_before)

        server_rounds = leave_rounds(server)
        steps = {}
        for trainer in trainers:
            summary = last_json(trainer.lives[-1])
            if summary is None or "trainer" not in summary:
                steps[trainer.name] = "no summary"
                continue
            counted, losses = summary["env_steps_called"], summary["server_losses"]
            # Each server loss adds two steps the server never played: the broken episode's
            # truncation and the first observation of the reopened arenas.
            played = counted - 2 * losses
            served = server_rounds.get(summary["trainer"])
            if target == "server" and fault.startswith("kill"):
                served = None  # the killed server's rounds died with it
            steps[trainer.name] = {
                "counted": counted,
                "server_losses": losses,
                "served": served,
                "unmatched": None if served is None else played - served,
            }
        result["steps"] = steps
        result["checkpoints"] = {path.parent.name: checkpoint_step(path) for path in checkpoints}
        result["recordings"] = {
            str(p.relative_to(case_dir)): check_recording(p)
            for p in sorted(case_dir.rglob("*.rrd"))
        }
    finally:
        if observer is not None:
            observer.close()
        for proc in (*trainers, server, router):
            if proc.popen is not None and proc.popen.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.signal(signal.SIGCONT)
                proc.stop(10)
        namespace.close()
    (case_dir / "result.json").write_text(json.dumps(result, indent=2))
    return result


def verdict(result: dict[str, Any]) -> list[str]:
    """What in ``result`` falls short of the bars (empty: all met)."""
    problems = []
    if result["arenas_settled"] != 2:
        problems.append(f"{result['arenas_settled']} arenas in use after the fault, not 2")
    if result["arenas_after_stop"] != 0:
        problems.append(f"{result['arenas_after_stop']} arenas left after the trainers stopped")
    if result.get("segments_left"):
        problems.append(f"shared-memory segments left: {', '.join(result['segments_left'])}")
    for name, back in result["back_after_s"].items():
        if back is None:
            problems.append(f"{name} did not step again")
    for name, steps in result["steps"].items():
        if not isinstance(steps, dict):
            problems.append(f"{name}: {steps}")
        elif steps["unmatched"] is not None and not (
            -steps["server_losses"] <= steps["unmatched"] <= 0
        ):
            # A loss may leave one round played whose Steps never arrived (the episode it
            # belonged to is reported truncated): at most one per loss, never more.
            problems.append(f"{name}: {steps['unmatched']} steps unmatched by the server's rounds")
    for name, how in result["stopped"].items():
        if how["killed"] or how["exit"] != 0:
            problems.append(f"{name} did not stop cleanly on SIGTERM: {how}")
    for name, step in result["checkpoints"].items():
        if not isinstance(step, int):
            problems.append(f"{name}'s checkpoint: {step}")
    if isinstance(result.get("checkpoint_after_kill"), str):
        problems.append(f"checkpoint after the kill: {result['checkpoint_after_kill']}")
    for name, rrd in result["recordings"].items():
        if not rrd["verified"] and not rrd.get("repaired"):
            problems.append(f"{name} unreadable: {rrd}")
    return problems


def main(config: FaultConfig) -> dict[str, Any]:
    unknown = set(config.faults) - set(FAULTS) or set(config.targets) - set(TARGETS)
    if unknown:
        raise SystemExit(
            f"unknown fault or target {sorted(unknown)}: expected {FAULTS} / {TARGETS}"
        )
    if os.geteuid() != 0:
        raise SystemExit("bench.reliability.faults: its network namespaces need root")
    if config.run_dir.exists():
        shutil.rmtree(config.run_dir)
    config.run_dir.mkdir(parents=True)
    missing, no_delay = link_faults_missing(), netem_missing()
    rng = random.Random(config.seed)
    results: list[dict[str, Any]] = []
    skipped: list[dict[str, str]] = []
    for index in range(config.rounds):
        for target in config.targets:
            for fault in config.faults:
                if fault == "kill-checkpoint" and target != "trainer":
                    continue
                if fault == "none" and target != config.targets[0]:
                    continue  # one baseline per round is enough
                why_not = missing if fault in ("cut", "loss") else None
                why_not = no_delay if fault == "delay" else why_not
                if why_not:
                    print(f"{target} {fault}: skipped ({why_not})", flush=True)
                    skipped.append({"target": target, "fault": fault, "why": why_not})
                    continue
                result = run_case(config, target, fault, index, rng)
                result["problems"] = verdict(result)
                results.append(result)
                print(
                    f"{target:7s} {fault:15s} fault {result['fault_s']:5.2f} s; back after "
                    + ", ".join(f"{v}" for v in result["back_after_s"].values())
                    + f" s; others' longest gap {result['others_max_gap_s']} s; arenas "
                    f"{result['arenas_settled']} -> {result['arenas_after_stop']}; "
                    + ("OK" if not result["problems"] else "; ".join(result["problems"])),
                    flush=True,
                )
    summary = {
        "config": {**asdict(config), "run_dir": str(config.run_dir)},
        "skipped": skipped,
        "cases": results,
    }
    (config.run_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(markdown_table(results))
    return summary


def markdown_table(results: list[dict[str, Any]]) -> str:
    """The cases as RELIABILITY.md shows them."""
    lines = [
        "| target | fault | lasted s | status back s | trainers back s | others' longest gap s "
        "| arenas settled / after stop | steps unmatched (losses) | checkpoints | .rrd | "
        "problems |",
        "|---|---|---:|---:|---|---:|---|---|---|---|---|",
    ]
    for r in results:
        steps = ", ".join(
            f"{v['unmatched']} ({v['server_losses']})"
            if isinstance(v, dict) and v["unmatched"] is not None
            else (f"n/a ({v['server_losses']})" if isinstance(v, dict) else str(v))
            for v in r["steps"].values()
        )
        rrd = list(r["recordings"].values())
        repaired = sum(1 for v in rrd if not v["verified"] and v.get("repaired"))
        lines.append(
            f"| {r['target']} | {r['fault']} | {r['fault_s']} | {r.get('status_answered_after_s')} "
            f"| {', '.join(str(v) for v in r['back_after_s'].values())} "
            f"| {r['others_max_gap_s'] if r['target'] == 'trainer' else '-'} "
            f"| {r['arenas_settled']} / {r['arenas_after_stop']} | {steps} "
            f"| {'load' if all(isinstance(v, int) for v in r['checkpoints'].values()) else 'NO'}"
            + (
                f" (after the kill: step {r['checkpoint_after_kill']})"
                if "checkpoint_after_kill" in r
                else ""
            )
            + f" | {len(rrd) - repaired} verify"
            + (f", {repaired} killed: read, repaired" if repaired else "")
            + f" | {'; '.join(r['problems']) or 'none'} |"
        )
    return "\n".join(lines)


def _interrupt(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


if __name__ == "__main__":
    # SIGTERM, and SIGINT (which a shell's background job ignores), end the matrix through the
    # case's own cleanup: its processes stopped, its namespace and veth pair removed.
    signal.signal(signal.SIGTERM, _interrupt)
    signal.signal(signal.SIGINT, _interrupt)
    main(tyro.cli(FaultConfig))
