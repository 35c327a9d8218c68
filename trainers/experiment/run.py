"""The experiment's run: every training run and evaluation scheduled at most ``jobs`` at once,
what a process of an earlier invocation holds or has finished skipped."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
import typing
from pathlib import Path
from typing import Any

from overtake.client.episodes.scenario import Scenario, Where

from ..checkpoint import CHECKPOINT_NAME
from ..evaluate import EvalConfig
from .catalogue import Density
from .files import LOCK_NAME, checkpoint_step, lock, note_life, read_json, say, write_atomic
from .plan import (
    ExperimentConfig,
    Plan,
    RunPlan,
    eval_command,
    member_batch_command,
    member_batches,
    train_command,
)
from .processes import POLL_S, Child, Task, release, start_process, stop_all, wait_any


class ExperimentRun:
    """One invocation of an experiment in its directory: trains what is not trained, evaluates
    what is not cached, then writes the table and the curves."""

    def __init__(self, config: ExperimentConfig, plan: Plan) -> None:
        self.config, self.plan = config, plan
        self.trained: list[str] = []
        self.evaluated: list[str] = []
        self.failed: list[str] = []

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
        )

    def cached(self, task: Task) -> dict[str, Any] | None:
        """The cached result of an evaluation made with the task's settings, or None."""
        assert task.cache is not None
        entry = read_json(task.cache)
        if isinstance(entry, dict) and entry.get("key") == task.key:
            return entry.get("result")
        return None

    # Scheduling -----------------------------------------------------------------------------

    def run(self) -> None:
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
            f"processes to run, {plan.jobs} at a time, {plan.torch_threads} PyTorch "
            "thread(s) each"
            + (
                f", training runs {plan.members or 'spread over --jobs'} to a process"
                if training
                else ""
            )
        )
        running: list[Child] = []
        next_progress = time.monotonic() + self.config.progress_every_s
        try:
            while pending or running:
                self._start_ready(pending, running)
                if not running:
                    # Every pending task is locked by a process of an earlier invocation.
                    wait_any([], POLL_S)
                    continue
                wait_any(running, POLL_S)
                for child in [c for c in running if c.process.poll() is not None]:
                    running.remove(child)
                    release(child)
                    pending += self._finished(child)
                if time.monotonic() >= next_progress:
                    self._report_progress(running)
                    next_progress = time.monotonic() + self.config.progress_every_s
        finally:
            stop_all(running)

    def _start_ready(self, pending: list[Task], running: list[Child]) -> None:
        """Start pending tasks, training first (the longest), while fewer than --jobs run."""
        for task in sorted(pending, key=lambda t: t.kind != "train"):
            if len(running) >= self.plan.jobs:
                return
            fds = lock_all(task.lock_paths)
            if fds is None:
                continue  # a process of an earlier invocation still holds one
            if self._done_meanwhile(task, pending):
                for fd in fds:
                    os.close(fd)
                continue
            for run in task.runs:
                step = checkpoint_step(run.run_dir)
                note_life(run.run_dir, step or 0)
                where = f"from step {step:,}" if step else "from scratch"
                say(f"train {run.name}: starts {where} (log {task.log_path})")
            if not task.runs:
                say(f"evaluate {task.name}")
            pending.remove(task)
            running.append(start_process(task, fds, self.plan.torch_threads))

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

    def _finished(self, child: Child) -> list[Task]:
        """Handle a child that ended; returns the tasks it makes ready (a finished run's
        evaluations)."""
        task, code = child.task, child.process.returncode
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

    def _report_progress(self, running: list[Child]) -> None:
        for child in running:
            for run in child.task.runs:
                last = _last_train_record(run.run_dir / "metrics.jsonl")
                if last is not None:
                    say(
                        f"train {run.name}: step {last['step']:,} of {self.plan.total_steps:,}, "
                        f"{last['steps_per_s']:.0f} steps/s"
                    )


def lock_all(paths: tuple[Path, ...]) -> tuple[int, ...] | None:
    """Descriptors holding the locks of every path, or None (and none held) where another
    process holds one of them."""
    fds: list[int] = []
    for path in paths:
        fd = lock(path)
        if fd is None:
            for held in fds:
                os.close(held)
            return None
        fds.append(fd)
    return tuple(fds)


def _last_train_record(path: Path) -> dict[str, Any] | None:
    """The last ``train`` record among the last 64 kB of a metrics.jsonl."""
    try:
        with open(path, "rb") as handle:
            handle.seek(max(0, path.stat().st_size - 65_536))
            lines = handle.read().splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        with contextlib.suppress(ValueError):
            record = json.loads(line)
            if isinstance(record, dict) and record.get("kind") == "train":
                return record
    return None
