"""An experiment resolved against a command line: every run's training configuration, checked
before anything is trained, and the command lines of its processes."""

from __future__ import annotations

import dataclasses
import json
import sys
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import tyro

from overtake.cli import Output, UsageError
from overtake.cli.options import unset
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.wire.remote_config import RemoteConfig
from overtake.viz.recording import RecordingConfig

from ..config.train_config import TrainConfig
from ..evaluate import EvalConfig
from ..learning.learner import execution_device
from ..run.checkpoint import plain_data
from .catalogue import EXPERIMENTS, RETIRED, Density, Experiment, Row, Schedule
from .launcher import RayCluster, available_cores, ray_cluster


@dataclass(frozen=True)
class ExperimentConfig:
    """Reproduce a paper's table: train its rows (resumable, in parallel), evaluate them and
    the reference policies on fixed seeds at each traffic density, write the table and the
    learning curves. Run the same command again to continue after a kill. Where the simulator
    is (--connect: a server for training and evaluation alike; default one in each process)
    is where's option; which simulator is the experiment's."""

    experiment: Annotated[str | None, tyro.conf.Positional] = None
    """the experiment to run (without one: the experiments, and how long each takes)"""
    where: Where = field(default_factory=Where)
    """where the simulator runs, for training and evaluation alike: a server (--connect), or
    one in each process"""
    out: Path | None = None
    """the experiment directory; default runs/experiments/<experiment>"""
    jobs: int | None = None
    """processes (training batches or evaluations) at once; default the cores this process
    may use"""
    members: int | None = None
    """training runs trained together in one process, as members of one learner (runs of one
    network only; docs/training.md "Members"); default: each network's runs spread evenly over
    --jobs processes; 1: a process per run"""
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
    """steps over which epsilon falls; None: the experiment's"""
    target_update_steps: int | None = None
    """steps between target network copies; None: the experiment's"""
    replay_size: int | None = None
    """transitions the replay keeps; None: the experiment's"""
    checkpoint_every: int | None = None
    """steps between checkpoints; None: the experiment's"""
    reward_window_steps: int | None = None
    """the training reward's window, for an experiment that plots it (Fayjie et al.'s 3,000);
    None keeps the experiment's"""
    set: tuple[str, ...] = ()
    """simulator overrides (dotted.name=value) for training and evaluation alike"""
    torch_threads: int | None = None
    """PyTorch threads per process; default the cores divided by --jobs"""
    device: str = "cpu"
    """where the training runs' networks learn (cpu, cuda, cuda:N, mps): the runs of one
    machine share its GPU; a run may be continued on another device; evaluation runs on the
    CPU"""
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
    ray: Annotated[tuple[str, ...] | None, unset("[ADDRESS]")] = None
    """run every training batch and evaluation as a Ray task on a cluster: its head's
    HOST:PORT, or auto (also what --ray alone means: the cluster ray.init finds, else a local
    one); --out must be storage every node sees (docs/cluster.md); needs the cluster extra;
    unset: processes of this machine"""
    ray_retries: int = 3
    """with --ray: times a task whose node (or worker) is lost is started again on another,
    each time resuming its runs from their last checkpoints"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before any run starts)."""
        return (
            Output("--out", self.out, folder=True),
            Output("--keep", self.keep, folder=True),
        )


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
    members: int | None
    """training runs per process at most; None: spread over the jobs"""
    rows: tuple[Row, ...]
    runs: tuple[RunPlan, ...]
    densities: tuple[Density, ...]
    references: tuple[str, ...]
    eval_episodes: int
    schedule: Schedule
    total_steps: int
    cluster: RayCluster | None = None
    """where the tasks run: a Ray cluster (--ray), or None: processes of this machine"""


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
    "members",
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


