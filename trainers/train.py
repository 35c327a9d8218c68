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
import platform
import subprocess
import sys
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
from overtake.viz.recording import RecordingConfig, close_recording, open_recording
from overtake.protocol.transport import SecurityConfig

from .checkpoint import (CHECKPOINT_NAME, REPLAY_NAME, CheckpointError, load_checkpoint,
                         plain_data, save_checkpoint)
from .learner import ALGOS, Algo, DQNConfig, DQNLearner
from .network import INPUT_SENSORS, Inputs, NetworkShape
from .observations import describe_space, frame_shapes
from .replay import FrameStacker, ReplayMemory
from .visual import TrainingRecording, training_blueprint

# Environment 0's view is logged every this many steps of the vector environment: about 6 MB
# of .rrd per 10,000 steps with the camera, and no loss in steps per second measurable above
# the machine's noise (bench/RESULTS.md), for runs that last days.
TRAINER_RECORD_EVERY = 10

@dataclass(frozen=True)
class TrainConfig:
    """Train a DQN-family learner on an overtake preset."""

    algo: Algo = "ddqn"
    """dqn, ddqn (Double DQN) or dueling (Dueling network with the Double DQN target)"""
    inputs: Inputs = "both"
    """camera, lidar or both (Min et al.'s multi-modal network)"""
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
    torch_threads: int | None = None
    """CPU threads for PyTorch; None keeps PyTorch's default"""
    progress: bool = True
    """show a progress bar"""
    dqn: DQNConfig = field(default_factory=DQNConfig)
    recording: RecordingConfig = field(
        default_factory=lambda: RecordingConfig(record_every=TRAINER_RECORD_EVERY))
    """Rerun: episodes, learning curves and environment 0's view (default: trainer.rrd in the
    run directory)"""

    def resolved_run_dir(self) -> Path:
        return self.run_dir or Path("runs") / f"{self.algo}-{self.inputs}-{self.seed}"

    def overrides(self) -> dict[str, Any]:
        """Simulator overrides: the user's, the traffic, and no sensor the network ignores
        (rendering a camera nobody looks at costs a third of a step)."""
        overrides = parse_overrides(self.set)
        if self.traffic is not None:
            overrides["traffic.density"] = self.traffic
        if self.inputs == "lidar":
            overrides.setdefault("camera.enabled", False)
        return overrides


def git_commit() -> str:
    try:
        here = Path(__file__).resolve().parent
        out = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True,
                             text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain"],
                               capture_output=True, text=True, timeout=5).stdout.strip()
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
        self.handle = open(path, "a", encoding="utf-8")

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
        return {f"time_{k}": (v / total if total else 0.0)
                for k, v in dataclasses.asdict(self).items()}


def main(config: TrainConfig, envs: Any = None) -> dict[str, Any]:
    """Train; returns a summary (steps, episodes, last metrics, run directory).

    ``envs``: a ready Gymnasium vector environment (next-step autoreset, the overtake
    observation keys and ``info["action_mask"]``) to train on instead of the one the
    configuration describes; the caller keeps it and closes it.
    """
    if config.total_steps < 1 or config.num_envs < 1:
        raise UsageError("--total-steps and --num-envs must be >= 1")
    if config.torch_threads is not None:
        torch.set_num_threads(config.torch_threads)
    run_dir = config.resolved_run_dir()
    checkpoint_path = run_dir / CHECKPOINT_NAME
    resumed = None
    if config.resume or (config.resume_if_found and checkpoint_path.exists()):
        if not checkpoint_path.exists():
            raise CheckpointError(f"--resume: no checkpoint at {checkpoint_path}")
        resumed = load_checkpoint(checkpoint_path)
        resumed.check_compatible(config.algo, config.inputs, config.preset)
    elif checkpoint_path.exists():
        raise UsageError(f"{run_dir} already holds a run (checkpoint.pt); pass --resume (or "
                         "--resume-if-found) to continue it or choose another --run-dir")
    run_dir.mkdir(parents=True, exist_ok=True)

    overrides = config.overrides()
    own_envs = envs is None
    if own_envs:
        envs = make_vector_env(config.preset, overrides, config.num_envs, config.connect,
                               config.security)
    elif envs.num_envs != config.num_envs:
        raise ValueError(f"the environment has {envs.num_envs} sub-environments, the "
                         f"configuration says num_envs={config.num_envs}")
    try:
        return _train(config, envs, run_dir, overrides, resumed)
    finally:
        if own_envs:
            envs.close()


