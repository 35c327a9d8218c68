"""What a checkpoint holds beyond the learner, so that a stopped run resumes exactly.

A training run stopped (SIGTERM, the end of a machine) or killed between checkpoints and
resumed from its last checkpoint goes on bit for bit as the run never stopped would have, on
the same device: the learner and every generator are in the checkpoint already; this module
adds the rest, in three parts that a resume restores separately where it can:

- ``replay``: the replay memory's account of its rings (:meth:`.replay_memory.ReplayMemory.state`);
  its frames are the memory-mapped files in the run directory (``replay/``), which a
  checkpoint does not rewrite;
- ``episodes``: the episodes under way, on both sides: the environments' own state (the
  in-process simulator's snapshot, :meth:`~overtake.envs.faces.VectorFace.snapshot`) and
  the trainer's of them (the latest observations and action masks, the frame stacks, which
  environments restart next step, the safety layer's per-environment marks);
- ``schedule``: when the next update, target copy, log line and checkpoint are due.

Where a part cannot be restored (no replay files, or arenas that live on a server), the resume
does what a resume did before: it refills the replay before learning goes on, or starts new
episodes; the run's life record says which (:func:`.run_files.life_record`).

Stored as plain data in the checkpoint (``torch.save`` with ``weights_only`` loading accepts
tensors, not numpy arrays: :func:`storable` and :func:`loaded` convert).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from overtake.protocol import errors

from ..learning.replay_memory import FrameShapes, ReplayMemory, ReplayMismatch
from .checkpoint import save_checkpoint

if TYPE_CHECKING:
    from ..config.train_config import TrainConfig
    from .training_run import TrainingRun

logger = logging.getLogger("overtake.trainer")

# The counters of the training loop that say when things are next due, and how far it is.
SCHEDULE = ("next_update", "next_sync", "next_checkpoint", "next_log", "iteration", "unstored")


@dataclass(frozen=True)
class Schedule:
    """When the loop's next update, target copy, checkpoint and log line are due, its
    iterations, and the transitions played past the budget (:data:`SCHEDULE`)."""

    next_update: int
    next_sync: int
    next_checkpoint: int
    next_log: int
    iteration: int
    unstored: int


@dataclass(frozen=True)
class EpisodesUnderWay:
    """The episodes a checkpoint caught under way: the arenas' own state (the face's
    snapshot) and the trainer's of them."""

    arenas: list[Any]
    obs: dict[str, np.ndarray]
    env_mask: np.ndarray
    mask: np.ndarray
    starting: np.ndarray
    stacker: dict[str, Any]
    safety: dict[str, Any]


@dataclass(frozen=True)
class ResumeState:
    """What a checkpoint holds for an exact resume beyond the learner, typed: the replay's
    account of its files (None: not kept, or not usable), the episodes under way (None: not
    kept), the schedule, and the last episode's metrics. The run's books apply it
    (:class:`.training_run.TrainingRun`); nothing here writes into them."""

    replay: dict[str, Any] | None
    episodes: EpisodesUnderWay | None
    schedule: Schedule
    last_episode: dict[str, float]

    @classmethod
    def of(cls, stored: Mapping[str, Any]) -> ResumeState:
        """From a checkpoint's ``resume`` (:func:`take`'s plain data)."""
        plain = loaded(stored)
        episodes = plain.get("episodes")
        return cls(
            replay=plain.get("replay"),
            episodes=None
            if episodes is None
            else EpisodesUnderWay(
                arenas=list(episodes["arenas"]),
                obs={name: np.array(value) for name, value in episodes["obs"].items()},
                env_mask=np.array(episodes["env_mask"]),
                mask=np.array(episodes["mask"]),
                starting=np.array(episodes["starting"]),
                stacker=episodes["stacker"],
                safety=episodes["safety"],
            ),
            schedule=Schedule(**{name: int(value) for name, value in plain["schedule"].items()}),
            last_episode={k: float(v) for k, v in plain.get("last_episode", {}).items()},
        )


