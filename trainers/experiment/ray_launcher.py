"""``--ray``: an experiment's tasks as Ray tasks on a cluster (imported only then).

Each task (a training batch, an evaluation) is one Ray task that asks for the cores its
process uses (and a GPU for a training batch with ``--device cuda``) and runs, on the node Ray
places it on, the very process the local launcher starts (:mod:`.processes`), in the
experiment directory, which every node must see at the same path (shared storage): that is
checked on every node before anything runs, and by every task before it starts. The task
takes its runs' locks there, records the run's new life and where it runs, posts its start
and its runs' progress to a board (a small actor on the experiment's own node) and waits for
its process.

A node lost (its machine, its raylet, or the worker running the task) fails the task with a
system error, which Ray retries on another node, at most ``retries`` times: the retry takes
the locks (once the lost process's are gone), resumes every run from its last checkpoint,
exactly, as a run stopped on one machine resumes, and records the life that says so. A stop
(Ctrl-C, SIGTERM) is posted on the board: every task stops its process as the local launcher
does (SIGTERM, a checkpoint, SIGKILL after a while) and ends; a task that does not, in time,
is cancelled by force (its worker killed: the trainer gets SIGTERM as its parent dies)."""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import ray
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from overtake.cli import UsageError

from .files import checkpoint_step, lock_all, say, storage_problem, write_storage_token
from .processes import (
    POLL_S,
    STOP_TIMEOUT_S,
    Child,
    LaunchEvent,
    Task,
    TaskEnded,
    TaskStarted,
    TrainingProgress,
    progress_of,
    start_lives,
    start_process,
    stop_all,
    wait_any,
)

if TYPE_CHECKING:
    from .launcher import RayCluster

# How long the head's address may take to accept a connection.
HEAD_PROBE_TIMEOUT_S = 10.0
# Every node's check of the experiment directory (a worker process started on each node).
STORAGE_CHECK_TIMEOUT_S = 120.0
# How long a stop waits for the tasks to stop their processes: a trainer's last checkpoint
# (SIGKILL after STOP_TIMEOUT_S), then the task's own end.
STOP_WAIT_S = STOP_TIMEOUT_S + 30.0
# How long a task waits for the board's answer before it starts its process: the board is on
# the experiment's own node.
BOARD_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class NodeStarted:
    """Posted by a task when its process starts (what :class:`.launcher.TaskStarted` says)."""

    task_name: str
    from_steps: tuple[int, ...]
    node: str


@dataclass(frozen=True)
class NodeWork:
    """What a Ray task is given: the task, and the directory it must find as the experiment
    wrote it."""

    task: Task
    out: Path
    token: str
    progress_every_s: float


@dataclass(frozen=True)
class NodeOutcome:
    """How a Ray task ended: its process's exit status; or refused (the experiment directory,
    seen from its node); or stopped before or while its process ran."""

    exit_status: int | None
    refused: str | None = None
    stopped: bool = False


class Board:
    """The tasks' reports to the experiment (starts, progress) and its stop to them: an actor
    on the experiment's node, read by the experiment about once a second."""

    def __init__(self) -> None:
        self.posted: list[NodeStarted | TrainingProgress] = []
        self.stopping = False

    def post(self, items: list[NodeStarted | TrainingProgress]) -> None:
        self.posted += items

    def take(self) -> list[NodeStarted | TrainingProgress]:
        taken, self.posted = self.posted, []
        return taken

    def stop(self) -> None:
        self.stopping = True

    def stop_asked(self) -> bool:
        return self.stopping


def this_node() -> str:
    """The node this runs on, as the experiment's lines name it: the start of its Ray node id
    and its address."""
    node_id = ray.get_runtime_context().get_node_id()
    return f"{node_id[:8]} ({ray.util.get_node_ip_address()})"


def check_storage(out: Path, token: str) -> str | None:
    """On a node: why it cannot work in ``out`` (naming the node), or None."""
    problem = storage_problem(out, token)
    return None if problem is None else f"node {this_node()} {problem}"


