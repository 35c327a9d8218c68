"""``overtake-experiment`` on a Ray cluster, with and without a lost node, against the same
experiment as this machine's processes (issue 69).

A local Ray cluster of ``--nodes`` nodes of one CPU each (``ray.cluster_utils.Cluster``: a head
and worker nodes, each its own raylet and workers) runs inside a network namespace this script
makes (``unshare``: its own user, network and mount namespaces, only the loopback up), where
Ray binds every node to 127.0.0.1; outside one it would bind the machine's own address. Its
scenarios (``--scenarios``), each the same experiment (``--experiment`` and
``--experiment-args``: by default the issue's short ``ho2018-table8``) in a directory of its
own:

- ``local``: the command without ``--ray`` (the reference table);
- ``ray``: with ``--ray ADDRESS``;
- ``lost-node``: with ``--ray``, and the worker node that trains the largest training batch
  lost once its runs have a checkpoint at ``--lose-at`` of the budget: the worker process
  running the task, the batch's trainer and the node's raylet killed (SIGKILL) and the node
  removed, as a machine that vanishes; Ray retries the task on another node, and its runs
  resume from their checkpoints;
- ``stopped``: with ``--ray``, SIGTERM to the experiment (as Ctrl-C) once every training batch
  has started and one has a checkpoint at ``--lose-at`` of the budget: every task stops its
  process, none is left running, every run has its checkpoint; then the same command again,
  to the table;
- ``refused``: ``--out`` on storage the nodes may not write (a read-only mount that only the
  nodes see) and on storage they do not see (a mount only the experiment sees): each refused
  in one line, before anything trains.

Figures (printed, and with ``--json`` written as JSON): the time to the table of each
scenario, the retries the experiment reported, whether each ``--ray`` table's trained rows
equal the local table's (every figure of every row and run, their provenance aside), what the
lost batch's runs resumed from and whether exactly, how the stop went (its time, the processes
left, the runs' steps), and each refusal's line and time.

    .venv/bin/python -m bench.reliability.experiment_cluster [--json PATH]
        [--scenarios local ray lost-node refused] [--experiment-args="--total-steps 3000 ..."]
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

from bench.harness import write_report

ROOT = Path(__file__).resolve().parents[2]
Scenario = Literal["local", "ray", "lost-node", "stopped", "refused"]
SCENARIOS: tuple[Scenario, ...] = ("local", "ray", "lost-node", "stopped", "refused")
# The experiment: a few thousand steps, one evaluation episode, one density and one
# reference policy, one PyTorch thread a task (a node's one CPU).
SHORT_TABLE8 = (
    "--total-steps 3000 --learning-starts 500 --eval-episodes 1 --densities medium "
    "--references idle --torch-threads 1"
)
POLL_S = 0.5


@dataclass(frozen=True)
class ClusterBenchConfig:
    """overtake-experiment on a local Ray cluster in a network namespace of its own, with and
    without a lost node, against the same experiment as local processes."""

    scenarios: tuple[Scenario, ...] = SCENARIOS
    """which to run (the ``--ray`` tables are compared with ``local``'s where it ran)"""
    experiment: str = "ho2018-table8"
    experiment_args: str = SHORT_TABLE8
    """overtake-experiment's options as one string, the same in every scenario (--out and
    --ray are added)"""
    nodes: int = 3
    """Ray nodes, the head among them, one CPU each"""
    lose_at: float = 1 / 3
    """lost-node: the node is lost once its batch's runs have a checkpoint at this fraction of
    the budget"""
    timeout_s: float = 3600.0
    """each experiment's limit"""
    work_dir: Path | None = None
    """where the experiments' directories go; unset: a temporary one, removed at the end"""
    json: Path | None = None
    """also write the figures here"""


def in_own_network() -> bool:
    """Whether this process's network namespace has only the loopback interface."""
    return {name for _, name in socket.if_nameindex()} == {"lo"}


def enter_namespace() -> None:
    """Run this script again in new user, network and mount namespaces (unshare, as an
    unprivileged user), where only the loopback interface exists."""
    command = ["unshare", "--user", "--map-root-user", "--net", "--mount"]
    probe = subprocess.run([*command, "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        raise SystemExit(
            f"this bench needs unprivileged user and network namespaces (unshare -rnm): "
            f"{probe.stderr.strip() or probe.returncode}"
        )
    os.execvp(command[0], [*command, sys.executable, "-m", __spec__.name, *sys.argv[1:]])


def say(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def ray_cluster(nodes: int) -> Iterator[Any]:
    """A local Ray cluster of ``nodes`` one-CPU nodes, shut down on the way out."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(
        initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False}
    )
    try:
        for _ in range(nodes - 1):
            cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        yield cluster
    finally:
        cluster.shutdown()


def experiment_command(config: ClusterBenchConfig, out: Path, address: str | None) -> list[str]:
    command = [sys.executable, "-m", "overtake.trainers.experiment", config.experiment]
    command += [*shlex.split(config.experiment_args), "--out", str(out)]
    return command + (["--ray", address] if address is not None else [])


@dataclass
class Experiment:
    """An overtake-experiment process and its output."""

    process: subprocess.Popen[bytes]
    stderr: Path
    started: float

    @classmethod
    def start(cls, command: list[str], folder: Path) -> Experiment:
        folder.mkdir(parents=True, exist_ok=True)
        stderr = folder / "experiment.stderr"
        with open(folder / "experiment.stdout", "wb") as out, open(stderr, "wb") as err:
            process = subprocess.Popen(command, stdout=out, stderr=err, cwd=ROOT)
        return cls(process, stderr, time.monotonic())

    def lines(self) -> list[str]:
        return self.stderr.read_text(encoding="utf-8", errors="replace").splitlines()

    def finish(self, timeout_s: float) -> dict[str, Any]:
        try:
            status = self.process.wait(timeout=max(1.0, timeout_s))
        except subprocess.TimeoutExpired:
            self.process.send_signal(signal.SIGINT)
            status = self.process.wait(timeout=120)
        lines = self.lines()
        again = [line for line in lines if " again on node " in line]
        return {
            "exit_status": status,
            "seconds": round(time.monotonic() - self.started, 1),
            # A line per run of each task started again (a batch's runs share its log).
            "retries": [line.split("] ", 1)[-1] for line in again],
            "tasks_retried": len({line.rsplit("(log ", 1)[-1] for line in again}),
            "last_line": lines[-1] if lines else "",
        }


def trained_rows(table_json: Path) -> dict[str, Any]:
    """A table's trained rows, per density: every figure of each row and of each of its runs,
    and the rows' order, without how each run was made (its lives' times and nodes, the code
    that evaluated it) and how fast its evaluation went."""
    table = json.loads(table_json.read_text())
    unlearned = ("provenance", "decisions_per_s", "evaluated_by")
    return {
        density: {
            "rows": [
                {
                    **row,
                    "runs": [
                        {key: value for key, value in run.items() if key not in unlearned}
                        for run in row["runs"]
                    ],
                }
                for row in part["rows"]
            ],
            "order": part["order"],
        }
        for density, part in table["densities"].items()
    }


def run_local(config: ClusterBenchConfig, work: Path) -> dict[str, Any]:
    out = work / "local"
    experiment = Experiment.start(experiment_command(config, out, None), work / "local-output")
    result = experiment.finish(config.timeout_s)
    say(f"local: exit {result['exit_status']} after {result['seconds']:.0f} s")
    return {**result, "out": str(out)}


def run_ray(config: ClusterBenchConfig, work: Path, address: str) -> dict[str, Any]:
    out = work / "ray"
    experiment = Experiment.start(experiment_command(config, out, address), work / "ray-output")
    result = experiment.finish(config.timeout_s)
    say(f"ray: exit {result['exit_status']} after {result['seconds']:.0f} s")
    return {**result, "out": str(out)}


START = re.compile(
    r"train (\S+): starts from (?:scratch|step [\d,]+) on node ([0-9a-f]{8}) .*\(log (.+)\)$"
)


def batches_on_nodes(lines: list[str]) -> dict[str, tuple[str, list[str]]]:
    """Each training batch started so far (by its log), its node and its runs."""
    batches: dict[str, tuple[str, list[str]]] = {}
    for line in lines:
        match = START.search(line)
        if match is not None and " again " not in line:
            run, node, log = match.groups()
            batches.setdefault(log, (node, []))[1].append(run)
    return batches


def run_lost_node(
    config: ClusterBenchConfig, work: Path, cluster: Any, budget: int
) -> dict[str, Any]:
    from overtake.trainers.experiment.files import checkpoint_step

    out = work / "lost-node"
    address = cluster.address
    experiment = Experiment.start(
        experiment_command(config, out, address), work / "lost-node-output"
    )
    workers = {node.node_id[:8]: node for node in cluster.worker_nodes}
    lost: dict[str, Any] = {}
    deadline = time.monotonic() + config.timeout_s
    while not lost and experiment.process.poll() is None and time.monotonic() < deadline:
        on_workers = [
            (len(runs), node, runs, log)
            for log, (node, runs) in batches_on_nodes(experiment.lines()).items()
            if node in workers
        ]
        if on_workers:
            _, node, runs, log = max(on_workers)
            run_dir = out / runs[0]
            step = checkpoint_step(run_dir) or 0
            if step >= config.lose_at * budget:
                lost = lose_node(cluster, workers[node], run_dir)
                lost.update(node=node, runs=runs, checkpoint_step=step, log=log)
                say(f"lost-node: node {node} lost, its batch of {len(runs)} at step {step:,}")
                break
        time.sleep(POLL_S)
    result = experiment.finish(deadline - time.monotonic())
    say(f"lost-node: exit {result['exit_status']} after {result['seconds']:.0f} s")
    if lost and result["exit_status"] == 0:
        lost["resumed"] = resumed_lives(out / "table.json", lost["runs"], lost["checkpoint_step"])
        lost["retry_waited_for_a_cpu"] = waited_for_a_cpu(experiment.lines(), lost["runs"])
    return {**result, "out": str(out), "lost": lost}


def waited_for_a_cpu(lines: list[str], lost_runs: list[str]) -> bool:
    """Whether the lost batch started again only once another task had ended: every node's
    one CPU was taken when its node was lost, so that is when Ray could place it (a task that
    gave its CPU back to Ray while it waited on a call would have let it in earlier)."""
    stamp = re.compile(r"^\[(\d\d:\d\d:\d\d)\] ")
    again = next(line for line in lines if " again on node " in line)
    others_done = [
        line
        for line in lines
        if re.search(r"train (\S+): done at step", line)
        and not any(f"train {run}: " in line for run in lost_runs)
    ]
    first = stamp.match(again)
    return bool(others_done) and first is not None and first.group(1) >= others_done[0][1:9]


def lose_node(cluster: Any, node: Any, run_dir: Path) -> dict[str, Any]:
    """The node gone as a machine that vanishes: the worker process running the task first
    (it reports nothing more), the trainer (no checkpoint on the way out), then the raylet
    and the rest of the node."""
    trainer = int((run_dir / "train.pid").read_text())
    worker = int(Path(f"/proc/{trainer}/stat").read_text().rsplit(")", 1)[1].split()[1])
    for pid in (worker, trainer):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    cluster.remove_node(node, allow_graceful=False)
    return {"worker_pid": worker, "trainer_pid": trainer, "at_s": time.monotonic()}


def resumed_lives(table_json: Path, runs: list[str], step: int) -> dict[str, Any]:
    """For each of the lost batch's runs, its lives' first steps and whether the life after
    the loss restored everything (its target, optimiser, replay and episodes under way)."""
    table = json.loads(table_json.read_text())
    lives = {
        run["run"]: run["provenance"]
        for part in table["densities"].values()
        for row in part["rows"]
        for run in row["runs"]
    }
    return {
        run: {
            "from_steps": [life["from_step"] for life in lives[run]],
            "exactly": all(
                life["target_restored"]
                and life["optimizer_restored"]
                and life["replay_restored"]
                and life["arenas_restored"]
                for life in lives[run][1:]
            ),
            "resumed_from_the_checkpoint": any(
                life["from_step"] >= step for life in lives[run][1:]
            ),
        }
        for run in runs
    }


def run_stopped(
    config: ClusterBenchConfig, work: Path, address: str, budget: int
) -> dict[str, Any]:
    """SIGTERM to the experiment once its training is under way, then the same command again
    to the table."""
    from overtake.trainers.experiment.files import checkpoint_step

    out = work / "stopped"
    command = experiment_command(config, out, address)
    experiment = Experiment.start(command, work / "stopped-output")
    deadline = time.monotonic() + config.timeout_s
    stopped: dict[str, Any] = {}
    while experiment.process.poll() is None and time.monotonic() < deadline:
        batches = batches_on_nodes(experiment.lines())
        steps = [checkpoint_step(out / runs[0]) or 0 for _, runs in batches.values()]
        if steps and max(steps) >= config.lose_at * budget:
            began = time.monotonic()
            experiment.process.send_signal(signal.SIGTERM)
            experiment.process.wait(timeout=600)
            pids = [int(p.read_text()) for p in out.rglob("*.pid")]
            stopped = {
                "stop_s": round(time.monotonic() - began, 1),
                "exit_status": experiment.process.returncode,
                "last_line": experiment.lines()[-1],
                "pid_files_left": len(pids),
                "processes_left": [pid for pid in pids if Path(f"/proc/{pid}").exists()],
                "steps": {
                    run: checkpoint_step(out / run) or 0
                    for _, runs in batches.values()
                    for run in runs
                },
            }
            say(f"stopped: {stopped['last_line']} ({stopped['stop_s']:.0f} s)")
            break
        time.sleep(POLL_S)
    again = Experiment.start(command, work / "stopped-again-output")
    result = again.finish(deadline - time.monotonic())
    say(f"stopped, then again: exit {result['exit_status']} after {result['seconds']:.0f} s")
    return {**result, "out": str(out), "stopped": stopped}


def run_refused(config: ClusterBenchConfig, work: Path, address: str) -> dict[str, Any]:
    """--out on storage the nodes may not write, then on storage they do not see."""
    results = {}
    readonly = work / "refused-readonly"
    readonly.mkdir(parents=True)
    # The nodes (this mount namespace) see it read-only; the experiment, in a mount namespace
    # of its own, without that mount, may write.
    subprocess.run(["mount", "--bind", str(readonly), str(readonly)], check=True)
    subprocess.run(["mount", "-o", "remount,ro,bind", str(readonly)], check=True)
    try:
        results["read-only"] = _refused_run(
            config, readonly / "exp", address, f"umount {readonly}", work / "refused-ro-output"
        )
    finally:
        subprocess.run(["umount", str(readonly)], check=True)
    unseen = work / "refused-unseen"
    unseen.mkdir(parents=True)
    # The experiment writes on a filesystem of its own that no node sees.
    results["unseen"] = _refused_run(
        config,
        unseen / "exp",
        address,
        f"mount -t tmpfs tmpfs {unseen}",
        work / "refused-unseen-output",
    )
    return results


def _refused_run(
    config: ClusterBenchConfig, out: Path, address: str, mount: str, folder: Path
) -> dict[str, Any]:
    command = experiment_command(config, out, address)
    shell = f"{mount} && exec {shlex.join(command)}"
    experiment = Experiment.start(["unshare", "--mount", "sh", "-c", shell], folder)
    result = experiment.finish(config.timeout_s)
    trained = [str(p.relative_to(out)) for p in out.rglob("train.log")] if out.exists() else []
    say(f"refused: {result['last_line']}")
    return {**result, "train_logs": trained}


def budget_of(options: str) -> int:
    args = shlex.split(options)
    if "--total-steps" in args:
        return int(args[args.index("--total-steps") + 1])
    from overtake.trainers.experiment import EXPERIMENTS

    raise SystemExit(f"give --total-steps in --experiment-args ({list(EXPERIMENTS)})")


def main(config: ClusterBenchConfig) -> dict[str, Any]:
    if not in_own_network():
        enter_namespace()
    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    made = config.work_dir is None
    work = Path(tempfile.mkdtemp(prefix="experiment-cluster-")) if made else config.work_dir
    assert work is not None
    work.mkdir(parents=True, exist_ok=True)
    # Ray's own warnings of a machine without a route out (its C++ side looks for one).
    os.environ.setdefault("RAY_BACKEND_LOG_LEVEL", "error")
    # Ray's sockets and session files in a short folder of their own (a Unix socket's path is
    # short), not in the machine's /tmp/ray, where another cluster's address would be found.
    ray_tmp = Path(tempfile.mkdtemp(prefix="ray-", dir="/tmp"))
    os.environ["RAY_TMPDIR"] = str(ray_tmp)
    report: dict[str, Any] = {"experiment": f"{config.experiment} {config.experiment_args}"}
    try:
        if "local" in config.scenarios:
            report["local"] = run_local(config, work)
        if set(config.scenarios) - {"local"}:
            began = time.monotonic()
            with ray_cluster(config.nodes) as cluster:
                report["cluster_up_s"] = round(time.monotonic() - began, 1)
                say(f"Ray cluster of {config.nodes} nodes up in {report['cluster_up_s']} s")
                if "refused" in config.scenarios:
                    report["refused"] = run_refused(config, work, cluster.address)
                if "ray" in config.scenarios:
                    report["ray"] = run_ray(config, work, cluster.address)
                budget = budget_of(config.experiment_args)
                if "stopped" in config.scenarios:
                    report["stopped"] = run_stopped(config, work, cluster.address, budget)
                if "lost-node" in config.scenarios:
                    report["lost-node"] = run_lost_node(config, work, cluster, budget)
        compare(report)
        print_figures(report)
        write_report(config.json, report)
    finally:
        shutil.rmtree(ray_tmp, ignore_errors=True)
        if made:
            shutil.rmtree(work, ignore_errors=True)
    return report


def compare(report: dict[str, Any]) -> None:
    """Whether each --ray table's trained rows equal the local table's."""
    local = report.get("local")
    if local is None or local["exit_status"] != 0:
        return
    reference = trained_rows(Path(local["out"]) / "table.json")
    for name in ("ray", "lost-node", "stopped"):
        result = report.get(name)
        if result is not None and result["exit_status"] == 0:
            rows = trained_rows(Path(result["out"]) / "table.json")
            result["rows_equal_local"] = rows == reference
            result["rows_differing"] = [
                f"{density} {row.get('label')}"
                for density, part in reference.items()
                for row in part["rows"]
                if row not in rows.get(density, {}).get("rows", [])
            ]


def print_figures(report: dict[str, Any]) -> None:
    print(f"overtake-experiment {report['experiment']}")
    if "local" in report:
        print(f"  local processes: the table in {report['local']['seconds']:.0f} s")
    if "cluster_up_s" in report:
        print(f"  Ray cluster up in {report['cluster_up_s']:.0f} s")
    for name in ("ray", "lost-node", "stopped"):
        result = report.get(name)
        if result is None:
            continue
        stop = result.get("stopped")
        if stop:
            print(
                f"  stopped by SIGTERM in {stop['stop_s']:.0f} s (exit {stop['exit_status']}, "
                f"{len(stop['processes_left'])} processes left, runs at steps "
                f"{sorted(set(stop['steps'].values()))}): {stop['last_line']}"
            )
        equal = result.get("rows_equal_local")
        said = {True: "equal the local table's", False: "DIFFER", None: "not compared"}[equal]
        print(
            f"  {name}: exit {result['exit_status']}, the table in {result['seconds']:.0f} s, "
            f"{result['tasks_retried']} task(s) retried, trained rows {said}"
        )
        lost = result.get("lost")
        if lost:
            print(
                f"    node {lost['node']} lost with its batch of {len(lost['runs'])} runs at "
                f"checkpoint step {lost['checkpoint_step']:,}; started again once a CPU was "
                f"free: {lost.get('retry_waited_for_a_cpu')}"
            )
            for line in result["retries"]:
                print(f"    {line}")
            for run, resumed in (lost.get("resumed") or {}).items():
                exactly = "exactly" if resumed["exactly"] else "NOT exactly"
                print(f"    {run}: lives from steps {resumed['from_steps']}, resumed {exactly}")
    for kind, result in (report.get("refused") or {}).items():
        print(f"  refused ({kind}) in {result['seconds']:.0f} s: {result['last_line']}")


if __name__ == "__main__":
    main(tyro.cli(ClusterBenchConfig))
