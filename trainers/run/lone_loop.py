"""A lone run's loop: one run's books (:class:`.training_run.TrainingRun`: replay, stacks,
logs, checkpoints) stepped by its own learner (:class:`.learner.DQNLearner`), in lock-step or
overlapped with its server (``--overlap``). Members of one learner have a loop of their own
(:mod:`.members_run`) over the same books."""

from __future__ import annotations

import logging
import time
from typing import Any

from overtake.protocol import errors

from ..learning.learner import DQNLearner
from .training_run import TrainingRun

logger = logging.getLogger("overtake.trainer")


class LoneLoop:
    """Steps ``run`` until its ``total_steps`` (or its stop): act, step, store, learn."""

    def __init__(self, run: TrainingRun) -> None:
        learner = run.learner
        assert isinstance(learner, DQNLearner), "a member is stepped by its members' loop"
        self.run_books, self.learner = run, learner

    def run(self) -> dict[str, Any]:
        """Train, checkpointing on the way and at the end; returns the run's summary."""
        books = self.run_books
        books.open()
        try:
            iteration = self.part_iteration if books.config.overlapped else self.iteration
            try:
                while not books.finished:
                    iteration()
                self.finish_parts()
            except errors.Interrupted as error:  # stopped while its server was gone
                logger.warning("%s: the run ends at its last whole step, %d", error, books.step)
            books.wind_up()
        finally:
            books.close()
        return books.summary()

    def iteration(self) -> None:
        """One step of every environment: act, step, store what came back, learn; log and
        checkpoint when due."""
        books = self.run_books
        t0 = time.perf_counter()
        epsilon = books.dqn.epsilon(books.step)
        actions, q = self.learner.act(books.stacker.observation(), books.mask, epsilon, books.rng)
        books.acted(q)
        t1 = time.perf_counter()
        seen = books.send(actions)
        outcome = books.env.recv(0) if books.sends else books.env.step(actions)
        t2 = time.perf_counter()
        stored = books.absorb(seen, actions, q, outcome)
        t3 = time.perf_counter()
        self.learn()
        t4 = time.perf_counter()
        books.account(epsilon, stored, (t0, t1, t2, t3, t4))

    def part_iteration(self) -> None:
        """Overlap: act for one part and send its actions; learn while the server simulates;
        then take the Steps of the part sent longest ago and store them; log and checkpoint
        when due. With one part the update runs during the round trip (it sees the
        transitions up to the previous iteration); with two the server also plays one part
        while the learner acts on the other."""
        books = self.run_books
        env = books.env
        t0 = time.perf_counter()
        part = books.env_calls % env.count
        rows = env.rows[part]
        epsilon = books.dqn.epsilon(books.step)
        stacked = books.stacker.observation()
        if env.count > 1:
            stacked = {k: v[rows] for k, v in stacked.items()}
        actions, q = self.learner.act(stacked, books.mask[rows], epsilon, books.rng)
        books.window.shield_overrides += books.safety.count(
            env.indices[part], q, books.env_mask[rows], books.mask[rows]
        )
        t1 = time.perf_counter()
        env.label_step(books.step)
        seen = {k: v[rows].copy() for k, v in books.obs.items()} if part == 0 else {}
        env.send(part, actions)
        books.in_flight[part] = (actions, q, seen)
        books.env_calls += 1
        t2 = time.perf_counter()
        self.learn()
        t3 = time.perf_counter()
        stored, waited = 0, 0.0
        oldest = books.env_calls % env.count  # the next to send is the one sent longest ago
        if oldest in books.in_flight and len(books.in_flight) == env.count:
            stored, waited = self.receive_part(oldest)
        t4 = time.perf_counter()
        # In account's order (act, env, replay, update): the wait is env's, the rest replay's.
        env_end = t2 + waited
        replay_end = env_end + (t4 - t3 - waited)
        books.account(epsilon, stored, (t0, t1, env_end, replay_end, t4))

    def receive_part(self, part: int) -> tuple[int, float]:
        """Take part ``part``'s Steps and store them; returns the transitions stored and the
        seconds spent waiting for them."""
        books = self.run_books
        envs, rows = books.env.indices[part], books.env.rows[part]
        actions, q, seen = books.in_flight.pop(part)
        start = time.perf_counter()
        obs, reward, terminated, truncated, info = books.env.recv(part)
        waited = time.perf_counter() - start
        for name, value in obs.items():
            books.obs[name][rows] = value
        if part == 0:
            books._record_car_view(seen, actions, q, reward, info)
        ends = books.dqn.stored_terminal(terminated, truncated)
        stored, taken = books._store(envs, actions, reward, ends, info)
        books._end_episodes(envs, terminated, truncated, info, taken)
        return stored, waited

    def finish_parts(self) -> None:
        """Take the Steps of the parts still in flight at the end of the run, without storing
        them (the run has its steps): the server's rounds and the trainer's sends agree."""
        books = self.run_books
        for part in sorted(books.in_flight):
            books.env.recv(part)
        books.in_flight.clear()

    def learn(self) -> None:
        """One update per ``train_every`` steps stored (once the replay holds ``warm``
        transitions), and the target network's sync every ``target_update_steps``."""
        books = self.run_books
        while books.step >= books.next_update:
            books.next_update += books.dqn.train_every
            if len(books.replay) >= books.warm:
                beta = books.dqn.priority_beta(books.step, books.config.total_steps)
                batch = books.replay.sample(books.dqn.batch_size, beta=beta)
                stats = self.learner.update(batch)
                if batch.leaves is not None:
                    books.replay.update_priorities(batch.leaves, stats["td_error"])
                books.window.losses.append(stats["loss"])
                books.window.q_taken.append(stats["q_taken"])
        if books.step >= books.next_sync:
            self.learner.sync_target()
            books.next_sync = books.step + books.dqn.target_update_steps
