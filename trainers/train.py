"""``overtake-train``: DQN, Double DQN or Dueling DQN on overtake, in-process or over Zenoh.

The run directory holds:

- ``run.json``: the resolved configuration, the simulator's configuration, package versions,
  the seed and the code's commit;
- ``metrics.jsonl``: one JSON object per line, ``{"kind": "episode", ...}`` at every episode
  end (the papers' metrics) and ``{"kind": "train", ...}`` every ``log_every`` steps (loss,
  epsilon, Q of the taken actions, steps per second and where the time went);
- ``checkpoint.pt``: the latest checkpoint, written to a temporary file and renamed, so a kill
  never leaves a broken one; it describes itself (algorithm, inputs, preset, spaces, step);
- ``replay.npz`` with ``--save-replay``: the replay memory, saved beside each checkpoint.

``--resume`` continues a run from its checkpoint (``--resume-if-found`` too, and starts a
fresh run where there is none yet): the step count, epsilon schedule, target network,
optimiser state and random generators carry on. The environments start new episodes (the ones
in flight at the checkpoint are not continued). The replay is restored if it was saved;
otherwise it refills, and updates wait until it again holds ``learning_starts`` transitions
(the same rule as at the start of a run), so a resumed learner never trains on a handful of
fresh transitions.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from overtake.client.commands import UsageError, run_command
from overtake.client.episodes import make_vector_env, parse_overrides
from overtake.protocol import ACTION_COUNT
from overtake.protocol.messages import BehaviourSpec
from overtake.protocol.transport import SecurityConfig
from overtake.viz.recording import (
    APPLICATION_ID,
    Recording,
    RecordingConfig,
    close_recording,
    open_recording,
)

from .checkpoint import (
    CHECKPOINT_NAME,
    REPLAY_NAME,
    Checkpoint,
    CheckpointError,
    load_checkpoint,
    plain_data,
    save_checkpoint,
)
from .grid_network import GridNetworkShape
from .learner import ALGOS, Algo, DQNConfig, DQNLearner, Precision, execution_device
from .network import INPUT_SENSORS, Inputs, NetworkShape
from .observations import describe_space, frame_shapes
from .presets import PRESET_TRAINING
from .replay import FrameStacker, ReplayMemory
from .two_stream_network import TwoStreamShape
from .visual import TrainingRecording, training_blueprint

log = logging.getLogger("overtake.trainer")

# The ego vector of a camera-only network: the car's own speed, nothing of the other cars.
CAMERA_ONLY_EGO_FIELDS = ("speed_mps",)

# Environment 0's view is logged every this many steps of the vector environment: about 6 MB
# of .rrd per 10,000 steps with the camera, and no loss in steps per second measurable above
# the machine's noise (bench/RESULTS.md), for runs that last days.
TRAINER_RECORD_EVERY = 10


@dataclass(frozen=True)
class TrainConfig:
    """Train a DQN-family learner on an overtake preset."""

    algo: Algo = "dueling"
    """dqn, ddqn (Double DQN) or dueling (Dueling network with the Double DQN target: Min et
    al.'s combination, the default of min2018)"""
    inputs: Inputs = "both"
    """camera, lidar or both (Min et al.'s multi-modal network), grid (Ho's occupancy grid and
    action stack) or camera-map (Fayjie et al.'s camera and LIDAR map); default the preset's"""
    preset: str = "min2018"
    traffic: Literal["light", "medium", "heavy"] | None = None
    """traffic density; None keeps the preset's"""
    set: tuple[str, ...] = ()
    """more simulator overrides as dotted.name=value"""
    connect: str | None = None
    """a simulator server's (or router's) Zenoh endpoint; None runs the simulator in-process"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates for --connect"""
    num_envs: int = 1
    """environments (arenas) stepped together"""
    overlap: Literal["auto", "on", "off"] = "auto"
    """with --connect: "on" learns while the server simulates (each iteration sends a part's
    actions, learns, then takes the Steps of the part sent longest ago), in a fixed order
    (deterministic for a seed, but not the lock-step run's transitions: README, "Overlap");
    "off" steps all arenas, then learns, as in-process training does; "auto" overlaps where
    this machine has a core beyond PyTorch's threads (on a machine without one the server's
    simulation and the update contend for the cores: measured slower, bench/RESULTS.md)"""
    overlap_parts: int = 1
    """with overlap: the groups the arenas are opened in on the server, stepped in turn (2 or
    more also overlap acting with simulation, at the cost of one network call per part);
    capped by --num-envs"""
    total_steps: int = 1_000_000
    """environment steps (transitions, summed over environments) to train for"""
    seed: int = 0
    run_dir: Path | None = None
    """where the run's files go; default runs/<algo>-<inputs>-<seed>"""
    resume: bool = False
    """continue the run in run_dir from its checkpoint"""
    resume_if_found: bool = False
    """continue the run in run_dir if it holds a checkpoint, else start a fresh one there (for
    a restarted container, whose run_dir is the same; --resume instead refuses a run_dir
    without a checkpoint)"""
    checkpoint_every: int = 50_000
    """environment steps between checkpoints (one is always written at the end)"""
    save_replay: bool = False
    """save the replay memory with each checkpoint (about 0.9 GB at the default size)"""
    log_every: int = 1_000
    """environment steps between training log lines"""
    device: str = "cpu"
    """where the networks run: cpu, cuda, cuda:N or mps (checked before the run starts)"""
    precision: Precision = "fp32"
    """fp32, or mixed precision: bf16 (CPU or GPU) or fp16 (CUDA, with loss scaling); the
    forward passes run in that type, weights, optimiser, TD targets and loss in float32
    (bench/RESULTS.md: bf16 updates on this project's CPU)"""
    torch_threads: int | None = None
    """CPU threads for PyTorch; None keeps PyTorch's default"""
    progress: bool = True
    """show a progress bar"""
    dqn: DQNConfig = field(default_factory=DQNConfig)
    recording: RecordingConfig = field(
        default_factory=lambda: RecordingConfig(record_every=TRAINER_RECORD_EVERY)
    )
    """Rerun: episodes, learning curves and environment 0's view (default: trainer.rrd in the
    run directory)"""

    @property
    def parts(self) -> int:
        """Groups the remote arenas are opened in (1 without overlap or in-process)."""
        return min(self.overlap_parts, self.num_envs) if self.overlapped else 1

    @property
    def overlapped(self) -> bool:
        """Whether the loop learns while the server simulates (remote, with overlap; "auto"
        reads PyTorch's threads, so ask after they are set)."""
        if self.connect is None or self.overlap == "off":
            return False
        return self.overlap == "on" or torch.get_num_threads() < (os.cpu_count() or 1)

    @classmethod
    def for_preset(cls, preset: str, **changes: Any) -> TrainConfig:
        """The preset's training defaults (:mod:`.presets`: its paper's algorithm, inputs,
        network and hyper-parameters; Min et al.'s for a preset without its own), with
        ``changes`` (fields of TrainConfig) applied."""
        base = cls(preset=preset)
        defaults = PRESET_TRAINING.get(preset)
        if defaults is not None:
            base = dataclasses.replace(
                base, algo=defaults.algo, inputs=defaults.inputs, dqn=defaults.dqn
            )
        return dataclasses.replace(base, **changes)

    def resolved_run_dir(self) -> Path:
        return self.run_dir or Path("runs") / f"{self.algo}-{self.inputs}-{self.seed}"

    def overrides(self) -> dict[str, Any]:
        """Simulator overrides: the user's, the traffic, no sensor the network ignores
        (rendering a camera nobody looks at costs a third of a step), and for the camera alone
        an ego vector of the car's own speed only: the warnings and the car ahead's distance and
        speed ride with the LIDAR in the authors' code (its vector's elements 360-365), so a
        camera-only network sees other cars only through its camera (Min et al.'s ablation)."""
        overrides = parse_overrides(self.set)
        if self.traffic is not None:
            overrides["traffic.density"] = self.traffic
        if self.inputs == "lidar":
            overrides.setdefault("camera.enabled", False)
        if self.inputs == "camera":
            overrides.setdefault("lidar.enabled", False)
            overrides.setdefault("ego_vector.fields", list(CAMERA_ONLY_EGO_FIELDS))
        return overrides


def git_commit() -> str:
    try:
        here = Path(__file__).resolve().parent
        out = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return out + ("+uncommitted" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown (not a git checkout)"


def package_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("overtake", "torch", "numpy", "gymnasium", "eclipse-zenoh", "msgpack"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


class MetricsLog:
    """Appends JSON lines; each line is flushed, so a kill loses at most the line being written."""

    def __init__(self, path: Path) -> None:
        self.handle = open(path, "a", encoding="utf-8")  # noqa: SIM115 (open for the run)

    def write(self, record: dict[str, Any]) -> None:
        self.handle.write(json.dumps(record) + "\n")
        self.handle.flush()

    def close(self) -> None:
        self.handle.close()


@dataclass
class Timings:
    """Wall seconds spent per part of the loop since the last log line."""

    env: float = 0.0
    act: float = 0.0
    update: float = 0.0
    replay: float = 0.0

    def shares(self) -> dict[str, float]:
        total = self.env + self.act + self.update + self.replay
        return {
            f"time_{k}": (v / total if total else 0.0) for k, v in dataclasses.asdict(self).items()
        }


def main(
    config: TrainConfig, envs: Any = None, stop: threading.Event | None = None
) -> dict[str, Any]:
    """Train; returns a summary (steps, episodes, last metrics, run directory).

    ``envs``: a ready Gymnasium vector environment (next-step autoreset, the overtake
    observation keys and ``info["action_mask"]``) to train on instead of the one the
    configuration describes; the caller keeps it and closes it.
    ``stop``: once set, the run ends after the step under way as it would at
    ``total_steps`` (a last log line, a checkpoint, the recording closed), and the summary
    says ``stopped``; ``cli`` sets it on SIGTERM and SIGINT.
    """
    if config.total_steps < 1 or config.num_envs < 1:
        raise UsageError("--total-steps and --num-envs must be >= 1")
    try:  # before a run directory, server or environment is touched
        execution_device(config.device, config.precision)
    except ValueError as error:
        raise UsageError(str(error)) from None
    if config.torch_threads is not None:
        torch.set_num_threads(config.torch_threads)
    run_dir = config.resolved_run_dir()
    resumed = prepare_run_dir(config, run_dir)
    overrides = config.overrides()
    own_envs = envs is None
    if own_envs:
        envs = make_vector_env(
            config.preset,
            overrides,
            config.num_envs,
            config.connect,
            config.security,
            parts=config.parts,
        )
    elif envs.num_envs != config.num_envs:
        raise ValueError(
            f"the environment has {envs.num_envs} sub-environments, the "
            f"configuration says num_envs={config.num_envs}"
        )
    try:
        return TrainingRun(config, envs, run_dir, overrides, resumed, stop).run()
    finally:
        if own_envs:
            envs.close()


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


def _ego_fields(spec: BehaviourSpec | None) -> tuple[str, ...]:
    """The fields of the ego vector observation, in order, from the environment's behaviour
    spec (none where it has no ego vector, or no spec: an environment of the caller's)."""
    return spec.observation("ego").columns if spec is not None and spec.has("ego") else ()


class TrainingRun:
    """One life of a training run (its start or one resume) in its run directory.

    It holds the learner, the replay and the frame stacker, steps the vector environment
    until ``total_steps`` transitions are stored, and writes the run's files: the run record,
    the metrics log, the Rerun recording and the checkpoints.
    """

    # Set by run(): its outputs, then, once the environments start, the latest observation
    # and action mask, the environments whose next step is their autoreset, the clock, and
    # what the next training log line averages (see _new_log_window).
    log: MetricsLog
    recording: Recording | None
    view: TrainingRecording | None
    bar: Any
    obs: dict[str, np.ndarray]
    mask: np.ndarray
    starting: np.ndarray
    everyone: np.ndarray
    started: float
    losses: list[float]
    q_taken: list[float]
    timings: Timings
    log_t: float
    log_step: int

    def __init__(
        self,
        config: TrainConfig,
        envs: Any,
        run_dir: Path,
        overrides: dict[str, Any],
        resumed: Checkpoint | None,
        stop: threading.Event | None = None,
    ) -> None:
        self.config, self.dqn, self.envs = config, config.dqn, envs
        self.stop = stop if stop is not None else threading.Event()
        # Remote arenas hear the step count with each action: a spectator's recording of them
        # then lies on this run's `step` timeline (in-process environments have no spectators).
        self._label_step = getattr(envs.unwrapped, "label_step", None)
        self.run_dir, self.overrides = run_dir, overrides
        self.checkpoint_path, self.replay_path = run_dir / CHECKPOINT_NAME, run_dir / REPLAY_NAME
        self.space = envs.single_observation_space
        self.space_description = describe_space(self.space)
        self._build_learner()
        self.step, self.episodes, self.resumes = 0, 0, 0
        self.resumed_at_step: int | None = None
        self.env_seed = config.seed
        if resumed is not None:
            self._restore(resumed)
        self.next_update = self.step + self.dqn.train_every
        self.next_sync = self.step + self.dqn.target_update_steps
        self.next_checkpoint = self.step + config.checkpoint_every
        self.next_log = self.step + config.log_every
        # Updates wait for this many transitions: at the start of a run, and again after a
        # resume without a saved replay (capped by what the replay can hold).
        self.warm = max(
            self.dqn.batch_size,
            min(self.dqn.learning_starts, (self.replay.per_env - 1) * config.num_envs),
        )
        self.last_episode: dict[str, float] = {}
        self.iteration = 0
        # Overlap: the environments' parts (a remote vector env opened in parts), stepped in
        # turn: part p's actions go out, then the part sent longest ago comes back.
        self.part_rows: tuple[slice, ...] = getattr(envs.unwrapped, "part_slices", None) or (
            slice(0, config.num_envs),
        )
        self.parts = tuple(np.arange(config.num_envs)[s] for s in self.part_rows)
        self.in_flight: dict[int, tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]] = {}
        self.env_calls = 0  # envs.step, or with overlap send: one each, autoreset steps included
        self.unstored = 0  # transitions played past the budget, in its last step: not stored

    def _build_learner(self) -> None:
        """The learner (seeded), its replay memory and frame stacker, and the random generator
        of its exploration."""
        config, dqn = self.config, self.dqn
        double, dueling = ALGOS[config.algo]
        shapes = frame_shapes(self.space, config.inputs, f"preset {config.preset}'s environment")
        stacked = INPUT_SENSORS[config.inputs]
        self.net_shape: NetworkShape | GridNetworkShape | TwoStreamShape
        if config.inputs == "grid":
            self.net_shape = GridNetworkShape.from_space(self.space, ACTION_COUNT, dqn.stack)
        elif config.inputs == "camera-map":
            self.net_shape = TwoStreamShape.from_space(self.space, ACTION_COUNT, dqn.stack)
        else:
            self.net_shape = NetworkShape.from_space(self.space, ACTION_COUNT, dqn.stack)
        torch.manual_seed(config.seed)
        self.learner = DQNLearner(
            self.net_shape,
            config.inputs,
            dqn,
            double=double,
            dueling=dueling,
            device=config.device,
            precision=config.precision,
        )
        self.replay = ReplayMemory(
            dqn.replay_size, config.num_envs, shapes, dqn.stack, stacked, seed=config.seed
        )
        self.stacker = FrameStacker(config.num_envs, shapes, dqn.stack, stacked)
        self.rng = np.random.default_rng(config.seed)

    def _restore(self, resumed: Checkpoint) -> None:
        """Carry on from ``resumed``: the learner, the counts, the random generators, and the
        replay where it was saved."""
        self.learner.load_state_dict(resumed.learner)
        self.step, self.episodes = resumed.step, resumed.episodes
        self.resumed_at_step = resumed.step
        self.resumes = resumed.resumes + 1
        self.rng.bit_generator.state = resumed.rng_state
        torch.set_rng_state(resumed.torch_rng_state)
        # New episodes, not the ones of the first life: different environment seeds.
        self.env_seed = self.config.seed + 1_000_003 * self.resumes
        if self.config.save_replay and self.replay_path.exists():
            self.replay.load(self.replay_path)

    def _life_file(self, stem: str, suffix: str) -> Path:
        """``stem.suffix`` for a run's start, ``stem-resume-N.suffix`` for its N-th resume."""
        name = stem if self.resumed_at_step is None else f"{stem}-resume-{self.resumes}"
        return self.run_dir / f"{name}{suffix}"

    def run(self) -> dict[str, Any]:
        """Train to ``total_steps``, checkpointing on the way and at the end; returns the
        summary :func:`main` returns."""
        self._write_run_record()
        self.log = MetricsLog(self.run_dir / "metrics.jsonl")
        self.recording, self.bar = None, None
        try:
            self._open_recording()
            self._start_episodes()
            iteration = self._part_iteration if self.config.overlapped else self._iteration
            while self.step < self.config.total_steps and not self.stop.is_set():
                iteration()
            self._finish_parts()
            if self.step > self.log_step:
                # The steps since the last line, a partial window: a learning curve (Fayjie
                # et al.'s reward per 3,000 steps) keeps its last point.
                self._log_training(self.dqn.epsilon(self.step))
            self._checkpoint()
        finally:
            if self.bar is not None:
                self.bar.close()
            self.log.close()
            close_recording(self.recording)
        return {
            "run_dir": str(self.run_dir),
            "steps": self.step,
            "resumed_at_step": self.resumed_at_step,
            # Calls of envs.step in this life (with overlap: of send, one part each), autoreset
            # steps included: on a server, the rounds it played for this trainer's groups,
            # plus two per server loss (the truncated step and the reopened arenas' first,
            # which no server played).
            "env_steps_called": self.env_calls,
            "parts": len(self.parts),
            # The transitions the last step played beyond the budget (not stored or learned
            # from): steps + unstored is what the environments played in this run.
            "unstored": self.unstored,
            **self._remote_facts(),
            "episodes": self.episodes,
            "updates": self.learner.updates,
            "last_episode": self.last_episode,
            "stopped": self.step < self.config.total_steps,
        }

    def _remote_facts(self) -> dict[str, Any]:
        """With --connect: this trainer's name on the network, and how often its server was
        lost and its arenas reopened (each loss ends the episodes under way as truncated)."""
        remote = self.envs.unwrapped
        groups = getattr(remote, "groups", None)
        if not groups:
            return {}
        return {"trainer": remote.trainer, "server_losses": sum(g.restarts for g in groups)}

    def _write_run_record(self) -> None:
        """run.json (run-resume-N.json): what this life of the run is, to reproduce it."""
        config = self.config
        double, dueling = ALGOS[config.algo]
        record = {
            "config": plain_data(config),
            "algo": {"name": config.algo, "double": double, "dueling": dueling},
            "overrides": self.overrides,
            "sim_config": getattr(self.envs.unwrapped, "sim_config", None),
            "observation_space": self.space_description,
            "network": dataclasses.asdict(self.net_shape),
            "versions": package_versions(),
            "commit": git_commit(),
            "seed": config.seed,
            "resumes": self.resumes,
            "resumed_at_step": self.resumed_at_step,
            "trainer": self._remote_facts().get("trainer"),
            "host": platform.node(),
            "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            "replay_bytes": self.replay.nbytes,
            "replay_naive_bytes": self.replay.naive_nbytes(),
        }
        self._life_file("run", ".json").write_text(json.dumps(record, indent=2, default=str))

    def _open_recording(self) -> None:
        run_name = self.run_dir.name or "run"
        # No footer: a run may write for days, and the SDK would hold the footer's index in
        # memory until the end (overtake.viz.recording, on footers; bench/recording_memory.py).
        self.recording = open_recording(
            APPLICATION_ID,
            self.config.recording,
            self._life_file("trainer", ".rrd"),
            training_blueprint(run_name),
            footer=False,
        )
        self.view = (
            # Coloured by algorithm: DQN, Double DQN and Dueling keep their colours in every
            # recording that holds several runs.
            TrainingRecording(
                self.recording.stream,
                run_name,
                colour_index=list(ALGOS).index(self.config.algo),
                ego_fields=_ego_fields(getattr(self.envs.unwrapped, "behaviour_spec", None)),
            )
            if self.recording is not None
            else None
        )
        groups = getattr(self.envs.unwrapped, "groups", None)
        if self.view is not None and groups:
            # Every part's arenas where they share environment 0's server (the usual case;
            # with several servers behind a router the parts may open on different ones).
            server = groups[0].server
            arenas = [a for g in groups if g.server == server for a in g.arena_ids]
            self.view.arenas(server, tuple(arenas))

    def _start_episodes(self) -> None:
        """Reset every environment and start its frame stack and its replay ring."""
        obs, info = self.envs.reset(seed=self.env_seed)
        # Own, writable copies: parts write their rows into them as their Steps come back.
        self.obs = {k: np.array(v) for k, v in obs.items()}
        everyone = self.everyone = np.arange(self.config.num_envs)
        self.stacker.reset(everyone, self.obs)
        self.replay.start(everyone, self.obs, info["action_mask"])
        self.mask = np.array(info["action_mask"])
        self.starting = np.zeros(self.config.num_envs, dtype=bool)
        now = time.perf_counter()
        self._new_log_window(now)
        self.started = now
        self.bar = _progress(self.config, self.step)

    def _iteration(self) -> None:
        """One step of every environment: act, step, store what came back, learn; log and
        checkpoint when due."""
        t0 = time.perf_counter()
        epsilon = self.dqn.epsilon(self.step)
        actions, q = self.learner.act(self.stacker.observation(), self.mask, epsilon, self.rng)
        t1 = time.perf_counter()
        seen = self.obs
        if self._label_step is not None:
            self._label_step(self.step)
        self.obs, reward, terminated, truncated, info = self.envs.step(actions)
        self.env_calls += 1
        t2 = time.perf_counter()
        self._record_car_view(seen, actions, q, reward, info)
        stored, taken = self._store(self.everyone, actions, reward, terminated, info["action_mask"])
        self._end_episodes(self.everyone, terminated, truncated, info, taken)
        t3 = time.perf_counter()
        self._learn()
        t4 = time.perf_counter()
        self._account(epsilon, stored, (t0, t1, t2, t3, t4))

    def _part_iteration(self) -> None:
        """Overlap: act for one part and send its actions; learn while the server simulates;
        then take the Steps of the part sent longest ago and store them; log and checkpoint
        when due. With one part the update runs during the round trip (it sees the
        transitions up to the previous iteration); with two the server also plays one part
        while the learner acts on the other."""
        t0 = time.perf_counter()
        part = self.env_calls % len(self.parts)
        rows = self.part_rows[part]
        epsilon = self.dqn.epsilon(self.step)
        stacked = self.stacker.observation()
        if len(self.parts) > 1:
            stacked = {k: v[rows] for k, v in stacked.items()}
        actions, q = self.learner.act(stacked, self.mask[rows], epsilon, self.rng)
        t1 = time.perf_counter()
        if self._label_step is not None:
            self._label_step(self.step)
        seen = {k: v[rows].copy() for k, v in self.obs.items()} if part == 0 else {}
        self.envs.unwrapped.send(part, actions)
        self.in_flight[part] = (actions, q, seen)
        self.env_calls += 1
        t2 = time.perf_counter()
        self._learn()
        t3 = time.perf_counter()
        stored, waited = 0, 0.0
        oldest = self.env_calls % len(self.parts)  # the next to send is the one sent longest ago
        if oldest in self.in_flight and len(self.in_flight) == len(self.parts):
            stored, waited = self._receive_part(oldest)
        t4 = time.perf_counter()
        # In _account's order (act, env, replay, update): the wait for the Steps counts as the
        # environment's time, the rest of receiving as the replay's.
        env_end = t2 + waited
        replay_end = env_end + (t4 - t3 - waited)
        self._account(epsilon, stored, (t0, t1, env_end, replay_end, t4))

    def _account(
        self, epsilon: float, stored: int, times: tuple[float, float, float, float, float]
    ) -> None:
        """An iteration's time split (act, env, replay, update, from its five clock readings)
        and progress; a log line and a checkpoint when due."""
        t0, t1, t2, t3, t4 = times
        self.timings.act += t1 - t0
        self.timings.env += t2 - t1
        self.timings.replay += t3 - t2
        self.timings.update += t4 - t3
        if self.bar is not None and stored:
            self.bar.update(stored)
        if self.step >= self.next_log:
            self._log_training(epsilon)
        if self.step >= self.next_checkpoint:
            self._checkpoint()
            self.next_checkpoint = self.step + self.config.checkpoint_every

    def _receive_part(self, part: int) -> tuple[int, float]:
        """Take part ``part``'s Steps and store them; returns the transitions stored and the
        seconds spent waiting for them."""
        envs, rows = self.parts[part], self.part_rows[part]
        actions, q, seen = self.in_flight.pop(part)
        start = time.perf_counter()
        obs, reward, terminated, truncated, info = self.envs.unwrapped.recv(part)
        waited = time.perf_counter() - start
        for name, value in obs.items():
            self.obs[name][rows] = value
        if part == 0:
            self._record_car_view(seen, actions, q, reward, info)
        stored, taken = self._store(envs, actions, reward, terminated, info["action_mask"])
        self._end_episodes(envs, terminated, truncated, info, taken)
        return stored, waited

    def _finish_parts(self) -> None:
        """Take the Steps of the parts still in flight at the end of the run, without storing
        them (the run has its steps): the server's rounds and the trainer's sends agree."""
        for part in sorted(self.in_flight):
            self.envs.unwrapped.recv(part)
        self.in_flight.clear()

    def _record_car_view(
        self,
        seen: dict[str, np.ndarray],
        actions: np.ndarray,
        q: np.ndarray,
        reward: np.ndarray,
        info: dict[str, Any],
    ) -> None:
        """Environment 0's view, action, Q-values and reward to Rerun, every record_every
        iterations (not for its autoreset step, whose action the environment ignored)."""
        if (
            self.view is not None
            and not self.starting[0]
            and self.iteration % self.config.recording.record_every == 0
        ):
            terms = {name: float(v[0]) for name, v in info.get("reward_terms", {}).items()}
            self.view.car_view(
                self.step,
                {k: v[0] for k, v in seen.items()},
                int(actions[0]),
                q[0],
                float(reward[0]),
                terms,
            )
        self.iteration += 1

    def _store(
        self,
        envs: np.ndarray,
        actions: np.ndarray,
        reward: np.ndarray,
        terminated: np.ndarray,
        mask: np.ndarray,
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
        ``unstored`` and not learned from.
        """
        self.mask[envs] = mask
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
            ids = envs[fresh]
            sub = {k: v[ids] for k, v in self.obs.items()}
            self.stacker.reset(ids, sub)
            self.replay.start(ids, sub, mask[fresh])
        if moving.size:
            ids = envs[moving]
            sub = {k: v[ids] for k, v in self.obs.items()}
            self.replay.add(
                ids, actions[moving], reward[moving], terminated[moving], sub, mask[moving]
            )
            self.stacker.push(ids, sub)
            self.step += moving.size
            self.reward_sum += float(reward[moving].sum())
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
            if self.view is not None:
                self.view.episode(self.step, self.last_episode)
        self.starting[envs] = ended

    def _learn(self) -> None:
        """One update per ``train_every`` steps stored (once the replay holds ``warm``
        transitions), and the target network's sync every ``target_update_steps``."""
        while self.step >= self.next_update:
            self.next_update += self.dqn.train_every
            if len(self.replay) >= self.warm:
                stats = self.learner.update(self.replay.sample(self.dqn.batch_size))
                self.losses.append(stats["loss"])
                self.q_taken.append(stats["q_taken"])
        if self.step >= self.next_sync:
            self.learner.sync_target()
            self.next_sync = self.step + self.dqn.target_update_steps

    def _new_log_window(self, now: float) -> None:
        """Start collecting what the next training log line averages."""
        self.losses, self.q_taken = [], []
        self.reward_sum = 0.0
        self.timings = Timings()
        self.log_t, self.log_step = now, self.step

    def _log_training(self, epsilon: float) -> None:
        """A ``{"kind": "train", ...}`` line (to metrics.jsonl, Rerun and the progress bar)
        over the steps since the last one."""
        now = time.perf_counter()
        sps = (self.step - self.log_step) / max(now - self.log_t, 1e-9)
        entry = {
            "kind": "train",
            "step": self.step,
            "episodes": self.episodes,
            "wall_s": round(now - self.started, 3),
            "epsilon": epsilon,
            "updates": self.learner.updates,
            "loss": float(np.mean(self.losses)) if self.losses else None,
            "q_taken": float(np.mean(self.q_taken)) if self.q_taken else None,
            # The rewards of the transitions stored since the last line (Fayjie et al.'s Fig.
            # 6 plots them per 3,000 steps).
            "reward_sum": self.reward_sum,
            "steps_per_s": sps,
            "replay": len(self.replay),
            **self.timings.shares(),
        }
        self.log.write(entry)
        if self.view is not None:
            self.view.learning(self.step, entry)
        if self.bar is not None:
            last = self.last_episode
            self.bar.set_postfix(
                eps=f"{epsilon:.2f}",
                loss=entry["loss"] and f"{entry['loss']:.3f}",
                speed=last and f"{last['avg_speed_kmh']:.1f}",
                ret=last and f"{last['return']:.0f}",
                refresh=False,
            )
        self._new_log_window(now)
        self.next_log = self.step + self.config.log_every

    def _checkpoint(self) -> None:
        save_checkpoint(
            self.checkpoint_path,
            learner=self.learner,
            config=self.config,
            overrides=self.overrides,
            space=self.space_description,
            net_shape=self.net_shape,
            step=self.step,
            episodes=self.episodes,
            rng_state=self.rng.bit_generator.state,
            resumes=self.resumes,
        )
        if self.config.save_replay:
            self.replay.save(self.replay_path)


def _progress(config: TrainConfig, start: int) -> Any:
    if not config.progress:
        return None
    from tqdm import tqdm

    return tqdm(
        total=config.total_steps,
        initial=start,
        unit="step",
        dynamic_ncols=True,
        desc=f"{config.algo}/{config.inputs}",
        file=sys.stderr,
    )


def preset_in(argv: list[str]) -> str:
    """The ``--preset`` a command line names (its last), or the default preset."""
    preset = TrainConfig().preset
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            preset = argv[i + 1]
        elif arg.startswith("--preset="):
            preset = arg.split("=", 1)[1]
    return preset


def parse_args(args: list[str]) -> TrainConfig:
    """The configuration an ``overtake-train`` command line asks for: the named preset's
    training (its defaults, which --help shows) with the options given."""
    import tyro

    return tyro.cli(
        TrainConfig,
        args=args,
        default=TrainConfig.for_preset(preset_in(args)),
        config=(tyro.conf.OmitArgPrefixes,),
        description="overtake-train: DQN / Double DQN / Dueling DQN on overtake",
    )


def cli(argv: list[str] | None = None) -> None:
    config = parse_args(sys.argv[1:] if argv is None else argv)
    stop = threading.Event()

    def on_signal(signum: int, _frame: Any) -> None:
        name = signal.Signals(signum).name
        if stop.is_set():  # asked twice: stop now (the recording and logs still close)
            raise SystemExit(
                f"overtake-train: stopped at once by a second {name}; the run continues "
                "with --resume from its last checkpoint"
            )
        log.warning(
            "%s: finishing the step under way, writing a checkpoint and stopping "
            "(send it again to stop at once); continue the run with --resume",
            name,
        )
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    summary = run_command("overtake-train", lambda c: main(c, stop=stop), config)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    cli()
