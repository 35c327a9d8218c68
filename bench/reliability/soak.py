"""Soak: one server, several learning trainers, a spectator and the server's own recording,
left running; every process's resident memory, the server's queues and each trainer's steps
per second sampled every minute.

One ``overtake.server`` (its Rerun recording on, to a file), ``--trainers`` real
``overtake-train`` processes (DQN, Double DQN and Dueling in turn; small replay memories, so
that they are full within the warm-up and memory growth after it means a leak, not a filling
buffer; each writes its own checkpoints and ``trainer.rrd``) and one ``overtake-spectate``
writing an ``.rrd``, all on 127.0.0.1 at a free port. Every ``--sample-every-s`` the bench
reads each process's resident memory (``/proc/PID/status``), asks the server its status (the
queued actions and requests, the frames dropped, each group's round count) and writes one JSON
line to ``samples.jsonl`` in ``--run-dir``. At the end it stops every process with SIGTERM,
checks that each exited on its own, that every checkpoint loads and every ``.rrd`` passes
``rerun rrd verify``, and prints a summary:

- memory: each process's resident memory after the warm-up, first sample / last, and the
  spread (max - min) / min; the bar is 5%;
- rates: each trainer's steps per second per sample interval after the warm-up, its
  coefficient of variation and last / first;
- queues: the most actions and requests waiting at any sample, and the frames dropped.

    .venv/bin/python -m bench.reliability.soak [--minutes 60] [--trainers 8] [--run-dir runs/soak]
"""

from __future__ import annotations

import itertools
import json
import os
import platform
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import tyro

from bench.harness import free_port

ALGOS = ("dqn", "ddqn", "dueling")
SERVER_NAME = "soak"


@dataclass(frozen=True)
class SoakConfig:
    minutes: float = 60.0
    """how long everything runs"""
    trainers: int = 8
    """overtake-train processes on the one server"""
    arenas: int = 1
    """remote arenas per trainer"""
    preset: str = "min2018"
    sample_every_s: float = 60.0
    """seconds between samples"""
    warmup_minutes: float = 10.0
    """samples before this are not judged (imports, replay memories filling, the first
    checkpoints)"""
    replay_size: int = 2000
    """each trainer's replay memory (transitions): full well within the warm-up"""
    learning_starts: int = 500
    checkpoint_every: int = 2000
    """environment steps between each trainer's checkpoints: several during the soak"""
    learners: bool = True
    """trainers that learn (overtake-train); --no-learners: processes stepping their arenas
    with random actions as fast as the server answers (the wire and the server alone)"""
    record: bool = True
    """the server's own recording and the spectator's to .rrd files; --no-record: neither
    records (the spectator still receives every world frame)"""
    transport: Literal["auto", "shm", "zenoh"] = "auto"
    """how the learners' Steps travel (shm: through shared memory; segments are then among
    what must not grow)"""
    run_dir: Path = Path("runs/soak")
    """where the processes' files, samples.jsonl and summary.json go (emptied first)"""


def random_trainer(endpoint: str, preset: str, arenas: int, seed: int) -> None:
    """--no-learners: step ``arenas`` remote arenas with random actions until SIGTERM."""
    from bench.harness import REMOTE_ENV_ID, make_env, random_action
    from overtake.client.wire.remote import RemoteConfig

    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    env = make_env(REMOTE_ENV_ID, arenas, preset=preset, remote=RemoteConfig(connect=(endpoint,)))
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    while not stop:
        _, _, terminated, truncated, _ = env.step(random_action(rng, arenas))
        if arenas == 1 and (terminated or truncated):
            env.reset()
    env.close()


def resident_mib(pid: int) -> float | None:
    """VmRSS of ``pid`` in MiB (None once it has gone)."""
    try:
        with open(f"/proc/{pid}/status") as handle:
            for line in handle:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
    except (FileNotFoundError, ProcessLookupError):
        return None
    return None


def start(command: list[str], log_path: Path) -> subprocess.Popen[bytes]:
    log = open(log_path, "wb")  # noqa: SIM115 - the child holds it; closed in stop_all
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def stop_all(processes: dict[str, subprocess.Popen[bytes]], timeout_s: float) -> dict[str, Any]:
    """SIGTERM every process by its PID, then wait; SIGKILL what outlives ``timeout_s``.
    Each one's exit status and whether it had to be killed."""
    for proc in processes.values():
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    out: dict[str, Any] = {}
    for name, proc in processes.items():
        try:
            code = proc.wait(timeout=max(deadline - time.monotonic(), 0.1))
            out[name] = {"exit": code, "killed": False}
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            out[name] = {"exit": proc.wait(), "killed": True}
    return out


def server_status(connection: Any) -> Any:
    from overtake.protocol.messages import StatusReply, StatusRequest

    return connection.request(SERVER_NAME, StatusRequest(), StatusReply)


