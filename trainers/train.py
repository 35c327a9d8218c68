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
import signal
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from overtake.client.commands import UsageError, run_command
from overtake.client.episodes import make_vector_env, parse_overrides
from overtake.client.shared_steps import Transport
from overtake.protocol.transport import SecurityConfig
from overtake.viz.recording import (
    RecordingConfig,
)

from .checkpoint import (
    CHECKPOINT_NAME,
    Checkpoint,
    CheckpointError,
    load_checkpoint,
)
from .learner import Algo, DQNConfig, Precision, execution_device
from .network import Inputs
from .presets import PRESET_TRAINING
from .training_run import TrainingRun

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
    transport: Transport = "auto"
    """how a server's Steps reach this process (--connect): auto (shared memory where the
    server is on this host, Zenoh otherwise), shm (shared memory or an error), zenoh"""
    num_envs: int = 1
    """environments (arenas) stepped together"""
    overlap: Literal["auto", "on", "off"] = "auto"
    """with --connect: "on" learns while the server simulates (each iteration sends a part's
    actions, learns, then takes the Steps of the part sent longest ago), in a fixed order
    (deterministic for a seed, but not the lock-step run's transitions: docs/training.md, "Speed");
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
    shield: bool = False
    """mask the actions a safety shield judges unsafe, from what the car observes (its LIDAR
    and speed), when acting, exploring and in the target's max (overtake.client.shield: the
    rule and its sources); evaluation, export and the ONNX driver use it where it was on"""
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
            transport=config.transport,
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
