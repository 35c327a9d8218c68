"""``overtake-train``: DQN, Double DQN or Dueling DQN on overtake, in-process or over Zenoh.

The run directory holds:

- ``run.json``: the resolved configuration, the simulator's configuration, package versions,
  the seed and the code's commit;
- ``metrics.jsonl``: one JSON object per line, ``{"kind": "episode", ...}`` at every episode
  end (the papers' metrics) and ``{"kind": "train", ...}`` every ``log_every`` steps (loss,
  epsilon, Q of the taken actions, steps per second and where the time went);
- ``checkpoint.pt``: the latest checkpoint, written to a temporary file and renamed, so a kill
  never leaves a broken one; it describes itself (algorithm, inputs, preset, spaces, step);
- ``replay/``: the replay memory as memory-mapped files, written as they fill (``--no-replay-
  on-disk`` keeps it in memory).

``--resume`` continues a run from its checkpoint (``--resume-if-found`` too, and starts a
fresh run where there is none yet), exactly as the run never stopped would have gone on where
it can (:mod:`.resume`): the learner, the generators, the schedule, the replay, the frame
stacks and, in process, the episodes under way and the simulator's state. What it cannot
restore (no replay files; arenas on a server) it says in the life's run record: the replay
refills before learning goes on, the episodes restart.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from overtake.cli import Command, UsageError
from overtake.cli.allocator import keep_freed_memory
from overtake.client.wire.stopping import interrupt_waits
from overtake.envs.faces import VectorFace
from overtake.envs.shares import share_face

from .config.train_config import TrainConfig
from .learning.learner import execution_device
from .run.checkpoint import (
    CHECKPOINT_NAME,
    Checkpoint,
    CheckpointError,
    load_checkpoint,
)
from .run.lone_loop import LoneLoop
from .run.members_run import MembersRun, check_members, member_configs
from .run.training_run import TRAINING_STARTED, TrainingRun

__all__ = [
    "COMMAND",
    "TrainConfig",
    "main",
    "preset_in",
]

log = logging.getLogger("overtake.trainer")


def main(
    config: TrainConfig, envs: Any = None, stop: threading.Event | None = None
) -> dict[str, Any]:
    """Train; returns a summary (steps, episodes, last metrics, run directory).

    ``envs``: a ready Gymnasium vector environment (next-step autoreset, the overtake
    observation keys and ``info["action_mask"]``) to train on instead of the one the
    configuration describes; the caller keeps it and closes it.
    ``stop``: once set, the run ends after the step under way as it would at
    ``total_steps`` (a last log line, a checkpoint, the recording closed), and the summary
    says ``stopped``; the command (:data:`COMMAND`) sets it on SIGTERM and SIGINT.
    """
    if config.total_steps < 1 or config.num_envs < 1:
        raise UsageError("--total-steps and --num-envs must be >= 1")
    try:  # before a run directory, server or environment is touched
        execution_device(config.device, config.precision)
    except ValueError as error:
        raise UsageError(str(error)) from None
    keep_freed_memory()  # an update's tensors reuse their pages (allocator.py: 1.6x at 8 members)
    if config.torch_threads is not None:
        torch.set_num_threads(config.torch_threads)
    if config.seeds:
        if envs is not None:
            raise ValueError("members (--seeds) open their own environments, one per seed")
        return {"members": train_members(member_configs(config), stop, config.resolved_run_dir())}
    run_dir = config.resolved_run_dir()
    made_here = not run_dir.exists()
    resumed = prepare_run_dir(config, run_dir)
    overrides = config.overrides()
    own_envs = envs is None
    if own_envs:
        try:
            envs = config.where.open(
                config.preset,
                overrides,
                config.num_envs,
                parts=config.parts,
                observations=config.observations,
                ego_fields=config.ego_fields,
            )
        except BaseException:
            # A run that could not start (a bad override, no server) leaves no empty folder
            # behind that a later run would have to be told to resume or avoid.
            if made_here and not any(run_dir.iterdir()):
                run_dir.rmdir()
            raise
    elif envs.num_envs != config.num_envs:
        raise ValueError(
            f"the environment has {envs.num_envs} sub-environments, the "
            f"configuration says num_envs={config.num_envs}"
        )
    try:
        return LoneLoop(TrainingRun(config, envs, run_dir, overrides, resumed, stop)).run()
    finally:
        if own_envs:
            envs.close()


def train_members(
    configs: list[TrainConfig], stop: threading.Event | None = None, folder: Path | None = None
) -> list[dict[str, Any]]:
    """Train ``configs`` (lone runs' configurations, each with its own run directory) as
    members of one learner (:mod:`.members_run`); returns each member's summary. ``folder``:
    where ``--seeds`` put the members' directories, which must not hold other seeds' runs when
    resuming."""
    check_members(configs)
    if folder is not None and any(c.resume or c.resume_if_found for c in configs):
        wanted = {c.resolved_run_dir().name for c in configs}
        others = sorted(
            p.name
            for p in folder.glob("seed-*")
            if p.name not in wanted and (p / CHECKPOINT_NAME).exists()
        )
        if others and configs[0].resume:
            raise UsageError(
                f"--resume --seeds {' '.join(str(c.seed) for c in configs)}: {folder} holds "
                f"the runs of other seeds too ({', '.join(others)}); name them all, or another "
                "--run-dir"
            )
    made = [not c.resolved_run_dir().exists() for c in configs]
    resumed = [prepare_run_dir(c, c.resolved_run_dir()) for c in configs]
    # A member already at its budget has nothing to train (members step in lock-step).
    done = [
        r is not None and r.step >= c.total_steps for c, r in zip(configs, resumed, strict=True)
    ]
    for config in (c for c, finished in zip(configs, done, strict=True) if finished):
        log.info("%s is at its %d steps already", config.resolved_run_dir(), config.total_steps)
    configs = [c for c, finished in zip(configs, done, strict=True) if not finished]
    resumed = [r for r, finished in zip(resumed, done, strict=True) if not finished]
    made = [m for m, finished in zip(made, done, strict=True) if not finished]
    if not configs:
        return []
    envs: list[Any] = []
    try:
        envs.extend(open_members_envs(configs))
        members = MembersRun(
            configs,
            envs,
            [c.resolved_run_dir() for c in configs],
            [c.overrides() for c in configs],
            resumed,
            stop,
        )
        return members.run()
    except BaseException:
        for config, new in zip(configs, made, strict=True):
            run_dir = config.resolved_run_dir()
            if new and run_dir.exists() and not any(run_dir.iterdir()):
                run_dir.rmdir()
        raise
    finally:
        for env in envs:
            env.close()


def open_members_envs(configs: Sequence[TrainConfig]) -> list[VectorFace]:
    """Each member's environment. In process, members of one simulator configuration (preset,
    overrides, sensors, ego fields) get shares of one engine
    (:func:`~overtake.envs.shares.share_face`): every member's arenas step in one simulator
    call a round, each exactly as in an engine of its own (a checkpoint moves between the
    two). Elsewhere each member opens its own (with --connect, the server puts every member's
    arenas in its group)."""
    first = configs[0]
    alike = all(
        c.where.in_process
        and c.preset == first.preset
        and c.overrides() == first.overrides()
        and c.observations == first.observations
        and c.ego_fields == first.ego_fields
        for c in configs
    )
    if alike and len(configs) > 1:
        whole = first.where.open(
            first.preset,
            first.overrides(),
            sum(c.num_envs for c in configs),
            observations=first.observations,
            ego_fields=first.ego_fields,
        )
        return list(share_face(whole, [c.num_envs for c in configs]))
    opened: list[VectorFace] = []
    try:
        for config in configs:
            opened.append(
                config.where.open(
                    config.preset,
                    config.overrides(),
                    config.num_envs,
                    observations=config.observations,
                    ego_fields=config.ego_fields,
                )
            )
    except BaseException:
        for env in opened:
            env.close()
        raise
    return opened


def prepare_run_dir(config: TrainConfig, run_dir: Path) -> Checkpoint | None:
    """The checkpoint this run continues (None for a fresh run), once ``run_dir`` is known to
    be usable: a resume needs a compatible checkpoint there, a fresh run refuses to overwrite
    one. Creates ``run_dir``."""
    checkpoint_path = run_dir / CHECKPOINT_NAME
    resumed = None
    if config.resume or (config.resume_if_found and checkpoint_path.exists()):
        if not checkpoint_path.exists():
            raise CheckpointError(f"--resume: no checkpoint at {checkpoint_path}")
        resumed = load_checkpoint(checkpoint_path)
        resumed.check_compatible(config.algo, config.inputs, config.preset)
    elif checkpoint_path.exists():
        raise UsageError(
            f"{run_dir} already holds a run (checkpoint.pt); pass --resume (or "
            "--resume-if-found) to continue it or choose another --run-dir"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    return resumed


def preset_in(argv: list[str]) -> str:
    """The ``--preset`` a command line names (its last), or the default preset."""
    return option_in(argv, "--preset") or TrainConfig().preset


def option_in(argv: list[str], flag: str) -> str | None:
    """The value a command line gives ``flag`` (its last), or None."""
    value = None
    for i, arg in enumerate(argv):
        if arg == flag and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith(flag + "="):
            value = arg.split("=", 1)[1]
    return value


def _say_stopping(name: str) -> None:
    if not TRAINING_STARTED.is_set():
        # Still building the environments and the learner (seconds of compiled kernels and
        # a server's arenas): nothing to checkpoint yet, so the process ends now rather than
        # after its start-up (an experiment stopped while its trainers start waited 10-20 s).
        raise SystemExit(f"{name}: stopped before training began (nothing to resume yet)")
    log.warning(
        "%s: finishing the step under way, writing a checkpoint and stopping "
        "(send it again to stop at once); continue the run with --resume",
        name,
    )
    # A step waiting on a server that is gone would hold the stop for the step timeout (or
    # the reconnect timeout): such waits end now, a healthy round still completes.
    interrupt_waits()


def _report(_config: TrainConfig, summary: dict[str, Any]) -> None:
    print(json.dumps(summary, indent=2))


def _defaults(args: list[str]) -> TrainConfig:
    """The named preset's training, or its --recipe's (their defaults, which --help shows)."""
    recipe = option_in(args, "--recipe")
    return TrainConfig.for_preset(preset_in(args), None if recipe == "None" else recipe)


COMMAND = Command(
    "overtake-train",
    TrainConfig,
    main,
    report=_report,
    default=_defaults,
    stopping="event",
    stopped_hint="the run continues with --resume from its last checkpoint",
    on_stop=_say_stopping,
)


if __name__ == "__main__":
    COMMAND.run()