def wait_for(condition: Any, timeout_s: float, what: str) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.5)
    raise TimeoutError(f"{what} within {timeout_s:g} s")


def summarise(samples: list[dict[str, Any]], config: SoakConfig) -> dict[str, Any]:
    judged = [s for s in samples if s["t_s"] >= config.warmup_minutes * 60]
    if len(judged) < 2:
        raise RuntimeError(
            f"{len(judged)} sample(s) after the warm-up: run longer than --warmup-minutes"
        )
    memory = {}
    for name in judged[0]["rss_mib"]:
        points = [(s["t_s"], s["rss_mib"][name]) for s in judged if s["rss_mib"].get(name)]
        minutes = np.array([t for t, _ in points]) / 60.0
        values = np.array([v for _, v in points])
        # The trend apart from the noise: a least-squares line through the samples (a process
        # whose memory breathes by a few percent has a spread but no slope; a leak has both).
        slope = float(np.polyfit(minutes, values, 1)[0]) if len(values) > 2 else 0.0
        memory[name] = {
            "first_mib": round(float(values[0]), 1),
            "last_mib": round(float(values[-1]), 1),
            "max_mib": round(float(values.max()), 1),
            "spread": round(float((values.max() - values.min()) / values.min()), 4),
            "last_over_first": round(float(values[-1] / values[0]), 4),
            "slope_mib_per_min": round(slope, 3),
            "trend_per_day": round(slope * 60 * 24 / float(values.mean()), 3),
        }
    rates = {}
    for trainer in judged[0]["rounds"]:
        points = [(s["t_s"], s["rounds"].get(trainer)) for s in judged]
        points = [(t, r) for t, r in points if r is not None]
        per_interval = np.array(
            [(r1 - r0) / (t1 - t0) for (t0, r0), (t1, r1) in itertools.pairwise(points)]
        )
        if per_interval.size == 0:
            continue
        rates[trainer] = {
            "mean_steps_per_s": round(float(per_interval.mean()), 2),
            "cv": round(float(per_interval.std() / per_interval.mean()), 4)
            if per_interval.mean() > 0
            else None,
            "last_over_first": round(float(per_interval[-1] / per_interval[0]), 4)
            if per_interval[0] > 0
            else None,
        }
    return {
        "judged_samples": len(judged),
        "memory": memory,
        "worst_memory_spread": max(m["spread"] for m in memory.values()),
        "rates": rates,
        "queues": {
            "max_queued_actions": max(s["queued_actions"] for s in samples),
            "max_queued_requests": max(s["queued_requests"] for s in samples),
            "dropped_frames": samples[-1]["dropped_frames"],
        },
    }


def checkpoint_step(path: Path) -> int | str:
    """The step of the checkpoint at ``path``, or why it does not load."""
    from overtake.trainers.run.checkpoint import load_checkpoint

    try:
        return load_checkpoint(path).step
    except Exception as error:  # a broken one is a finding, reported with the rest
        return f"unreadable: {error}"


def rerun_rrd(*args: str) -> subprocess.CompletedProcess[str]:
    """``rerun rrd ARGS`` (the CLI beside this Python)."""
    rerun = str(Path(sys.executable).with_name("rerun"))
    return subprocess.run([rerun, "rrd", *args], capture_output=True, text=True, timeout=600)


def verify_rrd(path: Path, footer: bool) -> subprocess.CompletedProcess[str]:
    """``rerun rrd verify``; ``footer=False`` for a file written without Rerun's footer (the
    server's, the spectator's and the trainers' recordings: overtake.viz.recording, on
    footers)."""
    return rerun_rrd("verify", "--check-footers", str(footer).lower(), str(path))


def check_outputs(run_dir: Path, trainers: int) -> dict[str, Any]:
    """Every checkpoint loads, every .rrd passes ``rerun rrd verify``."""
    from overtake.trainers.run.checkpoint import CHECKPOINT_NAME

    out: dict[str, Any] = {"checkpoints": {}, "recordings": {}}
    for index in range(trainers):
        path = run_dir / f"trainer-{index}" / CHECKPOINT_NAME
        out["checkpoints"][path.parent.name] = checkpoint_step(path)
    for rrd in sorted(run_dir.rglob("*.rrd")):
        # Every long-lived writer's (server, spectator, trainers) is written without a footer.
        done = verify_rrd(rrd, footer=False)
        out["recordings"][str(rrd.relative_to(run_dir))] = {
            "verified": done.returncode == 0,
            "mib": round(rrd.stat().st_size / 2**20, 1),
            **({} if done.returncode == 0 else {"error": done.stderr.strip()[-500:]}),
        }
    return out


