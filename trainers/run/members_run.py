"""Several training runs in one process, as members of one learner (:mod:`.member_learner`).

Each member is a whole run: its own run directory, configuration (seed, learning rate, any
setting that leaves the network's shapes alone), replay memory, frame stacks, exploration
generator, episodes, metrics, recording and checkpoints, all kept by a
:class:`.training_run.TrainingRun` of its own exactly as a lone run keeps them, so
``overtake-eval``, ``overtake-replay``, ``overtake-export``, a lone ``--resume`` and the
experiments' reports read a member's directory unchanged. Its environments are its own vector
environment, seeded as a lone run of its seed seeds them.

What the members share is the loop (:class:`MembersRun`): each iteration every member's
stacked observations go through one forward pass (each member's epsilon and generator choose
its actions), every member's actions go out before any member's steps come back (a server
plays them together), and every member that has an update due is updated in one backward pass
and one optimiser step. Members step in lock-step: they share ``num_envs``, ``total_steps``,
``train_every`` and the batch size.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from overtake.cli import UsageError
from overtake.protocol import ACTION_COUNT, errors

from ..learning.dqn_config import ALGOS
from ..learning.learner import Precision, network_shape
from ..learning.member_learner import MembersLearner
from ..learning.member_optim import shared_setting
from .checkpoint import Checkpoint
from .training_run import TrainingRun

if TYPE_CHECKING:
    from ..config.train_config import TrainConfig

logger = logging.getLogger("overtake.trainer")

# What members must share to step and learn in lock-step (beyond the network's shapes, which
# the members' learner checks).
LOCK_STEP_SETTINGS = ("num_envs", "total_steps", "algo", "inputs", "device", "precision")
LOCK_STEP_DQN_SETTINGS = ("batch_size", "train_every", "stack", "network", "optimizer")


class MemberPlace:
    """Member ``index`` of a :class:`.member_learner.MembersLearner`, as its run's books see a
    learner (:class:`.learner.LearnerState`): its update count and its state as a lone
    learner's."""

    def __init__(self, members: MembersLearner, index: int) -> None:
        self.members, self.index = members, index
        self.device: torch.device = members.device
        self.precision: Precision = members.precision

    @property
    def batch(self) -> int:
        """The members this one trains beside, itself included (its run record says so)."""
        return self.members.members

    @property
    def updates(self) -> int:
        return int(self.members.updates[self.index])

    def state_dict(self) -> dict[str, Any]:
        return self.members.member_state_dict(self.index)

    def load_state_dict(self, state: dict[str, Any]) -> dict[str, bool]:
        return self.members.load_member_state_dict(self.index, state)


def check_members(configs: Sequence[TrainConfig]) -> None:
    """Refuse, in one line, members that cannot train together: none, a seed or a run
    directory named twice, or settings that differ where lock-step needs them alike."""
    if not configs:
        raise UsageError("members: no run to train")
    dirs = [c.resolved_run_dir() for c in configs]
    if len(set(dirs)) != len(dirs):
        raise UsageError(f"members: a run directory is named twice: {[str(d) for d in dirs]}")
    try:
        for name in LOCK_STEP_SETTINGS:
            shared_setting(configs, name)
        dqns = [c.dqn for c in configs]
        for name in LOCK_STEP_DQN_SETTINGS:
            shared_setting(dqns, name)
    except ValueError as error:
        raise UsageError(f"members train in lock-step on one network: {error}") from None
    if any(c.overlap == "on" for c in configs):
        # ("auto" means lock-step for members: their rounds are played while the others'
        # are sent.)
        raise UsageError(
            "members step in lock-step: --overlap on is a lone run's (with --connect, every "
            "member's actions go out before any member's round is taken)"
        )