def _train(config: TrainConfig, envs: Any, run_dir: Path, overrides: dict[str, Any],
           resumed: Any) -> dict[str, Any]:
    dqn, n = config.dqn, config.num_envs
    double, dueling = ALGOS[config.algo]
    checkpoint_path, replay_path = run_dir / CHECKPOINT_NAME, run_dir / REPLAY_NAME
    space = envs.single_observation_space
    space_description = describe_space(space)
    shapes = frame_shapes(space, config.inputs)
    stacked = INPUT_SENSORS[config.inputs]
    net_shape = NetworkShape.from_space(space, ACTION_COUNT, dqn.stack)
    torch.manual_seed(config.seed)
    learner = DQNLearner(net_shape, config.inputs, dqn, double=double, dueling=dueling,
                         device=config.device)
    replay = ReplayMemory(dqn.replay_size, n, shapes, dqn.stack, stacked, seed=config.seed)
    stacker = FrameStacker(n, shapes, dqn.stack, stacked)
    rng = np.random.default_rng(config.seed)
    step, episodes = 0, 0
    env_seed = config.seed
    if resumed is not None:
        learner.load_state_dict(resumed.learner)
        step, episodes = resumed.step, resumed.episodes
        rng.bit_generator.state = resumed.rng_state
        torch.set_rng_state(resumed.torch_rng_state)
        # New episodes, not the ones of the first life: different environment seeds.
        env_seed = config.seed + 1_000_003 * (resumed.resumes + 1)
        if config.save_replay and replay_path.exists():
            replay.load(replay_path)
    resumes = 0 if resumed is None else resumed.resumes + 1

    record = {"config": plain_data(config), "algo": {"name": config.algo, "double": double,
                                                    "dueling": dueling},
              "overrides": overrides, "sim_config": getattr(envs.unwrapped, "sim_config", None),
              "observation_space": space_description,
              "network": dataclasses.asdict(net_shape), "versions": package_versions(),
              "commit": git_commit(), "seed": config.seed, "resumes": resumes,
              "resumed_at_step": step if resumed is not None else None,
              "host": platform.node(), "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ",
                                                                    time.gmtime()),
              "replay_bytes": replay.nbytes, "replay_naive_bytes": replay.naive_nbytes()}
    (run_dir / ("run.json" if resumed is None else f"run-resume-{resumes}.json")).write_text(
        json.dumps(record, indent=2, default=str))
    log = MetricsLog(run_dir / "metrics.jsonl")
    run_name = run_dir.name or "run"
    recording = open_recording("overtake-train", config.recording,
                               run_dir / ("trainer.rrd" if resumed is None
                                          else f"trainer-resume-{resumes}.rrd"),
                               training_blueprint(run_name))
    view = TrainingRecording(recording.stream, run_name) if recording is not None else None

    def checkpoint() -> None:
        save_checkpoint(checkpoint_path, learner=learner, config=config, overrides=overrides,
                        space=space_description, net_shape=net_shape, step=step,
                        episodes=episodes, rng_state=rng.bit_generator.state,
                        resumes=resumes)
        if config.save_replay:
            replay.save(replay_path)

    obs, info = envs.reset(seed=env_seed)
    everyone = np.arange(n)
    stacker.reset(everyone, obs)
    replay.start(everyone, obs, info["action_mask"])
    mask = info["action_mask"]
    starting = np.zeros(n, dtype=bool)   # envs whose next step is Gymnasium's autoreset step
    # Updates wait for this many transitions: at the start of a run, and again after a resume
    # without a saved replay (capped by what the replay can hold).
    warm = max(dqn.batch_size, min(dqn.learning_starts, (replay.per_env - 1) * n))
    next_update = step + dqn.train_every
    next_sync = step + dqn.target_update_steps
    next_checkpoint = step + config.checkpoint_every
    next_log = step + config.log_every
    last_episode: dict[str, float] = {}
    losses: list[float] = []
    q_taken: list[float] = []
    timings = Timings()
    log_t, log_step = time.perf_counter(), step
    started = log_t
    bar = _progress(config, step)
    iteration, record_every = 0, config.recording.record_every
    try:
        while step < config.total_steps:
            t0 = time.perf_counter()
            epsilon = dqn.epsilon(step)
            actions, q = learner.act(stacker.observation(), mask, epsilon, rng)
            t1 = time.perf_counter()
            seen = obs
            obs, reward, terminated, truncated, info = envs.step(actions)
            t2 = time.perf_counter()
            if view is not None and not starting[0] and iteration % record_every == 0:
                view.car_view(step, {k: v[0] for k, v in seen.items()}, int(actions[0]), q[0],
                              float(reward[0]), {name: float(v[0]) for name, v
                                                 in info.get("reward_terms", {}).items()})
            iteration += 1
            mask = info["action_mask"]
            # Gymnasium next-step autoreset: envs that ended last step were reset by this one
            # (its action ignored, reward 0); their observation starts a new episode.
            moving = np.flatnonzero(~starting)
            fresh = np.flatnonzero(starting)
            if fresh.size:
                sub = {k: v[fresh] for k, v in obs.items()}
                stacker.reset(fresh, sub)
                replay.start(fresh, sub, mask[fresh])
            if moving.size:
                sub = {k: v[moving] for k, v in obs.items()}
                replay.add(moving, actions[moving], reward[moving], terminated[moving], sub,
                           mask[moving])
                stacker.push(moving, sub)
                step += moving.size
            ended = (terminated | truncated) & ~starting
            for i in np.flatnonzero(ended):
                episodes += 1
                last_episode = {name: float(values[i])
                                for name, values in info["metrics"].items()}
                log.write({"kind": "episode", "step": step, "episode": episodes, "env": int(i),
                           "wall_s": round(time.perf_counter() - started, 3),
                           "terminated": bool(terminated[i]), **last_episode})
                if view is not None:
                    view.episode(step, last_episode)
            starting = ended
            t3 = time.perf_counter()
            while step >= next_update:
                next_update += dqn.train_every
                if len(replay) >= warm:
                    stats = learner.update(replay.sample(dqn.batch_size))
                    losses.append(stats["loss"])
                    q_taken.append(stats["q_taken"])
            if step >= next_sync:
                learner.sync_target()
                next_sync = step + dqn.target_update_steps
            t4 = time.perf_counter()
            timings.act += t1 - t0
            timings.env += t2 - t1
            timings.replay += t3 - t2
            timings.update += t4 - t3
            if bar is not None:
                bar.update(moving.size)
            if step >= next_log:
                now = time.perf_counter()
                sps = (step - log_step) / max(now - log_t, 1e-9)
                entry = {"kind": "train", "step": step, "episodes": episodes,
                         "wall_s": round(now - started, 3),
                         "epsilon": epsilon, "updates": learner.updates,
                         "loss": float(np.mean(losses)) if losses else None,
                         "q_taken": float(np.mean(q_taken)) if q_taken else None,
                         "steps_per_s": sps, "replay": len(replay), **timings.shares()}
                log.write(entry)
                if view is not None:
                    view.learning(step, entry)
                if bar is not None:
                    bar.set_postfix(eps=f"{epsilon:.2f}", loss=entry["loss"] and
                                    f"{entry['loss']:.3f}",
                                    speed=last_episode and
                                    f"{last_episode['avg_speed_kmh']:.1f}",
                                    ret=last_episode and f"{last_episode['return']:.0f}",
                                    refresh=False)
                losses.clear()
                q_taken.clear()
                timings = Timings()
                log_t, log_step = now, step
                next_log = step + config.log_every
            if step >= next_checkpoint:
                checkpoint()
                next_checkpoint = step + config.checkpoint_every
        checkpoint()
    finally:
        if bar is not None:
            bar.close()
        log.close()
        close_recording(recording)
    return {"run_dir": str(run_dir), "steps": step, "episodes": episodes,
            "updates": learner.updates, "last_episode": last_episode}


def _progress(config: TrainConfig, start: int) -> Any:
    if not config.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=config.total_steps, initial=start, unit="step", dynamic_ncols=True,
                desc=f"{config.algo}/{config.inputs}", file=sys.stderr)


def cli(argv: list[str] | None = None) -> None:
    import tyro

    config = tyro.cli(TrainConfig, args=argv, config=(tyro.conf.OmitArgPrefixes,),
                      description="overtake-train: DQN / Double DQN / Dueling DQN on overtake")
    summary = run_command("overtake-train", main, config)
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    cli()
