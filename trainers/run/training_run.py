"""One life of a training run (its start or one resume): the learner, the replay and the
frame stacker, the loop that steps the environments until ``total_steps`` transitions are
stored (lock-step or overlapped with the server), and the run's files. ``overtake-train``
(:mod:`.train`) builds it from its configuration."""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from overtake.protocol import ACTION_COUNT

from ..learning.learner import ALGOS, DQNLearner, LearnerState, network_shape
from ..learning.network import INPUT_SENSORS
from ..learning.replay_memory import FrameStacker
from . import resume as resuming
from .checkpoint import CHECKPOINT_NAME, REPLAY_DIR_NAME, Checkpoint, plain_data
from .env_parts import EnvParts
from .observations import describe_space, frame_shapes
from .run_files import MetricsLog, life_record, run_record
from .run_log import LogWindow, progress_bar
from .run_recording import RunRecording
from .shielding import SafetyLayer, TrainingShield

if TYPE_CHECKING:
    from ..config.train_config import TrainConfig


logger = logging.getLogger("overtake.trainer")

TRAINING_STARTED = threading.Event()
"""Set once a run of this process has opened its books (its run record, logs, episodes):
until then a stop has nothing to checkpoint (:func:`.train._say_stopping`)."""


class TrainingRun:
    """One life of a training run (its start or one resume) in its run directory.

    It holds the learner, the replay and the frame stacker, steps the vector environment
    until ``total_steps`` transitions are stored, and writes the run's files: the run record,
    the metrics log, the Rerun recording and the checkpoints.
    """

    # Set by run(): its outputs, then (the environments started) the latest observation and
    # mask, the environments autoresetting next, the clock and the next log line's window.
    log: MetricsLog
    recording: RunRecording | None
    bar: Any
    obs: dict[str, np.ndarray]
    mask: np.ndarray
    starting: np.ndarray
    everyone: np.ndarray
    started: float
    window: LogWindow

    def __init__(
        self,
        config: TrainConfig,
        envs: Any,
        run_dir: Path,
        overrides: dict[str, Any],
        resumed: Checkpoint | None,
        stop: threading.Event | None = None,
        learner: LearnerState | None = None,
    ) -> None:
        """``learner``: the run's place in a members' learner (:mod:`.members_run`, which
        then acts and learns for it); None: a lone :class:`.learner.DQNLearner` of its own."""
        self.config, self.dqn, self.envs = config, config.dqn, envs
        self.stop = stop if stop is not None else threading.Event()
        # Overlap steps the parts in turn: p's actions go out, the oldest part sent comes back.
        self.env = EnvParts(envs, config.num_envs)
        # Lock-step on overtake's face of one part: send, then receive (other work between
        # the two, for a loop of several runs); any other environment: step.
        self.sends = self.env.face is not None and self.env.count == 1
        self.run_dir, self.overrides = run_dir, overrides
        self.checkpoint_path = run_dir / CHECKPOINT_NAME
        self.space = envs.single_observation_space
        self.space_description = describe_space(self.space)
        # What an exact resume restores beyond the learner (resume.py), where it can.
        self.resume_state = (
            resuming.ResumeState.of(resumed.resume)
            if resumed is not None and resumed.resume is not None
            else None
        )
        self._build_learner(learner)
        self.step, self.episodes, self.resumes = 0, 0, 0
        self.resumed_at_step: int | None = None
        # What a resume restored of its checkpoint (run_files.life_record).
        self.restored: dict[str, bool] | None = None
        self.env_seed = config.seed
        self.last_episode: dict[str, float] = {}
        self.iteration = 0
        self.in_flight: dict[int, tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]] = {}
        self.env_calls = 0  # envs.step, or with overlap send: one each, autoreset steps included
        self.unstored = 0  # transitions played past the budget, in its last step: not stored
        # The shield (--shield, client/policies/shield.py) and what is stored where it acted.
        self.safety = SafetyLayer(
            TrainingShield(self.env.behaviour_spec, self.stacker, config.inputs)
            if config.shield
            else None,
            self.dqn,
            config.num_envs,
        )
        if resumed is not None:
            self._restore(resumed)
        self.next_update = self.step + self.dqn.train_every
        self.next_sync = self.step + self.dqn.target_update_steps
        self.next_checkpoint = self.step + config.checkpoint_every
        self.next_log = self.step + config.log_every
        if self.resume_state is not None:
            self._apply_schedule(self.resume_state.schedule)
            self.last_episode = dict(self.resume_state.last_episode)
        # Updates wait for this many transitions (again after a resume without its replay).
        self.warm = max(
            self.dqn.batch_size,
            min(self.dqn.learning_starts, (self.replay.per_env - 1) * config.num_envs),
        )

    def _build_learner(self, learner: LearnerState | None) -> None:
        """The learner (seeded; or the members' place given), its replay memory and frame
        stacker, and the random generator of its exploration."""
        config, dqn = self.config, self.dqn
        shapes = frame_shapes(self.space, config.inputs, f"preset {config.preset}'s environment")
        stacked = INPUT_SENSORS[config.inputs]
        self.net_shape = network_shape(self.space, config.inputs, ACTION_COUNT, dqn.stack)
        if learner is None:
            torch.manual_seed(config.seed)
            learner = DQNLearner.for_algo(
                config.algo, self.net_shape, config.inputs, dqn, config.device, config.precision
            )
        self.learner: LearnerState = learner
        self.replay, self.resume_state = resuming.open_replay(
            config, self.run_dir / REPLAY_DIR_NAME, shapes, stacked, self.resume_state
        )
        self.stacker = FrameStacker(config.num_envs, shapes, dqn.stack, stacked)
        self.rng = np.random.default_rng(config.seed)

    def _restore(self, resumed: Checkpoint) -> None:
        """Carry on from ``resumed``: the learner, the counts, the random generators, and the
        replay where it was saved."""
        restored = self.learner.load_state_dict(resumed.learner)
        self.step, self.episodes = resumed.step, resumed.episodes
        self.resumed_at_step = resumed.step
        self.resumes = resumed.resumes + 1
        self.rng.bit_generator.state = resumed.rng_state
        torch.set_rng_state(resumed.torch_rng_state)
        # Where the episodes under way cannot be restored, new ones, not the ones of the first
        # life: different environment seeds.
        self.env_seed = self.config.seed + 1_000_003 * self.resumes
        replay_restored = resuming.restore_replay(self.replay, self.resume_state)
        state = self.resume_state
        arenas = state is not None and state.episodes is not None and resuming.can_restore(self)
        self.restored = {**restored, "replay": replay_restored, "arenas": arenas}

    def _apply_schedule(self, schedule: resuming.Schedule) -> None:
        """When things are next due, as a checkpoint left it."""
        self.next_update, self.next_sync = schedule.next_update, schedule.next_sync
        self.next_checkpoint, self.next_log = schedule.next_checkpoint, schedule.next_log
        self.iteration, self.unstored = schedule.iteration, schedule.unstored

    def _apply_episodes(self, episodes: resuming.EpisodesUnderWay) -> None:
        """The trainer's side of the episodes a checkpoint caught under way (their arenas
        already put back): observations, masks, autoresets due, frame stacks, safety marks."""
        self.obs = {name: np.array(value) for name, value in episodes.obs.items()}
        self.env_mask = np.array(episodes.env_mask)
        self.mask = np.array(episodes.mask)
        self.starting = np.array(episodes.starting)
        self.stacker.load_state(episodes.stacker)
        self.safety.load_state(episodes.safety)

    def _life_file(self, stem: str, suffix: str) -> Path:
        """``stem.suffix`` for a run's start, ``stem-resume-N.suffix`` for its N-th resume."""
        name = stem if self.resumed_at_step is None else f"{stem}-resume-{self.resumes}"
        return self.run_dir / f"{name}{suffix}"

    @property
    def finished(self) -> bool:
        """Whether the run has its ``total_steps`` or was asked to stop."""
        return self.step >= self.config.total_steps or self.stop.is_set()

    def open(self) -> None:
        """The life's run record, metrics log and recording; the episodes started (or put
        back). :meth:`close` closes what this opened, whatever happened between."""
        TRAINING_STARTED.set()
        self._write_run_record()
        self.log = MetricsLog(self.run_dir / "metrics.jsonl")
        self.recording, self.bar = None, None
        self.recording = RunRecording.open(
            self.config.recording,
            self._life_file("trainer", ".rrd"),
            self.run_dir.name or "run",
            self.config.algo,
            self.env,
        )
        self._start_episodes()

    def wind_up(self) -> None:
        """The run's last log line (of a partial window) and its checkpoint."""
        if self.step > self.window.start_step:
            # A partial window: a learning curve (Fayjie's per 3,000 steps) keeps its end;
            # the next line stays due where it was (for a resume).
            next_log = self.next_log
            self._log_training(self.dqn.epsilon(self.step))
            self.next_log = next_log
        self._checkpoint()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        if hasattr(self, "log"):
            self.log.close()
        if getattr(self, "recording", None) is not None:
            self.recording.close()  # type: ignore[union-attr]

    def summary(self) -> dict[str, Any]:
        """What :func:`.train.main` returns of this life."""
        return {
            "run_dir": str(self.run_dir),
            "steps": self.step,
            "resumed_at_step": self.resumed_at_step,
            # envs.step (or send) calls this life, autoresets included: rounds, +2 a server loss.
            "env_steps_called": self.env_calls,
            "parts": self.env.count,
            # Decisions where the shield forbade the network's greedy choice (with --shield).
            "shield_overrides": self.safety.overrides,
            # Transitions played beyond the budget in the last step (not stored nor learned).
            "unstored": self.unstored,
            **self.env.remote_facts(),
            "episodes": self.episodes,
            "updates": self.learner.updates,
            "last_episode": self.last_episode,
            "stopped": self.step < self.config.total_steps,
        }

    def _write_run_record(self) -> None:
        """run.json (run-resume-N.json): what this life of the run is, to reproduce it."""
        algo = ALGOS[self.config.algo]
        record = run_record(
            config=plain_data(self.config),
            algo={"name": self.config.algo, "double": algo.double, "head": algo.head},
            overrides=self.overrides,
            sim_config=self.env.sim_config,
            observation_space=self.space_description,
            network=dataclasses.asdict(self.net_shape),
            seed=self.config.seed,
            resumes=self.resumes,
            resumed_at_step=self.resumed_at_step,
            trainer=self.env.remote_facts().get("trainer"),
            replay_bytes=self.replay.nbytes,
            replay_naive_bytes=self.replay.naive_nbytes(),
            life=life_record(
                self.step,
                str(self.learner.device),
                self.config.precision,
                self.restored,
                self.warm,
                members=int(getattr(self.learner, "batch", 1)),
            ),
        )
        self._life_file("run", ".json").write_text(json.dumps(record, indent=2, default=str))

    def _start_episodes(self) -> None:
        """Reset every environment and start its frame stack and its replay ring; or, on a
        resume that can, put the episodes under way back as the checkpoint left them."""
        everyone = self.everyone = np.arange(self.config.num_envs)
        restoring = self.restored is not None and self.restored["arenas"]
        episodes = resuming.put_back_arenas(self, self.resume_state) if restoring else None
        if episodes is not None:
            self._apply_episodes(episodes)
            if self.restored is not None and not self.restored["replay"]:
                # The episodes go on, into an empty replay: each ring starts from the frame now
                # (its stacks repeat that frame until the ring holds the ones after it).
                self.replay.start(everyone, self.obs, self.mask)
        else:
            if restoring and self.restored is not None:  # refused: the life record says so
                self.restored["arenas"] = False
                self._write_run_record()
            obs, info = self.envs.reset(seed=self.env_seed)
            # Own, writable copies: parts write their rows into them as their Steps come back.
            self.obs = {k: np.array(v) for k, v in obs.items()}
            self.stacker.reset(everyone, self.obs)
            self.env_mask = np.array(info["action_mask"])
            self.mask = self.safety.mask(everyone, self.env_mask)
            self.replay.start(everyone, self.obs, self.mask)
            self.starting = np.zeros(self.config.num_envs, dtype=bool)
        self.started = time.perf_counter()
        self.window = LogWindow(self.step, self.started)
        self.bar = progress_bar(self.config, self.step)

    # One lock-step iteration in parts, for the loops (lone_loop, members_run): acted, send,
    # (the environment's step), absorb, then the learning, and the accounting.

    def acted(self, q: np.ndarray) -> None:
        """Count the shield's overrides of the network's greedy choices ``q`` (N, actions)."""
        self.window.shield_overrides += self.safety.count(
            self.everyone, q, self.env_mask, self.mask
        )

    def send(self, actions: np.ndarray) -> dict[str, np.ndarray]:
        """Send every environment's actions (overtake's face; another environment is stepped
        in :meth:`absorb`'s caller); returns the observations they were chosen on."""
        seen = self.obs
        self.env.label_step(self.step)
        if self.sends:
            self.env.send(0, actions)
        self.env_calls += 1
        return seen

    def absorb(
        self, seen: dict[str, np.ndarray], actions: np.ndarray, q: np.ndarray, outcome: Any
    ) -> int:
        """Store what the step of every environment returned (``outcome``: the five-tuple of
        a Gymnasium vector step); returns the transitions stored."""
        self.obs, reward, terminated, truncated, info = outcome
        self._record_car_view(seen, actions, q, reward, info)
        ends = self.dqn.stored_terminal(terminated, truncated)
        stored, taken = self._store(self.everyone, actions, reward, ends, info)
        self._end_episodes(self.everyone, terminated, truncated, info, taken)
        return stored

    def account(
        self, epsilon: float, stored: int, times: tuple[float, float, float, float, float]
    ) -> None:
        """An iteration's time split (act, env, replay, update, from its five clock readings)
        and progress; a log line and a checkpoint when due."""
        self.window.add_times(times)
        if self.bar is not None and stored:
            self.bar.update(stored)
        if self.step >= self.next_log:
            self._log_training(epsilon)
        if self.step >= self.next_checkpoint:
            self.next_checkpoint = self.step + self.config.checkpoint_every
            self._checkpoint()
        elif self.replay.needs_checkpoint:
            # The replay's spare slots are taken: a checkpoint now, off the schedule.
            self._checkpoint()

    def _record_car_view(
        self,
        seen: dict[str, np.ndarray],
        actions: np.ndarray,
        q: np.ndarray,
        reward: np.ndarray,
        info: dict[str, Any],
    ) -> None:
        """Environment 0's view to Rerun every record_every iterations (not for its autoreset
        step, whose action the environment ignored)."""
        if (
            self.recording is not None
            and not self.starting[0]
            and self.iteration % self.config.recording.record_every == 0
        ):
            self.recording.car_view(self.step, seen, actions, q, reward, info)
        self.iteration += 1

    def _store(
        self,
        envs: np.ndarray,
        actions: np.ndarray,
        reward: np.ndarray,
        terminated: np.ndarray,
        info: dict[str, Any],
    ) -> tuple[int, np.ndarray]:
        """Store what a step of the environments ``envs`` returned (their rows of
        ``self.obs``; the other arrays have a row per environment of ``envs``); returns how
        many transitions that added, and which of the rows were taken (stored, or a new
        episode's start).

        Gymnasium next-step autoreset: environments that ended last step were reset by this
        one (its action ignored, reward 0); their observation starts a new episode, no
        transition. The others add one transition each, as long as the budget lasts: the step
        that reaches ``total_steps`` stores only what is left of it (the first environments'
        transitions), so that a run's step N is N stored transitions everywhere (its
        checkpoint, its metrics, the experiments' tables, resume); the rest are counted in
        ``unstored`` and not learned from. With the shield, the masks stored (what the
        target's max runs over) and acted on are the environment's and the shield's together;
        the actions and rewards stored are the safety layer's (:meth:`SafetyLayer.stored`)."""
        mask = info["action_mask"]
        earned = reward  # the log's: a learner's penalty changes what is stored, not what it earned
        actions, reward = self.safety.stored(envs, actions, reward, info)
        starting = self.starting[envs]
        moving = np.flatnonzero(~starting)
        room = self.config.total_steps - self.step
        if moving.size > room:
            self.unstored += moving.size - room
            moving = moving[:room]
        taken = starting.copy()
        taken[moving] = True
        fresh = np.flatnonzero(starting)
        if fresh.size:
            self.stacker.reset(envs[fresh], {k: v[envs[fresh]] for k, v in self.obs.items()})
        if moving.size:
            self.stacker.push(envs[moving], {k: v[envs[moving]] for k, v in self.obs.items()})
        self.env_mask[envs] = mask
        mask = self.mask[envs] = self.safety.mask(envs, mask)
        if fresh.size:
            ids = envs[fresh]
            sub = {k: v[ids] for k, v in self.obs.items()}
            self.replay.start(ids, sub, mask[fresh])
        if moving.size:
            ids = envs[moving]
            sub = {k: v[ids] for k, v in self.obs.items()}
            self.replay.add(
                ids, actions[moving], reward[moving], terminated[moving], sub, mask[moving]
            )
            self.step += moving.size
            self.window.reward_sum += float(earned[moving].sum())
        return int(moving.size), taken

    def _end_episodes(
        self,
        envs: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        info: dict[str, Any],
        taken: np.ndarray,
    ) -> None:
        """Log the episodes this step of the environments ``envs`` ended (their metrics) and
        mark those environments for the autoreset step that follows; an episode whose last
        transition was past the budget (not ``taken``) did not end in this run."""
        ended = (terminated | truncated) & ~self.starting[envs] & taken
        for i in np.flatnonzero(ended):
            self.episodes += 1
            self.last_episode = {name: float(values[i]) for name, values in info["metrics"].items()}
            self.log.write(
                {
                    "kind": "episode",
                    "step": self.step,
                    "episode": self.episodes,
                    "env": int(envs[i]),
                    "wall_s": round(time.perf_counter() - self.started, 3),
                    "terminated": bool(terminated[i]),
                    **self.last_episode,
                }
            )
            if self.recording is not None:
                self.recording.episode(self.step, self.last_episode)
        self.starting[envs] = ended

    def _log_training(self, epsilon: float) -> None:
        """A ``{"kind": "train", ...}`` line (to metrics.jsonl, Rerun and the progress bar)
        over the steps since the last one."""
        now = time.perf_counter()
        entry = self.window.train_line(
            self.step,
            now,
            episodes=self.episodes,
            wall_s=round(now - self.started, 3),
            epsilon=epsilon,
            updates=self.learner.updates,
            replay=len(self.replay),
            shielded=self.safety.shield is not None,
        )
        self.log.write(entry)
        if self.recording is not None:
            self.recording.learning(self.step, entry)
        if self.bar is not None:
            last = self.last_episode
            self.bar.set_postfix(
                eps=f"{epsilon:.2f}",
                loss=entry["loss"] and f"{entry['loss']:.3f}",
                speed=last and f"{last['avg_speed_kmh']:.1f}",
                ret=last and f"{last['return']:.0f}",
                refresh=False,
            )
        self.window = LogWindow(self.step, now)
        self.next_log = self.step + self.config.log_every

    def _checkpoint(self) -> None:
        resuming.write_checkpoint(self)
