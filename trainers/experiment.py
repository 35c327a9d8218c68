"""``overtake-experiment``: a paper's table reproduced by one resumable command.

An experiment is data (:data:`EXPERIMENTS`): the table's rows (an algorithm on some inputs,
trained from one or more seeds), the step budget and the training settings scaled to it, the
traffic densities it is evaluated at and the reference policies evaluated beside the rows.
``overtake-experiment min2018-table3`` then

1. trains every row's runs, each as its own ``overtake-train`` process (a crash of one leaves
   the others running) with ``--resume-if-found``, at most ``--jobs`` at once;
2. evaluates every run's final checkpoint and every reference policy with ``overtake-eval``,
   greedily, on the same fixed episode seeds at each density;
3. writes the table (``table.md``, ``table.json``) and the learning curves (``curves.png``,
   ``curves.rrd``) into the experiment directory.

Everything is resumable: the experiment may be killed at any moment and started again with the
same command. A run whose checkpoint has reached the budget is not trained again, an unfinished
one continues from its last checkpoint, and each evaluation is cached per (run and checkpoint
step, or reference policy; density) with the settings it was made with. Training and
evaluation processes die with the experiment (Linux), and each holds a lock on its run
directory while it lives, so a restarted experiment never runs a second trainer beside an
earlier one still stopping.

The experiment directory (default ``runs/experiments/<name>``) holds:

- ``experiment.json``: every run's training configuration; a later invocation that would
  train a run differently is refused (choose another ``--out``);
- ``<row>-seed<k>/``: an ``overtake-train`` run directory, plus ``train.log`` (the process's
  output) and ``experiment-lives.jsonl`` (where each life of the run started in its
  ``metrics.jsonl``, so the curves leave out the episodes a resume redid);
- ``evaluations/<run>/<density>-step<N>.json`` and ``evaluations/reference-<policy>/
  <density>.json``: the cached ``overtake-eval`` results, with their logs;
- ``table.md``, ``table.json``, ``curves.png``, ``curves.rrd``.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import fcntl
import itertools
import json
import math
import os
import select
import signal
import subprocess
import sys
import time
import typing
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import tyro

from overtake.client.commands import UsageError, run_command
from overtake.protocol.transport import SecurityConfig
from overtake.protocol.vocabulary import METRIC_FIELDS
from overtake.viz.recording import RecordingConfig, close_recording, open_recording

from .checkpoint import CHECKPOINT_NAME, load_checkpoint, plain_data
from .evaluate import EvalConfig
from .learner import Algo
from .network import Inputs
from .train import TrainConfig, git_commit, package_versions

Density = Literal["light", "medium", "heavy"]

ALGO_NAMES = {"dqn": "DQN", "ddqn": "Double DQN", "dueling": "Dueling DQN"}
INPUT_NAMES = {
    "both": "camera + LIDAR",
    "camera": "camera",
    "lidar": "LIDAR",
    "grid": "occupancy grid + actions",
    "camera-map": "camera + LIDAR map",
}

# The table's columns: (metric, heading, decimals). Collisions per 1,000 decisions is each
# episode's own rate, so that it has a spread like the others.
TABLE_COLUMNS: tuple[tuple[str, str, int], ...] = (
    ("avg_speed_kmh", "average speed km/h", 1),
    ("lane_changes", "lane changes", 1),
    ("overtakes", "overtakes", 1),
    ("collisions_per_1000_decisions", "collisions / 1,000 decisions", 2),
    ("emergency_brakes", "emergency brakes", 2),
    ("return", "return", 1),
)
EPISODE_METRICS = (*METRIC_FIELDS, "collisions_per_1000_decisions")
CURVE_METRICS: tuple[tuple[str, str], ...] = (
    ("avg_speed_kmh", "average speed km/h"),
    ("return", "return per episode"),
)

LIVES_NAME = "experiment-lives.jsonl"
PLAN_NAME = "experiment.json"
LOCK_NAME = ".lock"
# How often the scheduler wakes without a child ending (it prints the runs' progress every
# --progress-every-s).
POLL_S = 1.0
STOP_TIMEOUT_S = 30.0


class ExperimentError(ValueError):
    """A part of the experiment failed (a training run or an evaluation exited with an error,
    or another experiment holds the directory); the message names the part and its log. A
    ``ValueError``, so that :func:`run_command` reports it as the command's message: the
    experiment itself did what it should, and running it again retries what failed."""


@dataclass(frozen=True)
class Row:
    """One row of a table: an algorithm on some inputs, trained from ``seeds`` seeds (0, 1, ...)
    whose evaluation episodes are pooled."""

    label: str
    """the row's name in the table and its runs' directories (``<label>-seed<k>``)"""
    algo: Algo
    inputs: Inputs
    seeds: int = 1
    network: Literal["multimodal", "baseline", "proposed"] | None = None
    """None keeps the preset's network"""
    learning_rate: float | None = None
    """None keeps the preset's"""


@dataclass(frozen=True)
class Experiment:
    """A table to reproduce: its rows, budget, training settings, densities and references."""

    name: str
    title: str
    rows: tuple[Row, ...]
    preset: str
    total_steps: int
    """environment steps per training run"""
    num_envs: int
    """environments each training run steps together"""
    densities: tuple[Density, ...]
    """traffic densities every row and reference policy is evaluated at"""
    references: tuple[str, ...]
    """``overtake-eval --policy`` names evaluated beside the rows"""
    eval_episodes: int
    train_traffic: Density | None = None
    """traffic of the training runs; None keeps the preset's"""
    paper: str = ""
    """the paper's own table (Markdown), quoted under ours in table.md"""
    scale_schedule: bool = True
    """scale the paper's settings to the budget (Schedule.for_budget); False keeps the
    preset's own learning start, epsilon decay, target period and replay (a paper that trained
    about as long as the budget); checkpoints are scaled either way"""
    reward_window_steps: int | None = None
    """also plot the training reward summed over windows of this many steps (the runs log a
    training line at each)"""
    note: str = ""
    """what a reader of the table and curves must know (Markdown), written under the tables"""