class MembersRun:
    """The members' runs (their books, :class:`.training_run.TrainingRun` each) stepped,
    acted for and updated together."""

    def __init__(
        self,
        configs: Sequence[TrainConfig],
        envs: Sequence[Any],
        run_dirs: Sequence[Path],
        overrides: Sequence[dict[str, Any]],
        resumed: Sequence[Checkpoint | None],
        stop: threading.Event | None = None,
    ) -> None:
        check_members(configs)
        self.stop = stop if stop is not None else threading.Event()
        first = configs[0]
        space = envs[0].single_observation_space
        shape = network_shape(space, first.inputs, ACTION_COUNT, first.dqn.stack)
        try:
            self.learner = MembersLearner(
                shape,
                first.inputs,
                [c.dqn for c in configs],
                ALGOS[first.algo],
                [c.seed for c in configs],
                device=first.device,
                precision=first.precision,
            )
        except ValueError as error:
            raise UsageError(f"members: {error}") from None
        self.books = [
            TrainingRun(
                config, env, run_dir, over, checkpoint, self.stop, MemberPlace(self.learner, k)
            )
            for k, (config, env, run_dir, over, checkpoint) in enumerate(
                zip(configs, envs, run_dirs, overrides, resumed, strict=True)
            )
        ]

    @property
    def finished(self) -> bool:
        return all(book.finished for book in self.books)

    def run(self) -> list[dict[str, Any]]:
        """Train every member to its ``total_steps`` (or until stopped), checkpointing each on
        its schedule and at the end; returns each member's summary."""
        opened: list[TrainingRun] = []
        try:
            for book in self.books:
                book.open()
                opened.append(book)
            try:
                while not self.finished:
                    self._iteration()
            except errors.Interrupted as error:
                logger.warning("%s: the members end at their last whole step", error)
            for book in self.books:
                book.wind_up()
        finally:
            for book in opened:
                book.close()
        return [book.summary() for book in self.books]

    def _iteration(self) -> None:
        """One step of every member's environments: act for all, send all, absorb all, learn;
        each member logs and checkpoints when due. A member already at its budget (resumed
        from a later checkpoint than the others) waits: the network still takes its rows,
        its choices are dropped and its generator is left alone."""
        going = [not book.finished for book in self.books]
        books = [book for book, on in zip(self.books, going, strict=True) if on]
        t0 = time.perf_counter()
        epsilons = [book.dqn.epsilon(book.step) for book in self.books]
        everyone = self.learner.act(
            [book.stacker.observation() for book in self.books],
            [book.mask for book in self.books],
            epsilons,
            [
                book.rng if on else np.random.default_rng(0)
                for book, on in zip(self.books, going, strict=True)
            ],
        )
        chosen = [c for c, on in zip(everyone, going, strict=True) if on]
        epsilons = [e for e, on in zip(epsilons, going, strict=True) if on]
        for book, (_, q) in zip(books, chosen, strict=True):
            book.acted(q)
        t1 = time.perf_counter()
        seen = [book.send(actions) for book, (actions, _) in zip(books, chosen, strict=True)]
        outcomes = [
            book.env.recv(0) if book.sends else book.env.step(actions)
            for book, (actions, _) in zip(books, chosen, strict=True)
        ]
        t2 = time.perf_counter()
        stored = [
            book.absorb(s, actions, q, outcome)
            for book, s, (actions, q), outcome in zip(books, seen, chosen, outcomes, strict=True)
        ]
        t3 = time.perf_counter()
        self._learn()
        t4 = time.perf_counter()
        for book, epsilon, count in zip(books, epsilons, stored, strict=True):
            book.account(epsilon, count, (t0, t1, t2, t3, t4))

    def _learn(self) -> None:
        """Every update due (``train_every`` steps stored, the replay warm), members together:
        a member whose update is not due or whose replay is not warm yet sits that update out;
        then each member's target copy when due."""
        books = self.books
        while True:
            due = [book.step >= book.next_update for book in books]
            if not any(due):
                break
            batches = []
            for book, is_due in zip(books, due, strict=True):
                batch = None
                if is_due:
                    book.next_update += book.dqn.train_every
                    if len(book.replay) >= book.warm:
                        beta = book.dqn.priority_beta(book.step, book.config.total_steps)
                        batch = book.replay.sample(book.dqn.batch_size, beta=beta)
                batches.append(batch)
            if all(batch is None for batch in batches):
                continue
            stats = self.learner.update(batches)
            for book, batch, member in zip(books, batches, stats, strict=True):
                if batch is None:
                    continue
                if batch.leaves is not None:
                    book.replay.update_priorities(batch.leaves, member["td_error"])
                book.window.losses.append(member["loss"])
                book.window.q_taken.append(member["q_taken"])
        syncing = [k for k, book in enumerate(books) if book.step >= book.next_sync]
        if syncing:
            self.learner.sync_target(syncing)
            for k in syncing:
                books[k].next_sync = books[k].step + books[k].dqn.target_update_steps


def member_configs(config: TrainConfig) -> list[TrainConfig]:
    """``overtake-train --seeds K ...``: one lone run's configuration per seed, each in
    ``<run_dir>/seed-<k>``."""
    repeated = sorted({seed for seed in config.seeds if config.seeds.count(seed) > 1})
    if repeated:
        raise UsageError(f"--seeds names seed {repeated[0]} more than once: {list(config.seeds)}")
    base = config.resolved_run_dir()
    # One progress bar: the members step together, and several bars would write over each
    # other.
    return [
        dataclasses.replace(
            config,
            seed=seed,
            seeds=(),
            run_dir=base / f"seed-{seed}",
            progress=config.progress and index == 0,
        )
        for index, seed in enumerate(config.seeds)
    ]


__all__ = ["MemberPlace", "MembersRun", "check_members", "member_configs"]
