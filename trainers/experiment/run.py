"""The experiment's run: every training run and evaluation scheduled at most ``jobs`` at once,
what a process of an earlier invocation holds or has finished skipped."""

from __future__ import annotations

import dataclasses
import json
import os
import typing
from pathlib import Path
from typing import Any

from overtake.client.episodes.scenario import Scenario, Where

from ..evaluate import EvalConfig
from ..run.checkpoint import CHECKPOINT_NAME
from .catalogue import Density
from .files import LOCK_NAME, checkpoint_step, lock_all, read_json, say, write_atomic
from .launcher import Launcher, where_said
from .plan import (
    ExperimentConfig,
    Plan,
    RunPlan,
    eval_command,
    member_batch_command,
    member_batches,
    train_command,
)
from .processes import POLL_S, Task, TaskEnded, TaskStarted, TrainingProgress


class ExperimentRun:
    """One invocation of an experiment in its directory: trains what is not trained, evaluates
    what is not cached, then writes the table and the curves."""

    def __init__(self, config: ExperimentConfig, plan: Plan) -> None:
        self.config, self.plan = config, plan
        self.trained: list[str] = []
        self.evaluated: list[str] = []
        self.failed: list[str] = []
        self.retried: list[str] = []
        """the tasks started again after their node was lost (a line each, on a cluster)"""

    # The tasks --------------------------------------------------------------------------------

    def eval_tasks_of_run(self, run: RunPlan, step: int) -> list[Task]:
        checkpoint = run.run_dir / CHECKPOINT_NAME
        return [
            self._eval_task(
                f"{run.name}@{step} {density}",
                EvalConfig(checkpoint=checkpoint, name=run.row.label),
                density,
                self.plan.out / "evaluations" / run.name / f"{density}-step{step}.json",
                {"run": run.name, "checkpoint_step": step},
            )
            for density in self.plan.densities
        ]

    def reference_tasks(self) -> list[Task]:
        return [
            self._eval_task(
                f"{policy} {density}",
                # A name reference_policies() found among EvalConfig's, checked in make_plan.
                EvalConfig(
                    policy=typing.cast(Any, policy),
                    scenario=Scenario(preset=self.plan.experiment.preset),
                ),
                density,
                self.plan.out / "evaluations" / f"reference-{policy}" / f"{density}.json",
                {"policy": policy, "preset": self.plan.experiment.preset},
            )
            for policy in self.plan.references
            for density in self.plan.densities
        ]

    def _eval_task(
        self, name: str, base: EvalConfig, density: Density, cache: Path, key: dict[str, Any]
    ) -> Task:
        config = self.config
        evaluation = dataclasses.replace(
            base,
            episodes=self.plan.eval_episodes,
            seed=config.eval_seed,
            scenario=dataclasses.replace(
                base.scenario,
                traffic=density,
                set=config.set,
                max_decisions=config.eval_max_decisions,
            ),
            where=config.where,
            json_out=cache.with_name(cache.name + ".out"),
            # Every episode kept, for overtake-replay (the table names those with collisions).
            episodes_out=cache.with_name(cache.stem + ".episodes"),
        )
        if base.policy == "planner":
            # The planner reads the simulator's true state: it drives an in-process copy of
            # the same preset and overrides even when the rows train on a server.
            evaluation = dataclasses.replace(evaluation, where=Where())
        full_key = {
            **key,
            "density": density,
            "episodes": self.plan.eval_episodes,
            "seed": config.eval_seed,
            "max_decisions": config.eval_max_decisions,
            "set": list(config.set),
        }
        return Task(
            kind="eval",
            name=name,
            command=tuple(eval_command(evaluation)),
            lock_paths=(cache.with_name(cache.name + ".lock"),),
            log_path=cache.with_suffix(".log"),
            pid_file=cache.with_suffix(".pid"),
            cache=cache,
            key=full_key,
            cpus=self.plan.torch_threads,
        )

    def train_task(self, runs: tuple[RunPlan, ...]) -> Task:
        """Training ``runs``: one run's ``overtake-train``, or several as members of one
        learner in one process (:mod:`..member_batch`), whose log and pid file are the first
        run's."""
        first = runs[0]
        command = (
            train_command(first.train)
            if len(runs) == 1
            else member_batch_command([run.train for run in runs])
        )
        return Task(
            kind="train",
            name=" + ".join(run.name for run in runs),
            command=tuple(command),
            lock_paths=tuple(run.run_dir / LOCK_NAME for run in runs),
            log_path=first.run_dir / "train.log",
            pid_file=first.run_dir / "train.pid",
            runs=runs,
            cpus=self.plan.torch_threads,
            gpus=1 if self.config.device.startswith("cuda") else 0,
        )

    def cached(self, task: Task) -> dict[str, Any] | None:
        """The cached result of an evaluation made with the task's settings, or None."""
        assert task.cache is not None
        entry = read_json(task.cache)
        if isinstance(entry, dict) and entry.get("key") == task.key:
            return entry.get("result")
        return None

    # Scheduling -----------------------------------------------------------------------------

    def run(self, launcher: Launcher) -> None:
        """Train and evaluate what is missing, the tasks run by ``launcher``; returns when
        every task has ended (a failed one is in :attr:`failed`), or raises, every task
        stopped (Ctrl-C, SIGTERM, a directory a cluster node cannot use)."""
        plan = self.plan
        steps = {run.name: checkpoint_step(run.run_dir) for run in plan.runs}
        training = [run for run in plan.runs if (steps[run.name] or 0) < plan.total_steps]
        pending: list[Task] = [
            self.train_task(batch) for batch in member_batches(training, plan.jobs, plan.members)
        ]
        evaluations = self.reference_tasks()
        for run in plan.runs:
            step = steps[run.name]
            if step is not None and step >= plan.total_steps:
                evaluations += self.eval_tasks_of_run(run, step)
        pending += [task for task in evaluations if self.cached(task) is None]
        done_before = len(plan.runs) - len(training)
        say(
            f"{plan.experiment.name} in {plan.out}: {len(plan.runs)} training runs "
            f"({done_before} already at {plan.total_steps:,} steps), {len(pending)} "
            f"{'Ray tasks' if plan.cluster else 'processes'} to run, {plan.jobs} at a time, "
            f"{plan.torch_threads} PyTorch thread(s) each"
            + (
                f", training runs {plan.members or 'spread over --jobs'} to a process"
                if training
                else ""
            )
        )
        try:
            while pending or launcher.running():
                self._start_ready(pending, launcher)
                # Where nothing runs, every pending task is locked by a process of an earlier
                # invocation: this waits a while before trying again.
                for event in launcher.wait(POLL_S):
                    if isinstance(event, TaskStarted):
                        self._started(event)
                    elif isinstance(event, TrainingProgress):
                        say(
                            f"train {event.run}: step {event.step:,} of "
                            f"{plan.total_steps:,}, {event.steps_per_s:.0f} steps/s"
                        )
                    else:
                        pending += self._finished(event)
        finally:
            launcher.stop_all()

    def _start_ready(self, pending: list[Task], launcher: Launcher) -> None:
        """Start pending tasks, training first (the longest), while fewer than --jobs run."""
        for task in sorted(pending, key=lambda t: t.kind != "train"):
            if launcher.running() >= self.plan.jobs:
                return
            fds = lock_all(task.lock_paths)
            if fds is None:
                continue  # a process of an earlier invocation still holds one
            if self._done_meanwhile(task, pending):
                for fd in fds:
                    os.close(fd)
                continue
            pending.remove(task)
            launcher.start(task, fds)

    def _started(self, event: TaskStarted) -> None:
        task, where = event.task, where_said(event.node)
        if event.attempt:
            retries = self.plan.cluster.retries if self.plan.cluster is not None else 0
            line = f"retry {event.attempt} of {retries}"
            self.retried.append(f"{task.kind} {task.name}: {line}{where}")
            again = f" again{where} ({line}: the node or worker it ran on was lost)"
        else:
            again = where
        for run, step in zip(task.runs, event.from_steps, strict=True):
            start = f"from step {step:,}" if step else "from scratch"
            say(f"train {run.name}: starts {start}{again} (log {task.log_path})")
        if not task.runs:
            say(f"evaluate {task.name}{again}")

    def _done_meanwhile(self, task: Task, pending: list[Task]) -> bool:
        """Whether a process of an earlier invocation in the same directory (one that held
        the task's lock while this one planned: a child that outlived its killed experiment,
        where the system does not end it with its parent) has done ``task`` since; if so, drop
        it from ``pending`` and add what it makes ready, instead of repeating it. Two
        invocations do not run side by side: the command holds the directory's lock while it
        runs."""
        if task.runs:
            steps = [checkpoint_step(run.run_dir) or 0 for run in task.runs]
            if min(steps) < self.plan.total_steps:
                return False
            say(f"train {task.name}: done at step {min(steps):,} by another invocation")
            pending.remove(task)
            for run, step in zip(task.runs, steps, strict=True):
                pending += [t for t in self.eval_tasks_of_run(run, step) if self.cached(t) is None]
            return True
        if self.cached(task) is None:
            return False
        say(f"evaluate {task.name}: done by another invocation")
        pending.remove(task)
        return True

    def _finished(self, ended: TaskEnded) -> list[Task]:
        """Handle a task that ended; returns the tasks it makes ready (a finished run's
        evaluations)."""
        task, code = ended.task, ended.exit_status
        if ended.failure is not None:
            self.failed.append(f"{task.kind} {task.name} ({ended.failure}, log {task.log_path})")
            say(f"{task.kind} {task.name}: FAILED: {ended.failure}, see {task.log_path}")
            return []
        if code != 0:
            self.failed.append(f"{task.kind} {task.name} (exit status {code}, log {task.log_path})")
            say(f"{task.kind} {task.name}: FAILED with exit status {code}, see {task.log_path}")
            return []
        if task.runs:
            ready: list[Task] = []
            for run in task.runs:
                step = checkpoint_step(run.run_dir) or 0
                if step < self.plan.total_steps:
                    self.failed.append(
                        f"train {run.name} ended at step {step:,} of {self.plan.total_steps:,} "
                        f"(log {task.log_path})"
                    )
                    continue
                self.trained.append(run.name)
                say(f"train {run.name}: done at step {step:,}")
                ready += [t for t in self.eval_tasks_of_run(run, step) if self.cached(t) is None]
            return ready
        assert task.cache is not None
        result = read_json(task.json_out)
        if not isinstance(result, dict):
            self.failed.append(f"evaluate {task.name}: no result in {task.json_out}")
            return []
        write_atomic(task.cache, json.dumps({"key": task.key, "result": result}, indent=1))
        task.json_out.unlink()
        self.evaluated.append(task.name)
        speed = result["summary"]["avg_speed_kmh"]["mean"]
        say(f"evaluate {task.name}: done ({speed:.1f} km/h)")
        return []