def make_plan(config: ExperimentConfig, cores: int | None = None) -> Plan:
    """The experiment ``config`` asks for, checked: every bad option is refused here, before
    anything is trained. ``cores``: the CPUs the tasks run on (default: this process's; on a
    cluster, the cluster's), which --jobs and --torch-threads default from."""
    experiment = EXPERIMENTS.get(config.experiment or "")
    if experiment is None:
        retired = RETIRED.get(config.experiment or "")
        if retired is not None:
            raise UsageError(f"experiment {config.experiment!r} is {retired}")
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
    cluster = ray_cluster(config)
    if cluster is None:
        # On a cluster the nodes' devices count, checked when the tasks are placed.
        try:
            execution_device(config.device)
        except ValueError as error:
            raise UsageError(f"--device: {error}") from None
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
    cores = cores or available_cores()
    jobs = config.jobs or cores
    out = config.out or Path("runs") / "experiments" / experiment.name
    if cluster is not None:
        # The nodes' working directories are theirs: every path a task is given is absolute.
        out = out.absolute()
    rows = tuple(
        dataclasses.replace(row, seeds=config.seeds or row.seeds)
        for row in experiment.rows
        if not config.rows or row.label in config.rows
    )
    threads = config.torch_threads or max(1, cores // jobs)
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
        members=config.members,
        rows=rows,
        runs=runs,
        densities=config.densities or experiment.densities,
        references=references,
        eval_episodes=config.eval_episodes or experiment.eval_episodes,
        schedule=schedule,
        total_steps=total_steps,
        cluster=cluster,
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
    base = TrainConfig.for_preset(experiment.preset, row.recipe)
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
    if row.prioritized or row.n_step > 1:
        dqn = dataclasses.replace(dqn, prioritized=row.prioritized, n_step=row.n_step)
    if row.store_applied:
        dqn = dataclasses.replace(dqn, store_applied=True)
    train = dataclasses.replace(
        base,
        algo=row.algo,
        inputs=row.inputs,
        shield=row.shield,
        shield_watch=row.shield_watch,
        scenario=Scenario(
            preset=experiment.preset, traffic=experiment.train_traffic, set=config.set
        ),
        where=config.where,
        num_envs=config.num_envs or experiment.num_envs,
        total_steps=total_steps,
        seed=seed,
        run_dir=run_dir,
        resume_if_found=True,
        checkpoint_every=schedule.checkpoint_every,
        log_every=experiment.reward_window_steps or base.log_every,
        torch_threads=threads,
        device=config.device,
        progress=False,
        dqn=dqn,
        recording=RecordingConfig(
            sink="file" if config.record_training else "off",
            record_every=TrainConfig().recording.record_every,
        ),
    )
    return RunPlan(row=row, seed=seed, run_dir=run_dir, train=train)


# Settings of a run that do not change what it learns: a restarted experiment may change them
# (a run trained on a GPU may be finished on the CPU: the same algorithm, its numbers rounded
# differently). Where the simulator is (every field of Where and of the RemoteConfig it holds,
# which records written before the configuration held a Where keep at the top) is one of them.
_UNLEARNED = (
    *(f.name for f in dataclasses.fields(Where)),
    *(f.name for f in dataclasses.fields(RemoteConfig)),
    "where",
    "device",
    "torch_threads",
    "progress",
    "recording",
    "resume",
    "resume_if_found",
    "run_dir",
    # Where the replay lives (disk or memory; --save-replay before issue 56) changes how
    # exactly a resume goes on, not what a run learns.
    "replay_on_disk",
    "save_replay",
)


def training_identity(train: TrainConfig) -> dict[str, Any]:
    """What a run's training is, for comparing a directory's runs with a new invocation's."""
    return learned_settings(plain_data(train))


def learned_settings(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` (a run's recorded training configuration) without the settings that do not
    change what it learns; records written before a setting counted as such still hold it.
    The scenario's settings count as the configuration's own, as they were recorded before
    the configuration held a Scenario (issue 60)."""
    flat = {name: value for name, value in data.items() if name != "scenario"}
    scenario = data.get("scenario")
    if isinstance(scenario, dict):
        flat.update(scenario)
    return {name: value for name, value in flat.items() if name not in _UNLEARNED}


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
    base = TrainConfig.for_preset(train.preset, train.recipe)
    preset = [] if train.preset == TrainConfig().preset else ["--preset", train.preset]
    recipe = [] if train.recipe is None else ["--recipe", train.recipe]
    args = [*preset, *recipe, *command_args(train, base)]
    return [sys.executable, "-m", "overtake.trainers.train", *args]


def network_identity(train: TrainConfig) -> tuple[Any, ...]:
    """What runs must share to be members of one learner (:mod:`..members_run`): the network's
    architecture and what steps them in lock-step."""
    dqn = train.dqn
    return (
        train.algo,
        train.inputs,
        train.num_envs,
        train.total_steps,
        train.device,
        train.precision,
        json.dumps(train.overrides(), sort_keys=True, default=str),
        dqn.network,
        dqn.stack,
        dqn.lstm_cells,
        dqn.hidden_units,
        dqn.quantiles,
        dqn.loss,
        dqn.optimizer,
        dqn.rmsprop_centered,
        dqn.batch_size,
        dqn.train_every,
    )


def member_batches(
    runs: list[RunPlan], jobs: int, members: int | None
) -> list[tuple[RunPlan, ...]]:
    """``runs`` grouped into the processes that train them: the runs of one network (and
    lock-step settings, :func:`network_identity`) as members of one learner, at most
    ``members`` to a process (default: all the runs over ``jobs`` processes, rounded up, so
    that ``jobs`` processes finish together); the largest batches first."""
    per_batch = members or max(1, -(-len(runs) // max(jobs, 1)))
    groups: dict[tuple[Any, ...], list[RunPlan]] = {}
    for run in runs:
        groups.setdefault(network_identity(run.train), []).append(run)
    batches: list[tuple[RunPlan, ...]] = []
    for group in groups.values():
        count = -(-len(group) // per_batch)
        size = -(-len(group) // count)  # as even as the group allows
        batches += [tuple(group[i : i + size]) for i in range(0, len(group), size)]
    return sorted(batches, key=len, reverse=True)


def member_batch_command(trains: list[TrainConfig]) -> list[str]:
    """One process training ``trains`` as members (:mod:`..member_batch`): each member given as
    the arguments its own ``overtake-train`` would take."""
    members = [json.dumps(train_command(train)[3:]) for train in trains]
    return [sys.executable, "-m", "overtake.trainers.member_batch", "--members", *members]


def eval_command(evaluation: EvalConfig) -> list[str]:
    """``overtake-eval`` for ``evaluation``, as this interpreter's module."""
    args = command_args(evaluation, EvalConfig())
    return [sys.executable, "-m", "overtake.trainers.evaluate", *args]