@dataclass(frozen=True)
class Schedule:
    """The training settings that depend on the budget (the rest are TrainConfig's and
    DQNConfig's defaults, the paper's)."""

    learning_starts: int
    epsilon_decay_steps: int
    target_update_steps: int
    replay_size: int
    checkpoint_every: int

    @classmethod
    def for_budget(cls, total_steps: int) -> Schedule:
        """Min et al.'s settings (DQNConfig's defaults, made for 1,000,000 steps) scaled to
        ``total_steps``:

        - learning starts after 5% of the budget (the paper: 50,000 of 1,000,000), at most the
          paper's 50,000;
        - epsilon falls from 1 to 0.1 over the first third of the budget. The paper decays over
          its whole budget; at a fifth of it that leaves too little training near the final
          epsilon, and a third is what met the bar in bench/RESULTS.md (20,000 of 60,000);
        - the target network is copied every 1% of the budget (the paper: 10,000 of
          1,000,000), at most 10,000 steps apart;
        - the replay holds half the budget, at most the paper's 100,000 transitions (0.85 GB
          with both inputs): a run never stores more than its budget, and half kept 30,000 of
          60,000 in bench/RESULTS.md;
        - a checkpoint every 5% of the budget, at most 10,000 steps apart: a kill loses at most
          that much training (a few minutes of a run on 2 cores).
        """
        return cls(
            learning_starts=min(50_000, total_steps // 20),
            epsilon_decay_steps=max(1, total_steps // 3),
            target_update_steps=max(1, min(10_000, total_steps // 100)),
            replay_size=max(1, min(100_000, total_steps // 2)),
            checkpoint_every=max(1, min(10_000, total_steps // 20)),
        )


EXPERIMENTS: dict[str, Experiment] = {
    "min2018-table3": Experiment(
        name="min2018-table3",
        title="Min et al. (2018), Table III: Double + Dueling DQN with camera and LIDAR, the "
        "camera alone and the LIDAR alone (two seeds each), and DQN and Double DQN with both",
        rows=(
            # The algorithm comparison on both sensors ...
            Row("dqn-both", "dqn", "both"),
            Row("ddqn-both", "ddqn", "both"),
            # ... and the sensor ablation of Table III with the paper's algorithm (§IV: Double
            # and Dueling DQN "are combined", as the authors' code runs them), two seeds each:
            # its order is judged against the seed spread. dueling-both is in both.
            Row("dueling-both", "dueling", "both", seeds=2),
            Row("dueling-camera", "dueling", "camera", seeds=2),
            Row("dueling-lidar", "dueling", "lidar", seeds=2),
        ),
        preset="min2018",
        total_steps=200_000,
        # As in bench/RESULTS.md: four arenas step together (the simulation is batched, and
        # the cost of a step is the network's update, one per 4 transitions either way).
        num_envs=4,
        densities=("light", "medium", "heavy"),
        references=("rule", "random", "idle", "planner"),
        eval_episodes=50,
        paper=(
            "Min et al. (2018), Table III, 1,000,000 training steps: average speed 73.54 "
            "km/h (multi-input), 71.88 (camera only), 69.48 (LIDAR only); lane changes "
            "30.2 / 16.8 / 18.4; overtakes 42.2 / 35.8 / 32.2 per episode."
        ),
    ),
    "ho2018-table8": Experiment(
        name="ho2018-table8",
        title="Ho (2018), Table 8: the baseline network and the proposed network at four "
        "learning rates (Table 7), DQN with a target network on the occupancy grid",
        rows=(
            Row("baseline", "dqn", "grid", seeds=2, network="baseline"),
            *(
                Row(
                    f"proposed-lr{rate}",
                    "dqn",
                    "grid",
                    seeds=2,
                    network="proposed",
                    learning_rate=rate,
                )
                for rate in (0.0001, 0.00025, 0.0005, 0.00075)
            ),
        ),
        preset="ho2018",
        # His 2,000 episodes of 1,000 decisions (§6.1); --total-steps scales it down.
        total_steps=2_000_000,
        num_envs=4,
        # Table 6's schedule as it is (learning from 100,000 decisions, epsilon over
        # 2,000,000, a target copy every 10,000, replay 1,000,000): a smaller budget stops it
        # early rather than compressing it.
        scale_schedule=False,
        densities=("light", "medium", "heavy"),
        # The planner plans 6 s (75 of Ho's decisions) ahead: 200 episodes of it take hours
        # on 2 cores; add it with --references rule random idle planner.
        references=("rule", "random", "idle"),
        # §6.2: 200 evaluation episodes per traffic condition.
        eval_episodes=200,
        paper=(
            "Ho (2018), Table 8, 2,000 training episodes of 4,000 frames (average speed km/h "
            "and emergency brakes per episode, light / medium / heavy): baseline 71.98 / "
            "64.28 / 60.62 and 2.99 / 4.70 / 6.72; experiment 1 (lr 0.0001) 103.42 / 87.96 / "
            "72.94 and 8.56 / 22.67 / 23.92; experiment 2 (lr 0.00025) 102.64 / 86.39 / 72.76 "
            "and 7.98 / 20.96 / 22.71; experiment 3 (lr 0.0005) 98.87 / 85.64 / 71.10 and "
            "7.02 / 19.55 / 19.755; experiment 4 (lr 0.00075) 98.19 / 81.66 / 70.48 and "
            "6.73 / 16.705 / 19.68."
        ),
    ),
    "fayjie2018-fig6": Experiment(
        name="fayjie2018-fig6",
        title="Fayjie et al. (2018), Fig. 6: the reward per 3,000 training steps, DQN with the "
        "two-stream network on the camera and the LIDAR map",
        rows=(Row("dqn-camera-map", "dqn", "camera-map"),),
        preset="fayjie2018",
        total_steps=120_000,
        num_envs=4,
        densities=("medium",),
        references=("rule", "random", "idle"),
        eval_episodes=20,
        # Table I's settings as they are: the paper trained 100,000+ steps, this budget.
        scale_schedule=False,
        reward_window_steps=3_000,
        note=(
            "The curve's reward is the paper's (§III.B): keeping going earns the speed / 5 "
            "(m/s) every decision, more than any other action, so a driver that only keeps "
            "going (the idle reference) scores a high return without learning anything; "
            "read the learned row's return beside idle's, not alone."
        ),
        paper=(
            "Fayjie et al. (2018), Fig. 6: the cumulative reward per 3,000 steps over "
            '100,000+ training steps, "gradually increasing" (a plot; the paper gives no '
            "figures and no evaluation table)."
        ),
    ),
}


@dataclass(frozen=True)
class ExperimentConfig:
    """Reproduce a paper's table: train its rows (resumable, in parallel), evaluate them and
    the reference policies on fixed seeds at each traffic density, write the table and the
    learning curves. Run the same command again to continue after a kill."""

    experiment: Annotated[str, tyro.conf.Positional] = "min2018-table3"
    """the experiment to run (--list-experiments shows them)"""
    out: Path | None = None
    """the experiment directory; default runs/experiments/<experiment>"""
    jobs: int | None = None
    """processes (training runs or evaluations) at once; default the cores this process may
    use"""
    total_steps: int | None = None
    """environment steps per training run; None keeps the experiment's"""
    seeds: int | None = None
    """training seeds of every row; None keeps each row's"""
    rows: tuple[str, ...] = ()
    """only these rows (labels); default every row"""
    densities: tuple[Density, ...] | None = None
    """evaluation traffic densities; None keeps the experiment's"""
    references: tuple[str, ...] | None = None
    """reference policies (overtake-eval --policy) to evaluate beside the rows; None keeps the
    experiment's"""
    eval_episodes: int | None = None
    """evaluation episodes per policy and density; None keeps the experiment's"""
    eval_seed: int = 1_000
    """evaluation episode i uses seed eval_seed + i, for every policy and density"""
    eval_max_decisions: int | None = None
    """evaluation episode length in decisions; None keeps the preset's"""
    num_envs: int | None = None
    """environments per training run; None keeps the experiment's"""
    learning_starts: int | None = None
    """None: the experiment's schedule (scaled to the budget, Schedule.for_budget, or the
    preset's own where the experiment keeps it), as are the next four"""
    epsilon_decay_steps: int | None = None
    target_update_steps: int | None = None
    replay_size: int | None = None
    checkpoint_every: int | None = None
    reward_window_steps: int | None = None
    """the training reward's window, for an experiment that plots it (Fayjie et al.'s 3,000);
    None keeps the experiment's"""
    set: tuple[str, ...] = ()
    """simulator overrides (dotted.name=value) for training and evaluation alike"""
    connect: str | None = None
    """a simulator server's (or router's) Zenoh endpoint for training and evaluation; None runs
    the simulator in each process"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates for --connect"""
    torch_threads: int | None = None
    """PyTorch threads per process; default the cores divided by --jobs"""
    record_training: bool = False
    """each training run also records its Rerun trainer.rrd (about 6 MB per 10,000 steps)"""
    curve_bins: int = 40
    """learning curves: training episodes are averaged in this many equal bins of steps"""
    progress_every_s: float = 300.0
    """seconds between lines giving every running run's training step"""
    keep: Path | None = None
    """also copy table.md, table.json and curves.png into this directory (the evidence that is
    committed: bench/results/<experiment>)"""
    list_experiments: bool = False
    """print the experiments and their rows, and do nothing else"""


# --- the plan -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RunPlan:
    """One training run of a row."""

    row: Row
    seed: int
    run_dir: Path
    train: TrainConfig

    @property
    def name(self) -> str:
        return self.run_dir.name


@dataclass(frozen=True)
class Plan:
    """An experiment resolved against a configuration: what will be trained and evaluated."""

    experiment: Experiment
    out: Path
    jobs: int
    torch_threads: int
    rows: tuple[Row, ...]
    runs: tuple[RunPlan, ...]
    densities: tuple[Density, ...]
    references: tuple[str, ...]
    eval_episodes: int
    schedule: Schedule
    total_steps: int


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform tells it)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def reference_policies() -> tuple[str, ...]:
    """The ``--policy`` names ``overtake-eval`` accepts (read from EvalConfig, so new ones are
    known as soon as it has them)."""
    hint = typing.get_type_hints(EvalConfig)["policy"]
    return tuple(
        value
        for arg in typing.get_args(hint)
        if typing.get_origin(arg) is Literal
        for value in typing.get_args(arg)
    )


# The options that must be at least 1 where given.
_POSITIVE = (
    "jobs",
    "total_steps",
    "seeds",
    "eval_episodes",
    "eval_max_decisions",
    "num_envs",
    "epsilon_decay_steps",
    "target_update_steps",
    "replay_size",
    "checkpoint_every",
    "reward_window_steps",
    "torch_threads",
    "curve_bins",
)


def _at_least_one(name: str, value: int | None) -> None:
    if value is not None and value < 1:
        raise UsageError(f"--{name.replace('_', '-')} must be >= 1, got {value}")


def make_plan(config: ExperimentConfig) -> Plan:
    """The experiment ``config`` asks for, checked: every bad option is refused here, before
    anything is trained."""
    experiment = EXPERIMENTS.get(config.experiment)
    if experiment is None:
        raise UsageError(
            f"unknown experiment {config.experiment!r}: expected one of {', '.join(EXPERIMENTS)}"
        )
    if config.reward_window_steps is not None:
        if experiment.reward_window_steps is None:
            raise UsageError(
                f"--reward-window-steps: {experiment.name} plots no reward per window "
                "(fayjie2018-fig6 does)"
            )
        experiment = dataclasses.replace(experiment, reward_window_steps=config.reward_window_steps)
    for name in _POSITIVE:
        _at_least_one(name, getattr(config, name))
    if config.learning_starts is not None and config.learning_starts < 0:
        raise UsageError(f"--learning-starts must be >= 0, got {config.learning_starts}")
    labels = [row.label for row in experiment.rows]
    unknown = [label for label in config.rows if label not in labels]
    if unknown:
        raise UsageError(
            f"unknown row(s) {', '.join(unknown)} of {experiment.name}: expected some of "
            f"{', '.join(labels)}"
        )
    references = experiment.references if config.references is None else config.references
    known = reference_policies()
    missing = [policy for policy in references if policy not in known]
    if missing:
        raise UsageError(
            f"reference polic{'y' if len(missing) == 1 else 'ies'} {', '.join(missing)} "
            f"unknown to overtake-eval --policy (it has {', '.join(known)}): pass "
            f"--references with some of those"
        )
    total_steps = config.total_steps or experiment.total_steps
    scaled = Schedule.for_budget(total_steps)
    if not experiment.scale_schedule:
        own = TrainConfig.for_preset(experiment.preset).dqn
        scaled = dataclasses.replace(
            scaled,
            learning_starts=own.learning_starts,
            epsilon_decay_steps=own.epsilon_decay_steps,
            target_update_steps=own.target_update_steps,
            replay_size=own.replay_size,
        )
    schedule = Schedule(
        **{
            f.name: getattr(config, f.name)
            if getattr(config, f.name) is not None
            else getattr(scaled, f.name)
            for f in dataclasses.fields(Schedule)
        }
    )
    jobs = config.jobs or available_cores()
    out = config.out or Path("runs") / "experiments" / experiment.name
    rows = tuple(
        dataclasses.replace(row, seeds=config.seeds or row.seeds)
        for row in experiment.rows
        if not config.rows or row.label in config.rows
    )
    threads = config.torch_threads or max(1, available_cores() // jobs)
    runs = tuple(
        _run_plan(config, experiment, row, seed, out, total_steps, schedule, threads)
        for row in rows
        for seed in range(row.seeds)
    )
    return Plan(
        experiment=experiment,
        out=out,
        jobs=jobs,
        torch_threads=threads,
        rows=rows,
        runs=runs,
        densities=config.densities or experiment.densities,
        references=references,
        eval_episodes=config.eval_episodes or experiment.eval_episodes,
        schedule=schedule,
        total_steps=total_steps,
    )


def _run_plan(
    config: ExperimentConfig,
    experiment: Experiment,
    row: Row,
    seed: int,
    out: Path,
    total_steps: int,
    schedule: Schedule,
    threads: int,
) -> RunPlan:
    run_dir = out / f"{row.label}-seed{seed}"
    # The preset's training (its paper's network and hyper-parameters), scaled to the budget.
    base = TrainConfig.for_preset(experiment.preset)
    dqn = dataclasses.replace(
        base.dqn,
        learning_starts=schedule.learning_starts,
        epsilon_decay_steps=schedule.epsilon_decay_steps,
        target_update_steps=schedule.target_update_steps,
        replay_size=schedule.replay_size,
    )
    if row.network is not None:
        dqn = dataclasses.replace(dqn, network=row.network)
    if row.learning_rate is not None:
        dqn = dataclasses.replace(dqn, learning_rate=row.learning_rate)
    train = dataclasses.replace(
        base,
        algo=row.algo,
        inputs=row.inputs,
        preset=experiment.preset,
        traffic=experiment.train_traffic,
        set=config.set,
        connect=config.connect,
        security=config.security,
        num_envs=config.num_envs or experiment.num_envs,
        total_steps=total_steps,
        seed=seed,
        run_dir=run_dir,
        resume_if_found=True,
        checkpoint_every=schedule.checkpoint_every,
        log_every=experiment.reward_window_steps or base.log_every,
        torch_threads=threads,
        progress=False,
        dqn=dqn,
        recording=RecordingConfig(
            sink="file" if config.record_training else "off",
            record_every=TrainConfig().recording.record_every,
        ),
    )
    return RunPlan(row=row, seed=seed, run_dir=run_dir, train=train)


# Settings of a run that do not change what it learns: a restarted experiment may change them.
_UNLEARNED = (
    "connect",
    "security",
    "torch_threads",
    "progress",
    "recording",
    "resume",
    "resume_if_found",
    "run_dir",
)


def training_identity(train: TrainConfig) -> dict[str, Any]:
    """What a run's training is, for comparing a directory's runs with a new invocation's."""
    data = plain_data(train)
    for name in _UNLEARNED:
        data.pop(name, None)
    return data


# --- command lines ------------------------------------------------------------------------------


def command_args(config: Any, default: Any) -> list[str]:
    """The command-line arguments (tyro, with OmitArgPrefixes) that make a command parse
    ``config``: one per field that differs from ``default``, nested dataclasses flattened."""
    args: list[str] = []
    for f in dataclasses.fields(config):
        value, base = getattr(config, f.name), getattr(default, f.name)
        if dataclasses.is_dataclass(value):
            args += command_args(value, base)
            continue
        if value == base:
            continue
        flag = "--" + f.name.replace("_", "-")
        if isinstance(value, bool):
            args.append(flag if value else f"--no-{f.name.replace('_', '-')}")
        elif value is None:
            args += [flag, "None"]
        elif isinstance(value, tuple):
            args += [flag, *(str(item) for item in value)]
        else:
            args += [flag, str(value)]
    return args


def train_command(train: TrainConfig) -> list[str]:
    """``overtake-train`` for ``train``, as this interpreter's module (found whether or not
    the environment's bin is on PATH)."""
    # overtake-train's defaults are the training of the preset it is given (--preset first).
    base = TrainConfig.for_preset(train.preset)
    preset = [] if train.preset == TrainConfig().preset else ["--preset", train.preset]
    args = [*preset, *command_args(train, base)]
    return [sys.executable, "-m", "overtake.trainers.train", *args]


def eval_command(evaluation: EvalConfig) -> list[str]:
    """``overtake-eval`` for ``evaluation``, as this interpreter's module."""
    args = command_args(evaluation, EvalConfig())
    return [sys.executable, "-m", "overtake.trainers.evaluate", *args]


# --- files --------------------------------------------------------------------------------------


def write_atomic(path: Path, data: str | bytes) -> None:
    """Write to a temporary file beside ``path`` and rename it over ``path``: a kill leaves the
    old file or the new one, never half of one."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def read_json(path: Path) -> Any:
    """``path``'s JSON, or None where it is missing or unreadable (a file of a killed
    process)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def checkpoint_step(run_dir: Path) -> int | None:
    """The step of the run's checkpoint, or None where it has none."""
    path = run_dir / CHECKPOINT_NAME
    if not path.exists():
        return None
    return load_checkpoint(path).step


def lock(path: Path) -> int | None:
    """An open descriptor holding an exclusive lock on ``path`` (created), or None where
    another process holds it. The lock lasts while any process keeps the descriptor open: a
    child that inherits it holds it until it exits."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def note_life(run_dir: Path, from_step: int) -> None:
    """Record, before a trainer starts in ``run_dir``, where its records will begin in
    metrics.jsonl and from which step it trains (0: from scratch). The episodes an earlier
    life logged after that step are redone by this one, and the curves drop them."""
    metrics = run_dir / "metrics.jsonl"
    offset = metrics.stat().st_size if metrics.exists() else 0
    record = {"from_step": from_step, "metrics_offset_bytes": offset, "started_utc": _utc()}
    with open(run_dir / LIVES_NAME, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(record) + "\n")


def training_episodes(run_dir: Path) -> list[dict[str, Any]]:
    """The run's training episodes (metrics.jsonl's ``episode`` records) that its final model
    descends from: where a life resumed from step S, the earlier lives' episodes after S are
    left out (that training was lost with the kill and done again)."""
    return training_records(run_dir, "episode")


def training_records(run_dir: Path, kind: str) -> list[dict[str, Any]]:
    """:func:`training_episodes` for metrics.jsonl's records of any ``kind``."""
    metrics = run_dir / "metrics.jsonl"
    data = metrics.read_bytes() if metrics.exists() else b""
    starts: list[tuple[int, int | None]] = [(0, None)]
    lives = run_dir / LIVES_NAME
    if lives.exists():
        for text in lives.read_text(encoding="utf-8").splitlines():
            with contextlib.suppress(ValueError, KeyError, TypeError):
                life = json.loads(text)
                starts.append((int(life["metrics_offset_bytes"]), int(life["from_step"])))
    kept: list[dict[str, Any]] = []
    for i, (begin, from_step) in enumerate(starts):
        end = starts[i + 1][0] if i + 1 < len(starts) else len(data)
        if from_step is not None:
            kept = [record for record in kept if record["step"] <= from_step]
        for line in data[begin:end].splitlines():
            try:
                record = json.loads(line)
            except ValueError:
                continue  # the line a kill cut short
            if isinstance(record, dict) and record.get("kind") == kind:
                kept.append(record)
    return kept


def window_rewards(train_records_by_run: dict[str, list[dict[str, Any]]], window: int) -> Any:
    """A row's reward per window of training steps (Fayjie et al.'s Fig. 6): each training
    line's ``reward_sum`` (the runs log one per window), the mean over the row's runs of the
    k-th window, and the lowest and highest of them."""
    by_window: dict[int, list[float]] = {}
    for records in train_records_by_run.values():
        for record in records:
            if record.get("reward_sum") is not None:
                k = max(1, round(record["step"] / window))
                by_window.setdefault(k, []).append(float(record["reward_sum"]))
    windows = sorted(by_window)
    return {
        "window_end_step": [k * window for k in windows],
        "mean": [float(np.mean(by_window[k])) for k in windows],
        "run_min": [min(by_window[k]) for k in windows],
        "run_max": [max(by_window[k]) for k in windows],
    }


def _utc() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _say(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


# --- processes ----------------------------------------------------------------------------------


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
    lock_fd: int
    pid_file: Path
    log: Any
    pidfd: int | None


@dataclass(frozen=True)
class Task:
    """A process to run: a training run, or an evaluation whose result goes to ``cache``."""

    kind: Literal["train", "eval"]
    name: str
    """in the experiment's messages: the run, or the policy and density"""
    command: tuple[str, ...]
    lock_path: Path
    """held while it runs (a training run's directory, an evaluation's cache file)"""
    log_path: Path
    pid_file: Path
    """holds the process's id while it runs"""
    run: RunPlan | None = None
    cache: Path | None = None
    key: dict[str, Any] = field(default_factory=dict)
    """an evaluation's settings, stored with its result: a cache entry counts only for these"""

    @property
    def json_out(self) -> Path:
        assert self.cache is not None
        return self.cache.with_name(self.cache.name + ".out")


def _start(task: Task, fd: int, threads: int) -> Child:
    task.log_path.parent.mkdir(parents=True, exist_ok=True)
    log = open(task.log_path, "a", encoding="utf-8")  # noqa: SIM115 (open while it runs)
    log.write(f"--- {_utc()} overtake-experiment starts: {' '.join(task.command)}\n")
    log.flush()
    process = subprocess.Popen(
        task.command,
        stdin=subprocess.DEVNULL,
        stdout=log,
        stderr=subprocess.STDOUT,
        # PyTorch sizes its thread pool from these at start (overtake-eval has no option for
        # it): --jobs processes of as many threads each as there are cores would contend.
        env={**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)},
        # The lock's descriptor goes with it: the lock lives as long as the child.
        pass_fds=(fd,),
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
    )
    task.pid_file.write_text(f"{process.pid}\n")
    pidfd = None
    with contextlib.suppress(AttributeError, OSError):
        pidfd = os.pidfd_open(process.pid)
    return Child(task, process, fd, task.pid_file, log, pidfd)


def _release(child: Child) -> None:
    child.log.close()
    if child.pidfd is not None:
        os.close(child.pidfd)
    with contextlib.suppress(FileNotFoundError):
        child.pid_file.unlink()
    os.close(child.lock_fd)


def _stop(children: list[Child]) -> None:
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
        _release(child)


def _wait_any(children: list[Child], timeout_s: float) -> None:
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


# --- the experiment -----------------------------------------------------------------------------


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
                EvalConfig(policy=typing.cast(Any, policy), preset=self.plan.experiment.preset),
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
            traffic=density,
            set=config.set,
            max_decisions=config.eval_max_decisions,
            # The planner reads the simulator's true state: it drives an in-process copy of
            # the same preset and overrides even when the rows train on a server.
            connect=None if base.policy == "planner" else config.connect,
            security=config.security,
            json_out=cache.with_name(cache.name + ".out"),
        )
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
            lock_path=cache.with_name(cache.name + ".lock"),
            log_path=cache.with_suffix(".log"),
            pid_file=cache.with_suffix(".pid"),
            cache=cache,
            key=full_key,
        )

    def train_task(self, run: RunPlan) -> Task:
        return Task(
            kind="train",
            name=run.name,
            command=tuple(train_command(run.train)),
            lock_path=run.run_dir / LOCK_NAME,
            log_path=run.run_dir / "train.log",
            pid_file=run.run_dir / "train.pid",
            run=run,
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
        pending: list[Task] = [self.train_task(run) for run in training]
        evaluations = self.reference_tasks()
        for run in plan.runs:
            step = steps[run.name]
            if step is not None and step >= plan.total_steps:
                evaluations += self.eval_tasks_of_run(run, step)
        pending += [task for task in evaluations if self.cached(task) is None]
        done_before = len(plan.runs) - len(training)
        _say(
            f"{plan.experiment.name} in {plan.out}: {len(plan.runs)} training runs "
            f"({done_before} already at {plan.total_steps:,} steps), {len(pending)} "
            f"processes to run, {plan.jobs} at a time, {plan.torch_threads} PyTorch "
            "thread(s) each"
        )
        running: list[Child] = []
        next_progress = time.monotonic() + self.config.progress_every_s
        try:
            while pending or running:
                self._start_ready(pending, running)
                if not running:
                    # Every pending task is locked by a process of an earlier invocation.
                    _wait_any([], POLL_S)
                    continue
                _wait_any(running, POLL_S)
                for child in [c for c in running if c.process.poll() is not None]:
                    running.remove(child)
                    _release(child)
                    pending += self._finished(child)
                if time.monotonic() >= next_progress:
                    self._report_progress(running)
                    next_progress = time.monotonic() + self.config.progress_every_s
        finally:
            _stop(running)

    def _start_ready(self, pending: list[Task], running: list[Child]) -> None:
        """Start pending tasks, training first (the longest), while fewer than --jobs run."""
        for task in sorted(pending, key=lambda t: t.kind != "train"):
            if len(running) >= self.plan.jobs:
                return
            fd = lock(task.lock_path)
            if fd is None:
                continue  # a process of an earlier invocation still holds it
            if self._done_meanwhile(task, pending):
                os.close(fd)
                continue
            if task.run is not None:
                step = checkpoint_step(task.run.run_dir)
                note_life(task.run.run_dir, step or 0)
                where = f"from step {step:,}" if step else "from scratch"
                _say(f"train {task.name}: starts {where} (log {task.log_path})")
            else:
                _say(f"evaluate {task.name}")
            pending.remove(task)
            running.append(_start(task, fd, self.plan.torch_threads))

    def _done_meanwhile(self, task: Task, pending: list[Task]) -> bool:
        """Whether another invocation in the same directory (one that held the task's lock
        while this one planned) has done ``task`` since; if so, drop it from ``pending`` and
        add what it makes ready. Two invocations side by side then share the work instead of
        repeating it (one started with --jobs 1 to evaluate the references while another
        trains, for instance)."""
        if task.run is not None:
            step = checkpoint_step(task.run.run_dir) or 0
            if step < self.plan.total_steps:
                return False
            _say(f"train {task.name}: done at step {step:,} by another invocation")
            pending.remove(task)
            pending += [t for t in self.eval_tasks_of_run(task.run, step) if self.cached(t) is None]
            return True
        if self.cached(task) is None:
            return False
        _say(f"evaluate {task.name}: done by another invocation")
        pending.remove(task)
        return True

    def _finished(self, child: Child) -> list[Task]:
        """Handle a child that ended; returns the tasks it makes ready (a finished run's
        evaluations)."""
        task, code = child.task, child.process.returncode
        if code != 0:
            self.failed.append(f"{task.kind} {task.name} (exit status {code}, log {task.log_path})")
            _say(f"{task.kind} {task.name}: FAILED with exit status {code}, see {task.log_path}")
            return []
        if task.run is not None:
            step = checkpoint_step(task.run.run_dir) or 0
            if step < self.plan.total_steps:
                self.failed.append(
                    f"train {task.name} ended at step {step:,} of {self.plan.total_steps:,} "
                    f"(log {task.log_path})"
                )
                return []
            self.trained.append(task.name)
            _say(f"train {task.name}: done at step {step:,}")
            return [t for t in self.eval_tasks_of_run(task.run, step) if self.cached(t) is None]
        assert task.cache is not None
        result = read_json(task.json_out)
        if not isinstance(result, dict):
            self.failed.append(f"evaluate {task.name}: no result in {task.json_out}")
            return []
        write_atomic(task.cache, json.dumps({"key": task.key, "result": result}, indent=1))
        task.json_out.unlink()
        self.evaluated.append(task.name)
        speed = result["summary"]["avg_speed_kmh"]["mean"]
        _say(f"evaluate {task.name}: done ({speed:.1f} km/h)")
        return []

    def _report_progress(self, running: list[Child]) -> None:
        for child in running:
            run = child.task.run
            if run is None:
                continue
            last = _last_train_record(run.run_dir / "metrics.jsonl")
            if last is not None:
                _say(
                    f"train {run.name}: step {last['step']:,} of {self.plan.total_steps:,}, "
                    f"{last['steps_per_s']:.0f} steps/s"
                )


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


# --- statistics ---------------------------------------------------------------------------------


def episode_statistics(episodes: Sequence[dict[str, float]]) -> dict[str, Any]:
    """Mean and spread (standard deviation) over ``episodes`` of every metric and of each
    episode's collisions per 1,000 decisions; the pooled collision rate and the count."""
    table = {
        name: np.array([episode[name] for episode in episodes], dtype=float)
        for name in METRIC_FIELDS
    }
    table["collisions_per_1000_decisions"] = (
        1000.0 * table["collisions"] / np.maximum(table["decisions"], 1.0)
    )
    stats: dict[str, Any] = {
        name: {"mean": float(values.mean()), "std": float(values.std())}
        for name, values in table.items()
    }
    stats["pooled_collisions_per_1000_decisions"] = float(
        1000.0 * table["collisions"].sum() / max(table["decisions"].sum(), 1.0)
    )
    stats["episodes"] = len(episodes)
    return stats


def seed_statistics(per_seed: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Each metric's per-seed means and their spread over the seeds."""
    return {
        name: {
            "means": [s[name]["mean"] for s in per_seed],
            "std": float(np.std([s[name]["mean"] for s in per_seed])),
        }
        for name in EPISODE_METRICS
    }


def seed_order(rows: Sequence[dict[str, Any]], metric: str = "avg_speed_kmh") -> list[dict]:
    """The order of the rows trained from several seeds, judged against the seed spread: for
    every pair, the row with the higher mean of its seeds' means, and whether the order holds
    beyond the spread, that is every seed of the higher row above every seed of the lower (the
    test a table of a few seeds can bear: with two seeds a confidence interval from their
    means would span tens of km/h)."""
    several = sorted(
        (row for row in rows if len(row["runs"]) > 1),
        key=lambda row: -float(np.mean(row["seeds"][metric]["means"])),
    )
    order = []
    for i, high in enumerate(several):
        for low in several[i + 1 :]:
            highs, lows = high["seeds"][metric]["means"], low["seeds"][metric]["means"]
            order.append(
                {
                    "higher": high["label"],
                    "lower": low["label"],
                    "difference": float(np.mean(highs) - np.mean(lows)),
                    "beyond_seed_spread": min(highs) > max(lows),
                }
            )
    return order


def learning_curves(
    episodes_by_run: dict[str, list[dict[str, Any]]], total_steps: int, bins: int
) -> dict[str, Any]:
    """A row's learning curves: per bin of ``total_steps / bins`` steps, the mean of the
    training episodes that ended in it (over all the row's runs), and the lowest and highest
    of the runs' own means. Empty bins are None."""
    edges = np.linspace(0, total_steps, bins + 1)
    curves: dict[str, Any] = {"bin_end_step": [round(float(e)) for e in edges[1:]]}
    for metric, _ in CURVE_METRICS:
        pooled: list[float | None] = []
        low: list[float | None] = []
        high: list[float | None] = []
        for lo, hi in itertools.pairwise(edges):
            chosen = {
                run: [e[metric] for e in episodes if lo < e["step"] <= hi]
                for run, episodes in episodes_by_run.items()
            }
            values = [v for vs in chosen.values() for v in vs]
            means = [float(np.mean(vs)) for vs in chosen.values() if vs]
            pooled.append(float(np.mean(values)) if values else None)
            low.append(min(means) if means else None)
            high.append(max(means) if means else None)
        curves[metric] = {"mean": pooled, "run_min": low, "run_max": high}
    return curves


# --- outputs ------------------------------------------------------------------------------------


def _cell(stats: dict[str, Any], metric: str, decimals: int) -> str:
    return f"{stats[metric]['mean']:.{decimals}f} ± {stats[metric]['std']:.{decimals}f}"


def markdown_table(result: dict[str, Any]) -> str:
    """table.md: one table per density, the rows then the reference policies."""
    plan = result["plan"]
    episodes, seed = plan["eval_episodes"], plan["eval_seed"]
    lines = [
        f"# {result['experiment']}: {plan['title']}",
        "",
        f"Training: {plan['total_steps']:,} environment steps per run, preset "
        f"{plan['preset']}, {plan['num_envs']} environments, "
        f"{plan['train_traffic'] or 'the preset’s'} traffic; learning starts at "
        f"{plan['schedule']['learning_starts']:,} steps, epsilon 1 → 0.1 over "
        f"{plan['schedule']['epsilon_decay_steps']:,}, target copy every "
        f"{plan['schedule']['target_update_steps']:,}, replay "
        f"{plan['schedule']['replay_size']:,}.",
        f"Evaluation: greedy, {episodes} episodes per policy and density on seeds "
        f"{seed}–{seed + episodes - 1} (the same for every policy). Mean ± spread (standard "
        "deviation) over the episodes; a row with several training seeds pools the episodes "
        "of all of them (per-seed means below its table). Collisions per 1,000 decisions: "
        "each episode's own rate.",
        f"Code {result['commit']}, written {result['written_utc']}.",
    ]
    headings = [heading for _, heading, _ in TABLE_COLUMNS]
    for density, table in result["densities"].items():
        lines += [
            "",
            f"## {density.capitalize()} traffic",
            "",
            "| policy | algorithm | inputs | training seeds | " + " | ".join(headings) + " |",
            "|---|---|---|---:|" + "---:|" * len(headings),
        ]
        for row in table["rows"]:
            cells = [_cell(row["summary"], m, d) for m, _, d in TABLE_COLUMNS]
            lines.append(
                f"| {row['label']} | {ALGO_NAMES[row['algo']]} | {INPUT_NAMES[row['inputs']]} "
                f"| {len(row['runs'])} | " + " | ".join(cells) + " |"
            )
        for reference in table["references"]:
            cells = [_cell(reference["summary"], m, d) for m, _, d in TABLE_COLUMNS]
            lines.append(
                f"| {reference['policy']} | reference policy | - | - | " + " | ".join(cells) + " |"
            )
        several = [row for row in table["rows"] if len(row["runs"]) > 1]
        if several:
            lines += [
                "",
                "Per training seed (means over each seed's episodes; spread over the seeds "
                "in the last line of each row):",
                "",
                "| run | " + " | ".join(headings) + " |",
                "|---|" + "---:|" * len(headings),
            ]
            for row in several:
                for run in row["runs"]:
                    cells = [f"{run['summary'][m]['mean']:.{d}f}" for m, _, d in TABLE_COLUMNS]
                    lines.append(f"| {run['run']} | " + " | ".join(cells) + " |")
                cells = [f"± {row['seeds'][m]['std']:.{d}f}" for m, _, d in TABLE_COLUMNS]
                lines.append(f"| {row['label']}: spread over seeds | " + " | ".join(cells) + " |")
            if len(several) > 1:
                lines += [
                    "",
                    "The order of these rows by average speed, against the seed spread (it "
                    "holds beyond the spread when every seed of the faster row is faster than "
                    "every seed of the slower):",
                    "",
                ]
                means = {row["label"]: row["seeds"]["avg_speed_kmh"]["means"] for row in several}
                for pair in table["order"]:
                    high, low = means[pair["higher"]], means[pair["lower"]]
                    verdict = (
                        "beyond the seed spread"
                        if pair["beyond_seed_spread"]
                        else "in the means only (the seeds overlap)"
                    )
                    lines.append(
                        f"- {pair['higher']} ({min(high):.1f}–{max(high):.1f}) > "
                        f"{pair['lower']} ({min(low):.1f}–{max(low):.1f}) by "
                        f"{pair['difference']:.1f} km/h: {verdict}"
                    )
    experiment = EXPERIMENTS.get(result["experiment"])
    if experiment is not None and experiment.note:
        lines += ["", "## Reading it", "", experiment.note]
    if experiment is not None and experiment.paper:
        lines += ["", "## The paper's figures", "", experiment.paper]
    return "\n".join(lines) + "\n"


def plot_curves(curves: dict[str, Any], title: str, path: Path) -> None:
    """curves.png: one panel per curve metric, one line per row (with the band between its
    runs' lowest and highest bin means where it has several)."""
    # The object-oriented API draws with the Agg canvas and touches no global pyplot state.
    from matplotlib.figure import Figure

    windowed = [row for row, curve in curves.items() if "window_reward" in curve]
    panels = len(CURVE_METRICS) + (1 if windowed else 0)
    figure = Figure(figsize=(7.0, 3.2 * panels), layout="constrained")
    axes = figure.subplots(panels, 1, sharex=True, squeeze=False)[:, 0]
    if windowed:
        ax = axes[-1]
        for row in windowed:
            window = curves[row]["window_reward"]
            ax.plot(window["window_end_step"], window["mean"], marker=".", label=row)
        steps = curves[windowed[0]]["window_reward"]["window_end_step"]
        size = steps[0] if steps else 0
        ax.set_ylabel(f"reward per {size:,} steps")
        ax.grid(alpha=0.3)
    for ax, (metric, label) in zip(axes, CURVE_METRICS):
        for row, curve in curves.items():
            steps = np.array(curve["bin_end_step"], dtype=float)
            mean = _floats(curve[metric]["mean"])
            # Bins no episode ended in are skipped, so that the line joins its neighbours.
            ok = ~np.isnan(mean)
            (line,) = ax.plot(steps[ok], mean[ok], marker=".", label=row)
            if curve["runs"] > 1:
                ax.fill_between(
                    steps[ok],
                    _floats(curve[metric]["run_min"])[ok],
                    _floats(curve[metric]["run_max"])[ok],
                    color=line.get_color(),
                    alpha=0.2,
                    linewidth=0,
                )
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("training steps")
    axes[-1].set_xlim(0, max(max(c["bin_end_step"]) for c in curves.values()))
    axes[0].legend(fontsize="small")
    axes[0].set_title(title, fontsize="medium")
    tmp = path.with_name(path.name + ".tmp")
    figure.savefig(tmp, format="png", dpi=100)
    os.replace(tmp, path)


def _relative(path: Path | None, root: Path) -> Path | None:
    """``path`` within ``root`` (an evaluation's cache file, named in table.json)."""
    if path is None:
        return None
    try:
        return path.relative_to(root)
    except ValueError:
        return path


def _floats(values: list[float | None]) -> np.ndarray:
    return np.array([math.nan if v is None else v for v in values], dtype=float)


# matplotlib's default cycle (tab10), so that curves.rrd and curves.png colour rows alike.
ROW_COLORS = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)


def record_curves(curves: dict[str, Any], experiment: str, path: Path) -> None:
    """curves.rrd: ``curves/<metric>/<row>`` on the ``step`` timeline, one entity per row."""
    import rerun as rr
    import rerun.blueprint as rrb

    metrics = list(CURVE_METRICS)
    if any("window_reward" in curve for curve in curves.values()):
        metrics.append(("window_reward", "reward per window of training steps"))
    # Without a range the viewer shows a narrow window around the time cursor; a learning curve
    # is read whole.
    whole_run = rrb.archetypes.TimeAxis(
        view_range=rr.TimeRange(
            start=rr.TimeRangeBoundary.infinite(), end=rr.TimeRangeBoundary.infinite()
        )
    )
    blueprint = rrb.Blueprint(
        rrb.Vertical(
            *(
                rrb.TimeSeriesView(origin=f"/curves/{metric}", name=label, axis_x=whole_run)
                for metric, label in metrics
            )
        ),
        rrb.TimePanel(timeline="step"),
        collapse_panels=True,
    )
    tmp = path.with_name(path.name + ".tmp")
    recording = open_recording(
        f"overtake-experiment {experiment}", RecordingConfig(sink="file", rrd=tmp), tmp, blueprint
    )
    assert recording is not None  # sink=file always opens one
    stream = recording.stream
    try:
        for index, (row, curve) in enumerate(curves.items()):
            color = ROW_COLORS[index % len(ROW_COLORS)]
            for metric, _ in metrics:
                if metric not in curve:
                    continue
                entity = f"curves/{metric}/{row}"
                # One colour per row in every plot, as in curves.png; the viewer's own pick
                # hashes the entity path and colours a row differently from plot to plot.
                stream.log(entity, rr.SeriesLines(names=row, colors=color), static=True)
                steps = curve[metric].get("window_end_step", curve["bin_end_step"])
                for step, value in zip(steps, curve[metric]["mean"]):
                    if value is not None:
                        stream.set_time("step", sequence=step)
                        stream.log(entity, rr.Scalars(value))
    finally:
        close_recording(recording)
    os.replace(tmp, path)


def _versions() -> dict[str, str]:
    versions = package_versions()
    from importlib import metadata

    for name in ("matplotlib", "rerun-sdk", "tyro"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


class Outputs:
    """The table and the curves, from the cached evaluations and the runs' metrics."""

    def __init__(self, config: ExperimentConfig, plan: Plan, experiment_run: ExperimentRun):
        self.config, self.plan, self.run = config, plan, experiment_run

    def result(self) -> dict[str, Any]:
        plan = self.plan
        densities: dict[str, Any] = {}
        for density in plan.densities:
            rows = [self._row(row, density) for row in plan.rows]
            densities[density] = {
                "rows": rows,
                "order": seed_order(rows),
                "references": [self._reference(policy, density) for policy in plan.references],
            }
        curves = {}
        for row in plan.rows:
            runs = [run for run in plan.runs if run.row == row]
            curve = learning_curves(
                {run.name: training_episodes(run.run_dir) for run in runs},
                plan.total_steps,
                self.config.curve_bins,
            )
            window = plan.experiment.reward_window_steps
            if window:
                curve["window_reward"] = window_rewards(
                    {run.name: training_records(run.run_dir, "train") for run in runs}, window
                )
            curves[row.label] = {"runs": len(runs), **curve}
        experiment = plan.experiment
        return {
            "experiment": experiment.name,
            "plan": {
                "title": experiment.title,
                "rows": [dataclasses.asdict(row) for row in plan.rows],
                "preset": experiment.preset,
                "total_steps": plan.total_steps,
                "num_envs": plan.runs[0].train.num_envs if plan.runs else None,
                "train_traffic": experiment.train_traffic,
                "schedule": dataclasses.asdict(plan.schedule),
                "densities": list(plan.densities),
                "references": list(plan.references),
                "eval_episodes": plan.eval_episodes,
                "eval_seed": self.config.eval_seed,
                "eval_max_decisions": self.config.eval_max_decisions,
                "runs": {run.name: plain_data(run.train) for run in plan.runs},
            },
            "config": plain_data(self.config),
            "versions": _versions(),
            "commit": git_commit(),
            "written_utc": _utc(),
            "densities": densities,
            "curves": curves,
        }

    def _row(self, row: Row, density: Density) -> dict[str, Any]:
        runs: list[dict[str, Any]] = []
        pooled: list[dict[str, float]] = []
        for run in (run for run in self.plan.runs if run.row == row):
            step = checkpoint_step(run.run_dir)
            assert step is not None  # every run finished before the outputs are written
            [task] = [
                t for t in self.run.eval_tasks_of_run(run, step) if t.key["density"] == density
            ]
            result = self.run.cached(task)
            assert result is not None
            runs.append(
                {
                    "run": run.name,
                    "seed": run.seed,
                    "checkpoint_step": step,
                    "summary": episode_statistics(result["episodes"]),
                    "evaluation": str(_relative(task.cache, self.plan.out)),
                    "decisions_per_s": result["decisions_per_s"],
                }
            )
            pooled.extend(result["episodes"])
        return {
            "label": row.label,
            "algo": row.algo,
            "inputs": row.inputs,
            "summary": episode_statistics(pooled),
            "seeds": seed_statistics([run["summary"] for run in runs]),
            "runs": runs,
        }

    def _reference(self, policy: str, density: Density) -> dict[str, Any]:
        [task] = [
            t
            for t in self.run.reference_tasks()
            if t.key["policy"] == policy and t.key["density"] == density
        ]
        result = self.run.cached(task)
        assert result is not None
        return {
            "policy": policy,
            "summary": episode_statistics(result["episodes"]),
            "evaluation": str(_relative(task.cache, self.plan.out)),
            "decisions_per_s": result["decisions_per_s"],
        }

    def write(self) -> dict[str, Any]:
        out = self.plan.out
        result = self.result()
        write_atomic(out / "table.json", json.dumps(result, indent=1))
        write_atomic(out / "table.md", markdown_table(result))
        title = f"{self.plan.experiment.name}: training episodes ({self.config.curve_bins} bins)"
        plot_curves(result["curves"], title, out / "curves.png")
        record_curves(result["curves"], self.plan.experiment.name, out / "curves.rrd")
        return result


# --- main ---------------------------------------------------------------------------------------


def describe_experiments() -> str:
    lines = []
    for experiment in EXPERIMENTS.values():
        lines += [
            f"{experiment.name}: {experiment.title}",
            f"  {experiment.total_steps:,} steps per run, preset {experiment.preset}, "
            f"evaluated at {', '.join(experiment.densities)} traffic beside "
            f"{', '.join(experiment.references)}",
        ]
        lines += [
            f"  {row.label}: {ALGO_NAMES[row.algo]}, {INPUT_NAMES[row.inputs]}, {row.seeds} seed(s)"
            for row in experiment.rows
        ]
    return "\n".join(lines)


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
        now = training_identity(run.train)
        if before is not None and before != now:
            # A setting added to the trainer since the directory was recorded, at its default
            # (what the trainer did before the setting existed), is no difference.
            default = training_identity(TrainConfig.for_preset(run.train.preset))
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
    if config.list_experiments:
        text = describe_experiments()
        print(text)
        return {"experiments": text}
    plan = make_plan(config)
    plan.out.mkdir(parents=True, exist_ok=True)
    experiment_lock = lock(plan.out / LOCK_NAME)
    if experiment_lock is None:
        raise ExperimentError(f"another overtake-experiment is running in {plan.out}")
    try:
        check_directory(plan)
        experiment_run = ExperimentRun(config, plan)
        experiment_run.run()
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
    _say(f"wrote {table}, table.json, curves.png and curves.rrd in {plan.out}")
    return {
        "out": str(plan.out),
        "trained": experiment_run.trained,
        "evaluated": experiment_run.evaluated,
        "table_md": str(table),
        "table_json": str(plan.out / "table.json"),
        "curves_png": str(plan.out / "curves.png"),
        "curves_rrd": str(plan.out / "curves.rrd"),
    }


EVIDENCE = ("table.md", "table.json", "curves.png")


def keep_evidence(out: Path, keep: Path) -> None:
    """Copy an experiment's table and curves (small: table.json holds summaries, the episodes
    stay in the evaluations) from ``out`` into ``keep``, each written whole or not at all."""
    keep.mkdir(parents=True, exist_ok=True)
    for name in EVIDENCE:
        write_atomic(keep / name, (out / name).read_bytes())
    _say(f"kept {', '.join(EVIDENCE)} in {keep}")


def _terminate(_signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt


def cli(argv: list[str] | None = None) -> None:
    config = tyro.cli(
        ExperimentConfig,
        args=argv,
        config=(tyro.conf.OmitArgPrefixes,),
        description="overtake-experiment: train, evaluate and tabulate a paper's table "
        "(resumable: run the same command again to continue)",
    )
    # SIGTERM (a container stopping, `kill`) stops the children as Ctrl-C does.
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        summary = run_command("overtake-experiment", main, config)
    except KeyboardInterrupt:
        sys.exit("overtake-experiment: stopped; run the same command again to continue")
    finally:
        signal.signal(signal.SIGTERM, previous)
    if not config.list_experiments:
        print(Path(summary["table_md"]).read_text(encoding="utf-8"))


if __name__ == "__main__":
    cli()