def main(config: SoakConfig) -> dict[str, Any]:
    from overtake.client.wire.remote import Connection, RemoteConfig

    run_dir = config.run_dir
    if run_dir.exists():
        import shutil

        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    python = sys.executable
    processes: dict[str, subprocess.Popen[bytes]] = {}
    print(
        f"soak: {config.trainers} trainers x {config.arenas} arena(s) of {config.preset}, a "
        f"spectator and the server's recording, {config.minutes:g} min, one sample every "
        f"{config.sample_every_s:g} s ({platform.machine()}, {os.cpu_count()} cores); "
        f"files in {run_dir}",
        flush=True,
    )

    def sink(name: str) -> tuple[str, ...]:
        """The recording options of the server or the spectator: its own .rrd, or none."""
        if not config.record:
            return ("--sink", "off")
        return ("--sink", "file", "--rrd", str(run_dir / f"{name}.rrd"))

    connection = None
    samples: list[dict[str, Any]] = []
    try:
        processes["server"] = start(
            [
                python,
                *("-m", "overtake.server", "--listen", endpoint, "--name", SERVER_NAME),
                *sink("server"),
            ],
            run_dir / "server.log",
        )
        connection = Connection(RemoteConfig(connect=(endpoint,), connect_timeout_s=30.0))
        wait_for(lambda: connection.discover(), 60, "the server did not answer")
        processes["spectator"] = start(
            [
                python,
                *("-m", "overtake.client.wire.spectate", "--connect", endpoint),
                *sink("spectator"),
            ],
            run_dir / "spectator.log",
        )
        for index in range(config.trainers):
            trainer_dir = run_dir / f"trainer-{index}"
            random_argv = [
                *(python, "-m", "bench.reliability.soak", "--random-trainer", endpoint),
                *(config.preset, str(config.arenas), str(index)),
            ]
            processes[f"trainer-{index}"] = start(
                random_argv
                if not config.learners
                else [
                    python,
                    *("-m", "overtake.trainers.train", "--connect", endpoint),
                    *("--preset", config.preset, "--algo", ALGOS[index % len(ALGOS)]),
                    *("--num-envs", str(config.arenas), "--seed", str(index)),
                    *("--total-steps", "1000000000", "--run-dir", str(trainer_dir)),
                    *("--replay-size", str(config.replay_size)),
                    *("--learning-starts", str(config.learning_starts)),
                    *("--checkpoint-every", str(config.checkpoint_every)),
                    *("--no-progress", "--torch-threads", "1"),
                    *("--transport", config.transport),
                ],
                run_dir / f"trainer-{index}.log",
            )
        wait_for(
            lambda: len(server_status(connection).groups) == config.trainers,
            300,
            f"{config.trainers} trainers did not all open their arenas",
        )
        started = time.monotonic()
        with open(run_dir / "samples.jsonl", "w") as out:
            while True:
                t_s = time.monotonic() - started
                dead = [n for n, p in processes.items() if p.poll() is not None]
                if dead:
                    raise RuntimeError(f"{', '.join(dead)} exited during the soak; see its log")
                status = server_status(connection)
                sample = {
                    "t_s": round(t_s, 1),
                    "rss_mib": {n: resident_mib(p.pid) for n, p in processes.items()},
                    "queued_actions": status.queued_actions,
                    "queued_requests": status.queued_requests,
                    "dropped_frames": status.dropped_frames,
                    "rounds": {g.trainers[0]: g.rounds for g in status.groups},
                    "rounds_per_s": {g.trainers[0]: g.rounds_per_s for g in status.groups},
                }
                samples.append(sample)
                out.write(json.dumps(sample) + "\n")
                out.flush()
                rss = sample["rss_mib"]
                print(
                    f"{t_s / 60:5.1f} min: server {rss['server']:.0f} MiB, spectator "
                    f"{rss['spectator']:.0f} MiB, trainers "
                    + "/".join(f"{rss[f'trainer-{i}'] or 0:.0f}" for i in range(config.trainers))
                    + " MiB; rounds/s "
                    + "/".join(f"{r:.1f}" for r in sample["rounds_per_s"].values())
                    + f"; queued {status.queued_actions} actions, {status.queued_requests} "
                    f"requests; {status.dropped_frames} dropped",
                    flush=True,
                )
                if t_s >= config.minutes * 60:
                    break
                time.sleep(max(config.sample_every_s - (time.monotonic() - started - t_s), 0))
    finally:
        if connection is not None:
            connection.close()
        # Trainers first, so that none is left stepping against a server that is gone.
        trainers = {n: p for n, p in processes.items() if n.startswith("trainer")}
        stopped = stop_all(trainers, 120)
        stopped.update(stop_all({n: p for n, p in processes.items() if n not in trainers}, 60))
    summary = {
        "config": {**asdict(config), "run_dir": str(run_dir)},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "stopped": stopped,
        **summarise(samples, config),
        "outputs": check_outputs(run_dir, config.trainers if config.learners else 0),
    }
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return summary


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--random-trainer":
        endpoint, preset, arenas, seed = sys.argv[2:6]
        random_trainer(endpoint, preset, int(arenas), int(seed))
    else:
        main(tyro.cli(SoakConfig))
