"""What one training run is: :class:`TrainConfig`, the configuration ``overtake-train`` parses
from its command line (:mod:`.train`) and a run (:mod:`.training_run`), an experiment
(:mod:`.experiment`) or a user builds in Python; and the simulator overrides it implies."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import torch

from overtake.cli import Output, UsageError
from overtake.cli.options import unset
from overtake.client.episodes.scenario import Scenario, Where
from overtake.protocol.vocabulary import DEFAULT_PRESET, WATCH_SETTING
from overtake.viz.recording import RecordingConfig

from ..learning.dqn_config import Algo, DQNConfig
from ..learning.learner import Precision
from ..learning.network import Inputs, ego_fields_read, observations_read
from .presets import PRESET_TRAINING

# Environment 0's view is logged every this many steps of the vector environment: about 6 MB
# of .rrd per 10,000 steps with the camera, and no loss in steps per second measurable above
# the machine's noise (bench/RESULTS.md), for runs that last days.
TRAINER_RECORD_EVERY = 10


@dataclass(frozen=True)
class TrainConfig:
    """Train a DQN-family learner on an overtake preset (the simulator and where it runs are
    the scenario's and where's options)."""

    scenario: Scenario = field(default_factory=lambda: Scenario(preset=DEFAULT_PRESET))
    """the simulator preset (its paper's training is every option's default: --help with
    --preset shows them), its traffic, episode length and overrides"""
    where: Where = field(default_factory=Where)
    """where the simulator runs: in this process, or on a server (--connect)"""
    algo: Algo = "dueling"
    """dqn, ddqn (Double DQN), dueling (Dueling network with the Double DQN target: Min et
    al.'s combination, the default of min2018) or qr (QR-DQN: a quantile head and the quantile
    Huber loss, the Double DQN choice of the next action, as Min et al.'s public code trains it;
    --quantiles sets the quantiles per action)"""
    inputs: Inputs = "both"
    """camera, lidar or both (Min et al.'s multi-modal network), grid (Ho's occupancy grid and
    action stack) or camera-map (Fayjie et al.'s camera and LIDAR map); default the preset's"""
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
    """seeds the network, exploration, replay sampling and the arenas (their seeds follow it)"""
    seeds: tuple[int, ...] = ()
    """train these seeds together in this process, as members of one learner (one forward and
    one backward pass for all; each seed a whole run in <run_dir>/seed-<k>, as a lone run of
    that seed would be, docs/training.md "Members"); empty: the one run of --seed"""
    run_dir: Annotated[Path | None, unset("PATH")] = None
    """where the run's files go; unset: runs/<algo>-<inputs>-<seed>"""
    resume: bool = False
    """continue the run in run_dir from its checkpoint"""
    resume_if_found: bool = False
    """continue the run in run_dir if it holds a checkpoint, else start a fresh one there (for
    a restarted container, whose run_dir is the same; --resume instead refuses a run_dir
    without a checkpoint)"""
    checkpoint_every: int = 50_000
    """environment steps between checkpoints (one is always written at the end)"""
    replay_on_disk: bool = True
    """keep the replay memory in the run directory (replay/, memory-mapped files written as
    they fill: as much disk as the replay's size, about 0.9 GB at min2018's default), so that
    a stopped run resumes exactly (docs/training.md); --no-replay-on-disk keeps it in memory
    only, and a resume then refills it"""
    log_every: int = 1_000
    """environment steps between training log lines"""
    device: str = "cpu"
    """where the networks run: cpu, cuda, cuda:N or mps (checked before the run starts)"""
    precision: Precision = "fp32"
    """fp32, or mixed precision: bf16 (CPU or GPU) or fp16 (CUDA, with loss scaling); the
    forward passes run in that type, weights, optimiser, TD targets and loss in float32
    (bench/RESULTS.md: bf16 updates on this project's CPU)"""
    torch_threads: Annotated[int | None, unset("N|None")] = 1
    """CPU threads for PyTorch; None keeps PyTorch's default (one a core). One by default:
    measured the faster choice per CPU-second, and beside other work (docs/training.md,
    "Threads"); several seeds train faster as members (--seeds) than as threads"""
    progress: bool = True
    """show a progress bar"""
    shield: bool = False
    """mask the actions a safety shield judges unsafe, from what the car observes (its LIDAR
    and speed), when acting, exploring and in the target's max (overtake.client.policies.shield: the
    rule and its sources); evaluation, export and the ONNX driver use it where it was on"""
    shield_watch: bool = False
    """the shield's second half: driver assistance also watches each lane change through
    (ego.lane_change_watch, overtake.server.sim.lane_watch: an unsafe change turns back before
    the lane marking, past it the car brakes as hard as needed); a simulator setting, so
    evaluation and replays of the run's checkpoints have it too"""
    recipe: Annotated[str | None, unset("NAME")] = None
    """a named way of training the preset other than its paper's, whose settings become the
    defaults (min2018: notebook, Min et al.'s notebook: Adam's epsilon 0.01, the squared TD
    error, an update every step); unset: the paper's"""
    dqn: DQNConfig = field(default_factory=DQNConfig)
    recording: RecordingConfig = field(
        default_factory=lambda: RecordingConfig(record_every=TRAINER_RECORD_EVERY)
    )
    """Rerun: episodes, learning curves and environment 0's view (default: trainer.rrd in the
    run directory)"""

    @property
    def preset(self) -> str:
        """The simulator preset (the scenario's; min2018 where it names none)."""
        return self.scenario.preset_or(None)

    @property
    def parts(self) -> int:
        """Groups the remote arenas are opened in (1 without overlap or in-process)."""
        return min(self.overlap_parts, self.num_envs) if self.overlapped else 1

    @property
    def overlapped(self) -> bool:
        """Whether the loop learns while the server simulates (remote, with overlap; "auto"
        reads PyTorch's threads, so ask after they are set)."""
        if self.where.in_process or self.overlap == "off":
            return False
        return self.overlap == "on" or torch.get_num_threads() < (os.cpu_count() or 1)

    @classmethod
    def for_preset(cls, preset: str, recipe: str | None = None, **changes: Any) -> TrainConfig:
        """The preset's training defaults (:mod:`.presets`: its paper's algorithm, inputs,
        network and hyper-parameters; Min et al.'s for a preset without its own), or those of
        one of its ``recipe``s, with ``changes`` (fields of TrainConfig) applied."""
        scenario = changes.pop("scenario", None) or Scenario()
        if scenario.preset not in (None, preset):
            raise ValueError(f"for_preset({preset!r}) was given a scenario of {scenario.preset!r}")
        base = cls(scenario=dataclasses.replace(scenario, preset=preset), recipe=recipe)
        defaults = PRESET_TRAINING.get(preset)
        recipes = defaults.recipes if defaults is not None else {}
        if recipe is not None and recipe not in recipes:
            raise UsageError(
                f"--recipe {recipe}: preset {preset} has "
                + (f"the recipes {', '.join(sorted(recipes))}" if recipes else "no recipes")
            )
        if defaults is not None:
            dqn = dataclasses.replace(defaults.dqn, **recipes.get(recipe or "", {}))
            base = dataclasses.replace(base, algo=defaults.algo, inputs=defaults.inputs, dqn=dqn)
        return dataclasses.replace(base, **changes)

    def resolved_run_dir(self) -> Path:
        """The run directory (with --seeds: the folder of the members' seed-<k> directories)."""
        if self.run_dir is not None:
            return self.run_dir
        seed = "seeds-" + "-".join(map(str, self.seeds)) if self.seeds else str(self.seed)
        return Path("runs") / f"{self.algo}-{self.inputs}-{seed}"

    @property
    def observations(self) -> tuple[str, ...]:
        """The observations the network reads, the only sensors the simulator is asked to
        render (rendering a camera nobody looks at costs a third of a step); a run before
        issue 60 switched the others off with ``<sensor>.enabled`` overrides instead."""
        return observations_read(self.inputs)

    @property
    def ego_fields(self) -> tuple[str, ...]:
        """The ego vector's fields the network reads, which the trainer asks the simulator for
        (OpenRequest.ego_fields; none: the preset's); a run before issue 70 set them with an
        override instead."""
        return ego_fields_read(self.inputs)

    def overrides(self, base: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Simulator overrides: the user's, the traffic, and the lane-change watch where the
        shield watches lane changes through."""
        overrides = self.scenario.overrides(base)
        if self.shield_watch:
            overrides.setdefault(WATCH_SETTING, True)
        return overrides

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before anything is trained)."""
        run_dir = self.resolved_run_dir()
        return (
            Output("--run-dir", run_dir, folder=True),
            self.recording.output(run_dir / "trainer.rrd"),
        )
