"""What runs an experiment's tasks (a training batch, an evaluation): the seam between the
scheduling (:mod:`.run`: what is ready, at most ``--jobs`` at once, what a finished task makes
ready) and where the tasks' processes live. Two launchers: :class:`LocalLauncher`, processes of
this machine (the default), and :class:`.ray_launcher.RayLauncher` (``--ray``), Ray tasks on a
cluster, loaded only when asked for (nothing imports Ray otherwise).

A launcher starts a task whose locks the scheduler holds (so that a process of an earlier
invocation is never joined by a second), and tells what happened since as events: a task
started (where, from which steps), a run's training progress, a task ended (its exit status,
or why it did not end by itself)."""

from __future__ import annotations

import contextlib
import importlib.util
import os
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

from overtake.cli import UsageError

from .processes import (
    Child,
    LaunchEvent,
    Task,
    TaskEnded,
    TaskStarted,
    progress_of,
    release,
    start_lives,
    start_process,
    stop_all,
    wait_any,
)

if TYPE_CHECKING:
    from .plan import ExperimentConfig


@dataclass(frozen=True)
class RayCluster:
    """``--ray``: the tasks run on a Ray cluster."""

    address: str
    """``auto`` (the cluster ``ray.init`` finds, else a local one) or the head's HOST:PORT"""
    retries: int
    """times a task whose node (or worker process) is lost is started again elsewhere"""


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


RAY_EXTRA_HINT = (
    "--ray needs Ray, which is not installed here: install overtake's cluster extra "
    '(pip install -e ".[cluster]")'
)


def ray_installed() -> bool:
    """Whether Ray can be imported (without importing it)."""
    return importlib.util.find_spec("ray") is not None


def ray_cluster(config: ExperimentConfig) -> RayCluster | None:
    """The Ray cluster ``--ray`` names (None without it), checked."""
    if config.ray is None:
        return None
    if not ray_installed():
        raise UsageError(RAY_EXTRA_HINT)
    if len(config.ray) > 1:
        raise UsageError(
            f"--ray takes at most one address (auto or the head's HOST:PORT), got "
            f"{' '.join(config.ray)}"
        )
    address = config.ray[0] if config.ray else "auto"
    if "://" in address:
        # Ray Client: the command would run off the cluster, where its storage is not.
        raise UsageError(
            f"--ray {address}: expected auto or the head's HOST:PORT; run "
            "overtake-experiment on a node of the cluster (Ray Client addresses, ray://, are "
            "not supported: the command reads and writes the experiment directory itself)"
        )
    host, _, port = address.rpartition(":")
    if address != "auto" and not (host and port.isdigit()):
        raise UsageError(f"--ray {address}: expected auto or the head's HOST:PORT")
    if config.device.startswith("cuda:"):
        raise UsageError(
            f"--device {config.device}: with --ray, Ray gives each training task its GPU: "
            "give --device cuda"
        )
    if config.ray_retries < 0:
        raise UsageError(f"--ray-retries must be >= 0, got {config.ray_retries}")
    return RayCluster(address=address, retries=config.ray_retries)


class Launcher(Protocol):
    """Where an experiment's tasks run (see the module's docstring)."""

    @property
    def cores(self) -> int:
        """The CPUs the tasks run on (this machine's, or the cluster's): the default --jobs."""
        ...

    def start(self, task: Task, locks: tuple[int, ...]) -> None:
        """Start ``task``; ``locks`` are the descriptors holding its lock files (the launcher
        owns them from now on)."""
        ...

    def running(self) -> int:
        """The tasks started and not yet ended."""
        ...

    def wait(self, timeout_s: float) -> list[LaunchEvent]:
        """What happened since the last call, once something did or after ``timeout_s``."""
        ...

    def stop_all(self) -> None:
        """Stop every running task, each leaving its runs resumable (a trainer stops with a
        checkpoint), and wait for them."""
        ...


class LocalLauncher:
    """The tasks as processes of this machine: started holding their locks (inherited), ended
    with the experiment (Linux), waited for on their pidfds."""

    def __init__(self, progress_every_s: float) -> None:
        self.progress_every_s = progress_every_s
        self.children: list[Child] = []
        self.events: list[LaunchEvent] = []
        self.next_progress = time.monotonic() + progress_every_s

    @property
    def cores(self) -> int:
        return available_cores()

    def start(self, task: Task, locks: tuple[int, ...]) -> None:
        steps = start_lives(task)
        self.children.append(start_process(task, locks, task.cpus))
        self.events.append(TaskStarted(task, steps, node=None))

    def running(self) -> int:
        return len(self.children)

    def wait(self, timeout_s: float) -> list[LaunchEvent]:
        if not self.events:
            wait_any(self.children, timeout_s)
        events, self.events = self.events, []
        for child in [c for c in self.children if c.process.poll() is not None]:
            self.children.remove(child)
            release(child)
            events.append(TaskEnded(child.task, child.process.returncode))
        if time.monotonic() >= self.next_progress:
            events += [p for child in self.children for p in progress_of(child.task)]
            self.next_progress = time.monotonic() + self.progress_every_s
        return events

    def stop_all(self) -> None:
        stop_all(self.children)
        self.children = []


@contextlib.contextmanager
def open_launcher(
    cluster: RayCluster | None, out: Path, progress_every_s: float
) -> Iterator[Launcher]:
    """The launcher for ``cluster`` (None: this machine's processes), closed on the way out
    (a Ray connection ended). With a cluster, every node is first checked to see and write
    ``out``: one that cannot is refused in one line before anything runs."""
    if cluster is None:
        yield LocalLauncher(progress_every_s)
        return
    try:
        from .ray_launcher import RayLauncher
    except ModuleNotFoundError as error:
        if error.name != "ray" and not (error.name or "").startswith("ray."):
            raise
        raise UsageError(RAY_EXTRA_HINT) from None
    launcher = RayLauncher(cluster, out, progress_every_s)
    try:
        yield launcher
    finally:
        launcher.close()


def where_said(node: str | None) -> str:
    """`` on node N`` for a line of the experiment's output, nothing on this machine."""
    return "" if node is None else f" on node {node}"