class StopPoll:
    """Whether the experiment asked its tasks to stop, asked of the board without ever
    blocking in Ray: a task blocked in ``ray.get`` (or ``ray.wait``) hands its CPUs back to
    Ray while it waits, and Ray may place another task on them, which then shares the cores
    this task's process trains on for as long as both run. A reply is read from its future
    once it has come."""

    def __init__(self, board: Any) -> None:
        self.board = board
        self.reply: Any = None
        self.stop = False

    def asked(self) -> bool:
        """The answer so far (a question sent, where none is under way)."""
        if self.stop:
            return True
        if self.reply is None:
            self.reply = self.board.stop_asked.remote().future()
        elif self.reply.done():
            try:
                self.stop = bool(self.reply.result())
            except ray.exceptions.RayActorError:
                self.stop = True  # the board is gone with the experiment: nobody awaits this
            except ray.exceptions.RayError:
                pass  # asked again next time
            self.reply = None
        return self.stop

    def answered(self, timeout_s: float) -> bool:
        """A fresh answer, waited for up to ``timeout_s`` (none by then: not asked)."""
        self.reply = None
        self.asked()
        deadline = time.monotonic() + timeout_s
        while self.reply is not None and not self.reply.done() and time.monotonic() < deadline:
            time.sleep(0.02)
        return self.asked()


def run_on_node(work: NodeWork, board: Any) -> NodeOutcome:
    """A Ray task: ``work.task``'s process on this node, from its storage check to its end."""
    refused = check_storage(work.out, work.token)
    if refused is not None:
        return NodeOutcome(None, refused=refused)
    # The same module run by this node's own interpreter (a node's may live elsewhere).
    task = dataclasses.replace(work.task, command=(sys.executable, *work.task.command[1:]))
    stop = StopPoll(board)
    locks = lock_all(task.lock_paths)
    while locks is None:
        # A process of the task's earlier attempt still stopping (or a node cut off, not dead,
        # still training): its runs go on from where it leaves them.
        if stop.asked():
            return NodeOutcome(None, stopped=True)
        time.sleep(POLL_S)
        locks = lock_all(task.lock_paths)
    finished = task.runs and all(
        (checkpoint_step(run.run_dir) or 0) >= run.train.total_steps for run in task.runs
    )
    if finished or stop.answered(BOARD_TIMEOUT_S):
        # Finished by that earlier attempt meanwhile, or a stop asked before this began.
        for fd in locks:
            os.close(fd)
        return NodeOutcome(0) if finished else NodeOutcome(None, stopped=True)
    node = this_node()
    steps = start_lives(task, node)
    board.post.remote([NodeStarted(task.name, steps, node)])
    child = start_process(task, locks, task.cpus)
    return _wait_for(child, work, board, stop)


def _wait_for(child: Child, work: NodeWork, board: Any, stop: StopPoll) -> NodeOutcome:
    """Wait for ``child`` to end, posting its runs' progress, stopping it when the experiment
    asks (SIGTERM: a trainer writes its checkpoint), and however this ends, leaving no process
    behind and its locks released."""
    next_progress = time.monotonic() + work.progress_every_s
    stopped = False
    try:
        while child.process.poll() is None:
            wait_any([child], POLL_S)
            if child.process.poll() is None and stop.asked():
                stopped = True
                break
            if time.monotonic() >= next_progress and child.task.runs:
                board.post.remote(progress_of(child.task))
                next_progress = time.monotonic() + work.progress_every_s
    finally:
        stop_all([child])  # a process still running is stopped first; released
    return NodeOutcome(child.process.returncode, stopped=stopped)


_check_storage = ray.remote(check_storage)
_run_on_node = ray.remote(run_on_node)
_Board = ray.remote(num_cpus=0)(Board)


