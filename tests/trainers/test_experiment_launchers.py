"""overtake-experiment's launcher seam without a cluster: ``--ray`` read and checked (without
Ray where it is missing: the extra to install), the local launcher's events, what the
scheduler makes of a launcher's events (a start again elsewhere, a task lost for good), and
the check of an experiment directory a node must see and write. The Ray launcher itself runs
on a local cluster in tests/e2e/test_experiment_ray.py (slow)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from overtake.cli import UsageError
from overtake.trainers.experiment import COMMAND, ExperimentRun, make_plan
from overtake.trainers.experiment import launcher as launcher_module
from overtake.trainers.experiment.files import (
    STORAGE_TOKEN_NAME,
    lock_all,
    storage_problem,
    write_storage_token,
)
from overtake.trainers.experiment.launcher import LocalLauncher, RayCluster, open_launcher
from overtake.trainers.experiment.processes import (
    LaunchEvent,
    Task,
    TaskEnded,
    TaskStarted,
    TrainingProgress,
)

from tests.support.remote import wait_until

SHORT = ["ho2018-table8", "--total-steps", "3000", "--references", "idle"]


def test_ray_alone_means_the_cluster_ray_finds_and_its_cpus_size_the_jobs(tmp_path):
    config = COMMAND.parse([*SHORT, "--out", "relative/exp", "--ray"])
    plan = make_plan(config, cores=3)
    assert plan.cluster == RayCluster(address="auto", retries=3)
    # A node's working directory is its own: the tasks are given absolute paths.
    assert plan.out == Path.cwd() / "relative" / "exp"
    assert all(run.run_dir.is_absolute() for run in plan.runs)
    assert (plan.jobs, plan.torch_threads) == (3, 1)
    config = COMMAND.parse([*SHORT, "--ray", "10.0.0.1:6379", "--ray-retries", "1"])
    assert make_plan(config).cluster == RayCluster(address="10.0.0.1:6379", retries=1)
    # Without --ray: this machine's processes, as before.
    plan = make_plan(COMMAND.parse([*SHORT, "--out", "relative/exp"]))
    assert plan.cluster is None and plan.out == Path("relative/exp")


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--ray", "a:1", "b:2"], r"--ray takes at most one address \(auto or the head's "
         r"HOST:PORT\), got a:1 b:2"),
        (["--ray", "ray://head:10001"], r"--ray ray://head:10001: expected auto or the head's "
         r"HOST:PORT; run overtake-experiment on a node of the cluster"),
        (["--device", "cuda:1", "--ray"], r"--device cuda:1: with --ray, Ray gives each "
         r"training task its GPU: give --device cuda"),
        (["--ray-retries", "-1", "--ray"], r"--ray-retries must be >= 0, got -1"),
        (["--ray", "head"], r"--ray head: expected auto or the head's HOST:PORT"),
    ],
)  # fmt: skip
def test_bad_ray_options_are_refused_in_one_line(args, expected):
    with pytest.raises(UsageError, match=expected):
        make_plan(COMMAND.parse([*SHORT, *args]))


def test_without_ray_installed_ray_names_the_extra_and_nothing_is_made(monkeypatch, tmp_path):
    monkeypatch.setattr(launcher_module, "ray_installed", lambda: False)
    out = tmp_path / "exp"
    with pytest.raises(SystemExit) as exit_info:
        COMMAND.run([*SHORT, "--out", str(out), "--ray"])
    assert exit_info.value.code == (
        "overtake-experiment: --ray needs Ray, which is not installed here: install "
        'overtake\'s cluster extra (pip install -e ".[cluster]")'
    )
    assert not out.exists()
    # The launcher, asked for directly, says the same where Ray cannot be imported.
    monkeypatch.setitem(sys.modules, "ray", None)
    monkeypatch.delitem(sys.modules, "overtake.trainers.experiment.ray_launcher", raising=False)
    with (
        pytest.raises(UsageError, match=r"cluster extra"),
        open_launcher(RayCluster("auto", 3), out, 1.0),
    ):
        pass


def a_task(tmp_path: Path, name: str, code: str) -> Task:
    return Task(
        kind="eval",
        name=name,
        command=(sys.executable, "-c", code),
        lock_paths=(tmp_path / f"{name}.lock",),
        log_path=tmp_path / f"{name}.log",
        pid_file=tmp_path / f"{name}.pid",
    )


def events_until_ended(launcher: LocalLauncher, count: int) -> list[LaunchEvent]:
    events: list[LaunchEvent] = []

    def ended() -> bool:
        events.extend(launcher.wait(0.1))
        return sum(isinstance(e, TaskEnded) for e in events) >= count

    wait_until(ended, 60, f"{count} tasks to end")
    return events


def test_the_local_launcher_says_each_start_and_end_and_holds_the_locks_meanwhile(tmp_path):
    launcher = LocalLauncher(progress_every_s=600)
    gate = tmp_path / "go"
    waits = a_task(
        tmp_path,
        "waits",
        f"import os, time\nwhile not os.path.exists({str(gate)!r}): time.sleep(0.01)",
    )
    fails = a_task(tmp_path, "fails", "raise SystemExit(3)")
    for task in (waits, fails):
        locks = lock_all(task.lock_paths)
        assert locks is not None
        launcher.start(task, locks)
    assert launcher.running() == 2
    [ended] = [e for e in events_until_ended(launcher, 1) if isinstance(e, TaskEnded)]
    assert ended == TaskEnded(fails, 3)
    # The task still running holds its lock (its process inherited it); the ended one's is
    # free again.
    assert lock_all(waits.lock_paths) is None
    free = lock_all(fails.lock_paths)
    assert free is not None
    os.close(free[0])
    with open(gate, "w"):
        pass
    events = events_until_ended(launcher, 1)
    assert TaskEnded(waits, 0) in events and launcher.running() == 0
    assert "overtake-experiment starts" in waits.log_path.read_text()
    assert not waits.pid_file.exists()


def test_the_scheduler_says_a_start_again_elsewhere_and_a_task_lost_for_good(tmp_path, capsys):
    config = COMMAND.parse([*SHORT, "--out", str(tmp_path / "exp"), "--ray", "h:1"])
    plan = make_plan(config, cores=3)
    experiment = ExperimentRun(config, plan)
    task = experiment.train_task(plan.runs[:2])
    assert (task.cpus, task.gpus) == (1, 0)
    experiment._started(TaskStarted(task, (0, 0), node="1a2b3c4d (10.0.0.2)"))
    experiment._started(TaskStarted(task, (1_050, 900), node="5e6f7a8b (10.0.0.3)", attempt=1))
    said = capsys.readouterr().err
    assert f"train {plan.runs[0].name}: starts from scratch on node 1a2b3c4d (10.0.0.2)" in said
    assert (
        f"train {plan.runs[0].name}: starts from step 1,050 again on node 5e6f7a8b (10.0.0.3) "
        "(retry 1 of 3: the node or worker it ran on was lost)"
    ) in said
    assert experiment.retried == [f"train {task.name}: retry 1 of 3 on node 5e6f7a8b (10.0.0.3)"]
    lost = "its node or worker was lost, and it has been retried 3 time(s) (--ray-retries)"
    assert experiment._finished(TaskEnded(task, None, failure=lost)) == []
    assert experiment.failed == [f"train {task.name} ({lost}, log {task.log_path})"]
    # A GPU for every training batch with --device cuda, none for an evaluation.
    config = COMMAND.parse([*SHORT, "--out", str(tmp_path / "exp"), "--ray", "--device", "cuda"])
    experiment = ExperimentRun(config, make_plan(config, cores=3))
    assert experiment.train_task(plan.runs[:1]).gpus == 1
    assert {task.gpus for task in experiment.reference_tasks()} == {0}


def test_progress_comes_from_the_runs_own_logs(tmp_path):
    config = COMMAND.parse([*SHORT, "--out", str(tmp_path / "exp")])
    plan = make_plan(config)
    task = ExperimentRun(config, plan).train_task(plan.runs[:1])
    run_dir = plan.runs[0].run_dir
    run_dir.mkdir(parents=True)
    (run_dir / "metrics.jsonl").write_text(
        '{"kind": "episode", "step": 90}\n{"kind": "train", "step": 100, "steps_per_s": 25.0}\n'
        '{"kind": "episode", "step": 120}\n{"kind": "train", "step": 2'
    )
    from overtake.trainers.experiment.processes import progress_of

    assert progress_of(task) == [TrainingProgress(plan.runs[0].name, 100, 25.0)]


def test_a_directory_is_usable_where_its_token_is_seen_and_files_can_be_written(tmp_path):
    out = tmp_path / "exp"
    out.mkdir()
    assert "does not see the experiment's files there" in storage_problem(out, "abc")
    token = write_storage_token(out)
    assert storage_problem(out, token) is None
    assert list(out.iterdir()) == [out / STORAGE_TOKEN_NAME]  # the probe cleaned up
    # A directory of the node's own at the same path, made by another experiment.
    assert storage_problem(out, "another") == (
        "sees another directory at that path (not the experiment's token)"
    )
    if os.geteuid() != 0:  # root writes where permissions say no
        out.chmod(0o555)
        try:
            assert storage_problem(out, token).startswith("cannot write there (Permission")
        finally:
            out.chmod(0o755)