def storable(value: Any) -> Any:
    """``value`` with every numpy array a tensor (a copy) and every numpy scalar a number."""
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.array(value, copy=True))
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {key: storable(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [storable(item) for item in value]
    return value


def loaded(value: Any) -> Any:
    """:func:`storable`'s inverse: tensors back to numpy arrays."""
    if isinstance(value, torch.Tensor):
        return value.numpy()
    if isinstance(value, Mapping):
        return {key: loaded(item) for key, item in value.items()}
    if isinstance(value, list):
        return [loaded(item) for item in value]
    return value


def open_replay(
    config: TrainConfig,
    directory: Path,
    shapes: FrameShapes,
    stacked: tuple[str, ...],
    state: ResumeState | None,
) -> tuple[ReplayMemory, ResumeState | None]:
    """The run's replay memory: in memory only (``replay_on_disk`` off), the files of the life
    before in ``directory`` (a resume whose checkpoint accounts for them), or new files there;
    and the resume ``state``, without its replay part where those files could not be used."""
    dqn = config.dqn
    options: dict[str, Any] = dict(
        seed=config.seed,
        n_step=dqn.n_step,
        gamma=dqn.gamma,
        prioritized=dqn.prioritized,
        priority_alpha=dqn.priority_alpha,
        priority_eps=dqn.priority_eps,
    )
    args = (dqn.replay_size, config.num_envs, shapes, dqn.stack, stacked)
    if not config.replay_on_disk:
        return ReplayMemory(*args, **options), state
    saved = state.replay if state is not None else None
    if saved is not None and directory.is_dir():
        # The files of the life before: their spare slots are theirs.
        spare = int(saved["layout"]["slots"]) - dqn.replay_size // config.num_envs
        try:
            replay = ReplayMemory(
                *args, **options, directory=directory, spare=max(spare, 1), reopen=True
            )
            return replay, state
        except ReplayMismatch as error:
            logger.warning("%s: the replay starts empty and refills", error)
    replay = ReplayMemory(*args, **options, directory=directory, spare=spare_slots(config))
    return replay, None if state is None else dataclasses.replace(state, replay=None)


def spare_slots(config: TrainConfig) -> int:
    """Spare slots per replay ring (:class:`.replay_memory.ReplayMemory`): a checkpoint interval's
    writes, capped at a tenth of the ring (a checkpoint comes early where the spare slots
    run out first, :attr:`~.replay_memory.ReplayMemory.needs_checkpoint`)."""
    per_env = config.dqn.replay_size // config.num_envs
    interval = math.ceil(config.checkpoint_every / config.num_envs) + 2
    return max(1, min(interval, max(per_env // 10, 2 * config.dqn.stack + 2)))


def take(run: TrainingRun, replay_state: dict[str, Any] | None) -> dict[str, Any]:
    """The run's resume state now, between two iterations (``replay_state``: what the replay's
    :meth:`~.replay_memory.ReplayMemory.mark` returned, None for a replay in memory only)."""
    face, arenas = run.env.face, None
    # Between rounds only: where the loop learns while a round is in flight (--overlap), the
    # arenas are not kept, and a resume starts new episodes.
    if face is not None and can_restore(run) and not run.in_flight:
        try:
            arenas = face.snapshot()
        except errors.ProtocolError as error:  # a server gone: the checkpoint goes on without
            logger.warning("the arenas' state could not be kept (%s)", error)
    state: dict[str, Any] = {
        "replay": replay_state,
        "episodes": None,
        "schedule": {name: getattr(run, name) for name in SCHEDULE},
        "episodes_done": run.episodes,
        "last_episode": dict(run.last_episode),
    }
    if arenas is not None:
        state["episodes"] = {
            "arenas": list(arenas),
            "obs": dict(run.obs),
            "env_mask": run.env_mask,
            "mask": run.mask,
            "starting": run.starting,
            "stacker": run.stacker.state(),
            "safety": run.safety.state(),
        }
    return storable(state)


def write_checkpoint(run: TrainingRun) -> None:
    """The run's checkpoint now (:mod:`.checkpoint`), with its resume state: the replay's files
    flushed first, so that the checkpoint's account of them is on disk before it is."""
    replay_state = run.replay.mark() if run.replay.directory is not None else None
    save_checkpoint(
        run.checkpoint_path,
        learner=run.learner,
        config=run.config,
        overrides=run.overrides,
        space=run.space_description,
        net_shape=run.net_shape,
        step=run.step,
        episodes=run.episodes,
        rng_state=run.rng.bit_generator.state,
        resumes=run.resumes,
        resume=take(run, replay_state),
    )


def can_restore(run: TrainingRun) -> bool:
    """Whether the run's environment can snapshot and restore its arenas (overtake's own, in
    process)."""
    face = run.env.face
    return face is not None and face.restorable


def restore_replay(replay: ReplayMemory, state: ResumeState | None) -> bool:
    """Put the replay back as the checkpoint left it, where its files and the checkpoint's
    account of them are both there; returns whether it did."""
    if state is None or state.replay is None or replay.directory is None:
        return False
    replay.load_state(state.replay)
    return True


def put_back_arenas(run: TrainingRun, state: ResumeState | None) -> EpisodesUnderWay | None:
    """The arenas of the episodes under way put back into the run's environment, where the
    checkpoint holds them and the environment takes its snapshot; returns the trainer's side
    of those episodes for the books to apply, or None (new episodes start)."""
    episodes = state.episodes if state is not None else None
    if episodes is None or not can_restore(run):
        return None
    try:
        run.env.face.restore(episodes.arenas)  # type: ignore[union-attr]
    except (errors.ProtocolError, ValueError) as error:
        # A server of another configuration, or one that lost the group: new episodes.
        logger.warning("the arenas' kept state was refused (%s): new episodes start", error)
        return None
    return episodes