class RayLauncher:
    """The experiment's tasks as Ray tasks (see the module's docstring)."""

    def __init__(self, cluster: RayCluster, out: Path, progress_every_s: float) -> None:
        self.cluster, self.out, self.progress_every_s = cluster, out, progress_every_s
        # ray.init sets its own SIGTERM handler (an exit): a SIGTERM must stop the experiment
        # as Ctrl-C does, through the command's own, which stops the tasks.
        if cluster.address != "auto":
            _check_listening(cluster.address)
        sigterm = signal.getsignal(signal.SIGTERM)
        try:
            ray.init(
                address=None if cluster.address == "auto" else cluster.address,
                logging_level=logging.WARNING,
                log_to_driver=False,
            )
        except ConnectionError as error:
            raise UsageError(
                f"--ray {cluster.address}: no Ray cluster there ({error}); start one with "
                "`ray start --head` (docs/cluster.md)"
            ) from None
        finally:
            if sigterm is not None:
                signal.signal(signal.SIGTERM, sigterm)
        try:
            here = ray.get_runtime_context().get_node_id()
            self.board: Any = _Board.options(
                scheduling_strategy=NodeAffinitySchedulingStrategy(here, soft=False)
            ).remote()
            self.token = write_storage_token(out)
            self._check_storage()
        except BaseException:
            ray.shutdown()
            raise
        self.refs: dict[Any, Task] = {}
        self.tasks: dict[str, Task] = {}
        self.starts: dict[str, int] = {}

    @staticmethod
    def _alive_nodes() -> list[dict[str, Any]]:
        return [node for node in ray.nodes() if node.get("Alive")]

    def _check_storage(self) -> None:
        """Every node sees the experiment directory and may write there, or the experiment is
        refused in one line, before anything runs."""
        nodes = self._alive_nodes()
        checks = [
            _check_storage.options(
                num_cpus=0,
                scheduling_strategy=NodeAffinitySchedulingStrategy(node["NodeID"], soft=False),
            ).remote(self.out, self.token)
            for node in nodes
        ]
        try:
            problems = [p for p in ray.get(checks, timeout=STORAGE_CHECK_TIMEOUT_S) if p]
        except ray.exceptions.GetTimeoutError:
            raise UsageError(
                f"--ray {self.cluster.address}: not every node of the cluster checked --out "
                f"{self.out} within {STORAGE_CHECK_TIMEOUT_S:.0f} s"
            ) from None
        if problems:
            others = f" (and {len(problems) - 1} more of its nodes)" if len(problems) > 1 else ""
            raise UsageError(_refusal(self.out, problems[0] + others, "nothing was trained"))
        say(
            f"Ray cluster {self.cluster.address}: {len(nodes)} node(s), {self.cores} CPU(s), "
            f"{self._gpus()} GPU(s); every node sees and may write {self.out}"
        )

    @property
    def cores(self) -> int:
        return int(sum(node["Resources"].get("CPU", 0) for node in self._alive_nodes()))

    def _gpus(self) -> int:
        return int(sum(node["Resources"].get("GPU", 0) for node in self._alive_nodes()))

    def _check_fits(self, task: Task) -> None:
        """Refuse a task no node can hold (Ray would keep it waiting for ever)."""
        nodes = self._alive_nodes()
        largest = max((int(n["Resources"].get("CPU", 0)) for n in nodes), default=0)
        if task.cpus > largest:
            raise UsageError(
                f"each task asks for its PyTorch threads' CPUs, {task.cpus} here (--torch-threads, "
                f"by default the cluster's CPUs over --jobs), and the Ray cluster's largest node "
                f"has {largest}: give --torch-threads {largest} or fewer"
            )
        if task.gpus > max((n["Resources"].get("GPU", 0) for n in nodes), default=0):
            raise UsageError(
                "--device cuda: each training task asks for a GPU, and no node of the Ray "
                "cluster has one"
            )

    def start(self, task: Task, locks: tuple[int, ...]) -> None:
        # The task takes the locks itself, on its node.
        for fd in locks:
            os.close(fd)
        self._check_fits(task)
        work = NodeWork(task, self.out, self.token, self.progress_every_s)
        ref = _run_on_node.options(
            num_cpus=task.cpus,
            num_gpus=task.gpus,
            max_retries=self.cluster.retries,
            retry_exceptions=False,
            name=f"overtake {task.kind} {task.name}",
        ).remote(work, self.board)
        self.refs[ref] = task
        self.tasks[task.name] = task

    def running(self) -> int:
        return len(self.refs)

    def wait(self, timeout_s: float) -> list[LaunchEvent]:
        ready: list[Any] = []
        if self.refs:
            ready, _ = ray.wait(list(self.refs), num_returns=1, timeout=timeout_s)
            if ready:
                ready, _ = ray.wait(list(self.refs), num_returns=len(self.refs), timeout=0)
        else:
            time.sleep(timeout_s)
        events = self._posted()
        for ref in ready:
            task = self.refs.pop(ref)
            events.append(self._ended(task, ref))
        return events

    def _posted(self) -> list[LaunchEvent]:
        events: list[LaunchEvent] = []
        try:
            posted = ray.get(self.board.take.remote(), timeout=BOARD_TIMEOUT_S)
        except ray.exceptions.GetTimeoutError:
            return events  # the board is slow to answer: what it holds comes next time
        for item in posted:
            if isinstance(item, NodeStarted):
                attempt = self.starts.get(item.task_name, 0)
                self.starts[item.task_name] = attempt + 1
                task = self.tasks[item.task_name]
                events.append(TaskStarted(task, item.from_steps, item.node, attempt))
            else:
                events.append(item)
        return events

    def _ended(self, task: Task, ref: Any) -> TaskEnded:
        try:
            outcome: NodeOutcome = ray.get(ref)
        except ray.exceptions.RayError as error:
            lost = isinstance(
                error,
                ray.exceptions.WorkerCrashedError
                | ray.exceptions.NodeDiedError
                | ray.exceptions.LocalRayletDiedError,
            )
            why = (
                f"its node or worker was lost, and it has been retried {self.cluster.retries} "
                "time(s) (--ray-retries)"
                if lost
                else str(error).strip().splitlines()[0]
            )
            return TaskEnded(task, None, failure=why)
        if outcome.refused is not None:
            raise UsageError(_refusal(self.out, outcome.refused, "the tasks under way stop"))
        if outcome.stopped:
            return TaskEnded(task, outcome.exit_status, failure="stopped")
        return TaskEnded(task, outcome.exit_status)

    def stop_all(self) -> None:
        if not self.refs:
            return
        say(f"stopping {len(self.refs)} Ray task(s): each stops its process with a checkpoint")
        try:
            self.board.stop.remote()
            pending = list(self.refs)
            deadline = time.monotonic() + STOP_WAIT_S
            while pending and time.monotonic() < deadline:
                _, pending = ray.wait(
                    pending, num_returns=len(pending), timeout=deadline - time.monotonic()
                )
            for ref in pending:
                ray.cancel(ref, force=True)
        finally:
            self.refs.clear()

    def close(self) -> None:
        ray.shutdown()


def _check_listening(address: str) -> None:
    """Refuse at once a head address nothing listens on: Ray would try it for minutes."""
    host, _, port = address.rpartition(":")
    try:
        socket.create_connection(
            (host.strip("[]"), int(port)), timeout=HEAD_PROBE_TIMEOUT_S
        ).close()
    except OSError as error:
        raise UsageError(
            f"--ray {address}: no Ray head listens there ({error.strerror or error}): start "
            f"one with `ray start --head --port {port}` (docs/cluster.md)"
        ) from None


def _refusal(out: Path, problem: str, then: str) -> str:
    return (
        f"--out {out}: {problem}: with --ray the experiment directory must be storage every "
        f"node sees and may write, at the same path (a shared filesystem; docs/cluster.md); "
        f"{then}"
    )
