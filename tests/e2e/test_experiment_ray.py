"""overtake-experiment on a Ray cluster (issue 69): three local nodes of one CPU each
(``ray.cluster_utils.Cluster``) in a network namespace of their own, where Ray binds
127.0.0.1, run the issue's short ``ho2018-table8`` to the same table as this machine's
processes; also with a worker node lost while it trains, and after a stop and a second
invocation; a directory the nodes cannot write, or do not see, is refused before anything
trains. The scenarios are bench/reliability/experiment_cluster.py's, run once for the module;
its figures are in docs/cluster.md and bench/RESULTS.md."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.support.remote import child_env

ROOT = Path(__file__).resolve().parents[2]
NAMESPACES = ["unshare", "--user", "--map-root-user", "--net", "--mount", "true"]
# Four tables (each a few minutes on 2 cores), two refusals, a cluster's start: about half an
# hour on 2 cores beside other work, far past the default suite's budget.
pytestmark = [pytest.mark.slow, pytest.mark.timeout(3 * 3600)]


def namespaces_refused() -> str | None:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "needs unshare and ip (util-linux, iproute2)"
    probe = subprocess.run(NAMESPACES, capture_output=True, text=True)
    return None if probe.returncode == 0 else f"no user namespaces here: {probe.stderr.strip()}"


@pytest.fixture(scope="module")
def figures(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    # Here, not at collection: the default suite, which leaves these tests out, loads no Ray.
    pytest.importorskip("ray", reason="Ray is not installed (the cluster extra)")
    refused = namespaces_refused()
    if refused is not None:
        pytest.skip(refused)
    work = tmp_path_factory.mktemp("cluster")
    report = work / "figures.json"
    done = subprocess.run(
        [sys.executable, "-m", "bench.reliability.experiment_cluster"]
        + ["--work-dir", str(work / "experiments"), "--json", str(report)],
        capture_output=True,
        text=True,
        timeout=3 * 3600 - 300,
        cwd=ROOT,
        env=child_env(),
    )
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    return json.loads(report.read_text())


def test_the_ray_table_equals_the_local_one(figures):
    assert figures["local"]["exit_status"] == 0, figures["local"]["last_line"]
    ray = figures["ray"]
    assert ray["exit_status"] == 0, ray["last_line"]
    assert ray["retries"] == [] and ray["tasks_retried"] == 0
    assert ray["rows_equal_local"], ray["rows_differing"]


def test_a_lost_node_s_batch_resumes_exactly_elsewhere_to_the_same_table(figures):
    lost = figures["lost-node"]
    assert lost["exit_status"] == 0, lost["last_line"]
    assert lost["lost"], "no worker node ran a training batch"
    # Started again on another node (the loss of the worker, then of the node, may cost a
    # retry each), within the bounded retries, once a CPU was free there: a task never gives
    # its CPU back to Ray while it runs.
    assert 1 <= lost["tasks_retried"] <= 3, lost["retries"]
    assert all(f"on node {lost['lost']['node']}" not in line for line in lost["retries"])
    assert lost["lost"]["retry_waited_for_a_cpu"], lost["retries"]
    for run, resumed in lost["lost"]["resumed"].items():
        assert resumed["resumed_from_the_checkpoint"], (run, resumed)
        assert resumed["exactly"], (run, resumed)
    assert lost["rows_equal_local"], lost["rows_differing"]


def test_a_stopped_experiment_leaves_nothing_running_and_resumes_to_the_same_table(figures):
    result = figures["stopped"]
    stop = result["stopped"]
    assert stop, "the experiment ended before it could be stopped"
    assert stop["exit_status"] == 1
    assert stop["last_line"] == (
        "overtake-experiment: stopped; run the same command again to continue"
    )
    assert stop["processes_left"] == [] and stop["pid_files_left"] == 0
    assert any(step > 0 for step in stop["steps"].values())
    assert result["exit_status"] == 0, result["last_line"]
    assert result["rows_equal_local"], result["rows_differing"]


@pytest.mark.parametrize(
    ("kind", "problem"),
    [
        ("read-only", r"cannot write there \(Read-only file system\)"),
        ("unseen", r"does not see the experiment's files there \(no \.storage-token\)"),
    ],
)
def test_a_directory_the_nodes_cannot_use_is_refused_before_anything_trains(figures, kind, problem):
    result = figures["refused"][kind]
    assert result["exit_status"] == 1
    assert re.fullmatch(
        rf"overtake-experiment: --out \S+: node [0-9a-f]{{8}} \(127\.0\.0\.1\) {problem}"
        r"( \(and \d more of its nodes\))?: with --ray the experiment directory must be "
        r"storage every node sees and may write, at the same path \(a shared filesystem; "
        r"docs/cluster\.md\); nothing was trained",
        result["last_line"],
    ), result["last_line"]
    assert result["train_logs"] == []
