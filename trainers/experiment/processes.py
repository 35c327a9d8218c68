"""The training and evaluation processes: started with a lock and a PID file, ended with the
experiment, waited for without polling their pipes; what is done around one wherever it runs
(its runs' new lives recorded, their progress read), and what a launcher (:mod:`.launcher`)
says of its tasks (:data:`LaunchEvent`)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from .files import checkpoint_step, last_train_record, note_life, utc_now

if TYPE_CHECKING:
    from .plan import RunPlan

# How often the scheduler wakes without a child ending (it prints the runs' progress every
# --progress-every-s).
POLL_S = 1.0
STOP_TIMEOUT_S = 30.0


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the child gets SIGTERM when the experiment dies, even by SIGKILL, rather than
    training on unseen (a restarted experiment would wait for it)."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG


@dataclass
class Child:
    """A running training or evaluation process, the lock it holds and its pid file."""

    task: Task
    process: subprocess.Popen
    lock_fds: tuple[int, ...]
    pid_file: Path
    log: Any
    pidfd: int | None


@dataclass(frozen=True)
class Task:
    """A process to run: training runs (one, or several as members of one learner), or an
    evaluation whose result goes to ``cache``."""

    kind: Literal["train", "eval"]
    name: str
    """in the experiment's messages: the run(s), or the policy and density"""
    command: tuple[str, ...]
    lock_paths: tuple[Path, ...]
    """held while it runs (each training run's directory, an evaluation's cache file)"""
    log_path: Path
    pid_file: Path
    """holds the process's id while it runs"""
    runs: tuple[RunPlan, ...] = ()
    cache: Path | None = None
    key: dict[str, Any] = field(default_factory=dict)
    """an evaluation's settings, stored with its result: a cache entry counts only for these"""
    cpus: int = 1
    """the cores it uses (its PyTorch threads): what a cluster reserves for it"""
    gpus: int = 0
    """the GPUs it uses (a training batch with --device cuda): what a cluster reserves"""

    @property
    def json_out(self) -> Path:
        assert self.cache is not None
        return self.cache.with_name(self.cache.name + ".out")


def start_process(task: Task, fds: tuple[int, ...], threads: int) -> Child:
    """Start ``task``'s command, its output appended to its log, holding the locks ``fds``
    (the child inherits them) with ``threads`` PyTorch and OpenMP threads."""
    task.log_path.parent.mkdir(parents=True, exist_ok=True)
    log = open(task.log_path, "a", encoding="utf-8")  # noqa: SIM115 (open while it runs)
    log.write(f"--- {utc_now()} overtake-experiment starts: {' '.join(task.command)}\n")
    log.flush()
    process = subprocess.Popen(
        task.command,
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=subprocess.STDOUT,
        # PyTorch sizes its thread pool from these at start (overtake-eval has no option for
        # it): --jobs processes of as many threads each as there are cores would contend.
        env={**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)},
        # The locks' descriptors go with it: the locks live as long as the child.
        pass_fds=fds,
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
    )
    task.pid_file.write_text(f"{process.pid}\n")
    pidfd = None
    with contextlib.suppress(AttributeError, OSError):
        pidfd = os.pidfd_open(process.pid)
    return Child(task, process, fds, task.pid_file, log, pidfd)


def release(child: Child) -> None:
    child.log.close()
    if child.pidfd is not None:
        os.close(child.pidfd)
    with contextlib.suppress(FileNotFoundError):
        child.pid_file.unlink()
    for fd in child.lock_fds:
        os.close(fd)


def stop_all(children: list[Child]) -> None:
    """End every running child (SIGTERM, then SIGKILL after STOP_TIMEOUT_S) and release it."""
    for child in children:
        if child.process.poll() is None:
            child.process.terminate()
    deadline = time.monotonic() + STOP_TIMEOUT_S
    for child in children:
        try:
            child.process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.process.kill()
            child.process.wait()
        release(child)


def wait_any(children: list[Child], timeout_s: float) -> None:
    """Return when a child has ended or after ``timeout_s``."""
    fds = [child.pidfd for child in children if child.pidfd is not None]
    if len(fds) == len(children) and fds:
        select.select(fds, [], [], timeout_s)
        return
    # Without pidfds (not Linux): poll.
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(child.process.poll() is not None for child in children):
            return
        time.sleep(0.1)


@dataclass(frozen=True)
class TaskStarted:
    """A task's process started: a task's first start, or (``attempt`` 1 and on) its start
    again elsewhere after the node it ran on was lost."""

    task: Task
    from_steps: tuple[int, ...]
    """each of its training runs' step when it started (0: from scratch)"""
    node: str | None
    """where: None on this machine, else the cluster node (its id's start and address)"""
    attempt: int = 0


@dataclass(frozen=True)
class TrainingProgress:
    """A training run's last logged step, as the task training it read it."""

    run: str
    step: int
    steps_per_s: float


@dataclass(frozen=True)
class TaskEnded:
    """A task's process ended (``exit_status``), or the task ended without it: lost more times
    than its retries allow, or stopped (``exit_status`` None, ``failure`` says why)."""

    task: Task
    exit_status: int | None
    failure: str | None = None


LaunchEvent = TaskStarted | TrainingProgress | TaskEnded


def start_lives(task: Task, node: str | None = None) -> tuple[int, ...]:
    """Before ``task``'s process starts: each of its training runs' step (its checkpoint's),
    each recorded as a new life of the run (:func:`.files.note_life`)."""
    steps = tuple(checkpoint_step(run.run_dir) or 0 for run in task.runs)
    for run, step in zip(task.runs, steps, strict=True):
        note_life(run.run_dir, step, node)
    return steps


def progress_of(task: Task) -> list[TrainingProgress]:
    """The training progress of ``task``'s runs, from their metrics.jsonl."""
    progress = []
    for run in task.runs:
        last = last_train_record(run.run_dir / "metrics.jsonl")
        if last is not None:
            progress.append(TrainingProgress(run.name, last["step"], last["steps_per_s"]))
    return progress
