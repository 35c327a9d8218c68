"""``overtake-experiment``: the command that plans, runs and reports an experiment."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from overtake.cli import Command, UsageError

from ..config.train_config import TrainConfig
from .catalogue import ALGO_NAMES, EXPERIMENTS, INPUT_NAMES, Experiment, ExperimentError
from .evidence import keep_evidence
from .files import LOCK_NAME, PLAN_NAME, lock, read_json, say, write_atomic
from .launcher import open_launcher
from .plan import ExperimentConfig, Plan, learned_settings, make_plan, training_identity
from .report import Outputs
from .run import ExperimentRun


def describe_experiments() -> str:
    lines = []
    for experiment in EXPERIMENTS.values():
        lines += [
            f"{experiment.name}: {experiment.title}",
            f"  {experiment.total_steps:,} steps per run, preset {experiment.preset}, "
            f"evaluated at {', '.join(experiment.densities)} traffic beside "
            f"{', '.join(experiment.references)}; {hours_estimate(experiment)}",
        ]
        lines += [
            f"  {row.label}: {ALGO_NAMES[row.algo]}, {INPUT_NAMES[row.inputs]}, {row.seeds} seed(s)"
            for row in experiment.rows
        ]
    return "\n".join(lines)


def hours_estimate(experiment: Experiment, total_steps: int | None = None) -> str:
    """What the experiment takes, in words: the hours measured on the project's 2-core VM,
    scaled to ``total_steps`` where that replaces the experiment's budget."""
    hours = experiment.hours_on_two_cores
    scaled = ""
    if total_steps is not None and total_steps != experiment.total_steps:
        hours *= total_steps / experiment.total_steps
        scaled = f", scaled to {total_steps:,} steps"
    when = f"about {hours:.1f} hours" if hours >= 1 else f"about {hours * 60:.0f} minutes"
    return f"{when} on a 2-core machine{scaled}, less with more cores or a GPU"


def check_directory(plan: Plan) -> None:
    """Refuse a directory whose runs were trained with other settings than this plan's; record
    this plan's runs in experiment.json."""
    path = plan.out / PLAN_NAME
    stored = read_json(path) if path.exists() else {"runs": {}}
    if not isinstance(stored, dict) or not isinstance(stored.get("runs"), dict):
        raise UsageError(f"{path} is not an overtake-experiment record")
    if stored.get("experiment", plan.experiment.name) != plan.experiment.name:
        raise UsageError(
            f"{plan.out} holds experiment {stored['experiment']!r}, not "
            f"{plan.experiment.name!r}: choose another --out"
        )
    for run in plan.runs:
        before = stored["runs"].get(run.name)
        if before is not None:
            before = learned_settings(before)
        now = training_identity(run.train)
        if before is not None and before != now:
            # A setting added to the trainer since the directory was recorded, at its default
            # (what the trainer did before the setting existed), is no difference.
            default = training_identity(TrainConfig.for_preset(run.train.preset, run.train.recipe))
            differ = sorted(_differences(before, now, added_at=default))
            if not differ:
                stored["runs"][run.name] = now
                continue
            raise UsageError(
                f"{run.run_dir} was trained with other settings ({', '.join(differ)}) than "
                "this invocation asks for: give the same options as before, or choose "
                "another --out"
            )
        stored["runs"][run.name] = now
    stored["experiment"] = plan.experiment.name
    write_atomic(path, json.dumps(stored, indent=1))


def _differences(
    before: dict[str, Any], now: dict[str, Any], prefix: str = "", added_at: Any = None
) -> Iterator[str]:
    """The settings that differ, named; one ``before`` lacks is none if ``now`` holds it at
    its value in ``added_at`` (the defaults)."""
    defaults = added_at if isinstance(added_at, dict) else {}
    for name in before.keys() | now.keys():
        a, b = before.get(name), now.get(name)
        if isinstance(a, dict) and isinstance(b, dict):
            yield from _differences(a, b, f"{prefix}{name}.", defaults.get(name))
        elif name not in before and name in defaults and b == defaults[name]:
            continue
        elif a != b:
            yield f"{prefix}{name} {a!r} then, {b!r} now"


def main(config: ExperimentConfig) -> dict[str, Any]:
    """Run the experiment ``config`` names (or continue it); returns what it did and where the
    outputs are. Raises UsageError for bad options, ExperimentError when a part failed (what
    succeeded is kept: running it again retries only what failed)."""
    if config.list_experiments or config.experiment is None:
        # Hours start only when asked for by name: without one, what there is to run.
        text = describe_experiments()
        print(text)
        if config.experiment is None:
            print("\nname one to run it, e.g. overtake-experiment fayjie2018-fig6")
        return {"experiments": text}
    plan = make_plan(config)
    say(f"{plan.experiment.name}: {hours_estimate(plan.experiment, config.total_steps)}")
    plan.out.mkdir(parents=True, exist_ok=True)
    experiment_lock = lock(plan.out / LOCK_NAME)
    if experiment_lock is None:
        raise ExperimentError(f"another overtake-experiment is running in {plan.out}")
    try:
        with open_launcher(plan.cluster, plan.out, config.progress_every_s) as launcher:
            if plan.cluster is not None:
                # --jobs and --torch-threads default from the cluster's CPUs.
                plan = make_plan(config, cores=launcher.cores)
            check_directory(plan)
            experiment_run = ExperimentRun(config, plan)
            experiment_run.run(launcher)
        if experiment_run.failed:
            raise ExperimentError(
                "these parts failed (run the same command again to retry them): "
                + "; ".join(experiment_run.failed)
            )
        Outputs(config, plan, experiment_run).write()
        if config.keep is not None:
            keep_evidence(plan.out, config.keep)
    finally:
        os.close(experiment_lock)
    table = plan.out / "table.md"
    say(f"wrote {table}, table.json, curves.png and curves.rrd in {plan.out}")
    return {
        "out": str(plan.out),
        "trained": experiment_run.trained,
        "evaluated": experiment_run.evaluated,
        "retried": experiment_run.retried,
        "table_md": str(table),
        "table_json": str(plan.out / "table.json"),
        "curves_png": str(plan.out / "curves.png"),
        "curves_rrd": str(plan.out / "curves.rrd"),
    }


def _report(_config: ExperimentConfig, summary: dict[str, Any]) -> None:
    if "table_md" in summary:
        print(Path(summary["table_md"]).read_text(encoding="utf-8"))


# SIGTERM (a container stopping, `kill`) stops the children as Ctrl-C does.
COMMAND = Command(
    "overtake-experiment",
    ExperimentConfig,
    main,
    report=_report,
    stopping="interrupt",
    stopped_hint="run the same command again to continue",
)


if __name__ == "__main__":
    COMMAND.run()
