"""What a trainer shows in Rerun, on the ``step`` timeline (environment steps).

Summaries are logged metric first, run second, so that runs sharing a recording (the demo's
DQN, Double DQN and Dueling trainers, ``--recording-id``) fall into the same plots, one line
per run, on one step axis:

- ``training/episode/<metric>/<run>``: every episode's return and the papers' metrics (average
  speed, lane changes, overtakes, collisions, emergency brakes, distance, ...), as the episode
  ends;
- ``training/learning/<name>/<run>``: loss, epsilon, the mean Q of the actions taken in the
  updates, and steps per second, once per log line (``--log-every``);
- ``trainer/<run>/env0/...``: what the first environment's car sees and does, every
  ``--record-every`` steps: its camera frame, its LIDAR hits around the car (drawn as a map:
  x ahead, the car's left up), speed (km/h), the action taken (a point on the series of its
  name), the Q-value of every action, the reward and each reward term.

:func:`~overtake.viz.training_layout.training_blueprint` lays out one run, or several side by
side; one plot per quantity (never distance beside collisions, nor steps/s beside epsilon).

Summaries are logged at most once per episode or log line; the car's view is decimated, and
with the default decimation the training loop loses nothing measurable (``bench/RESULTS.md``,
``python -m bench.speed.bench_recording``).
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from overtake.protocol.vocabulary import ACTION_NAMES
from overtake.viz.car_view import CarView
from overtake.viz.recording import APPLICATION_ID, Recording, RecordingConfig, open_recording
from overtake.viz.training_layout import CAR_PICTURES, training_blueprint

from ..learning.learner import ALGOS

__all__ = ["LEARNING_SERIES", "TrainingRecording", "training_blueprint"]

LEARNING_SERIES = ("loss", "epsilon", "q_taken", "steps_per_s")

# One colour per run, in the order a layout lists them (more runs repeat the colours).
RUN_COLOURS = np.array(
    [[80, 160, 255], [240, 120, 40], [60, 200, 110], [220, 80, 200], [230, 210, 60]],
    dtype=np.uint8,
)


class TrainingRecording:
    """Logs one training run's episodes, learning statistics and first car to a stream."""

    def __init__(
        self,
        stream: Any,
        run: str,
        colour_index: int = 0,
        ego_fields: Sequence[str] = (),
        action_names: Sequence[str] = ACTION_NAMES,
    ) -> None:
        """``ego_fields`` names the ego vector's fields in order (its observation's columns in
        the behaviour spec): the car's speed is read from its ``speed_mps``, when it has
        one (:class:`~overtake.viz.car_view.CarView`); ``action_names``: the behaviour spec's
        (highway-env's names in its scenes)."""
        import rerun as rr

        self.rr, self.stream, self.run = rr, stream, run
        self.root = f"trainer/{run}"
        self.car = CarView(stream, f"{self.root}/env0", ego_fields, action_names)
        self.colour = RUN_COLOURS[colour_index % len(RUN_COLOURS)]
        self._styled: set[str] = set()

    def _series(self, section: str, name: str) -> str:
        """The entity of ``name``'s line for this run, styled (named, coloured) once."""
        path = f"training/{section}/{name}/{self.run}"
        if path not in self._styled:
            self.stream.log(
                path,
                self.rr.SeriesLines(names=f"{self.run}: {name}", colors=[self.colour]),
                static=True,
            )
            self._styled.add(path)
        return path

    def arenas(self, server: str, arena_ids: Sequence[int]) -> None:
        """Which server's arenas this run drives (remote runs): a layout of a recording that
        also holds a spectator's view of the roads puts them beside this run's curves."""
        self.stream.log(
            f"{self.root}/arenas",
            self.rr.AnyValues(server=[server], arenas=[int(a) for a in arena_ids]),
            static=True,
        )

    def episode(self, step: int, metrics: dict[str, float]) -> None:
        rr = self.rr
        self.stream.set_time("step", sequence=step)
        for name, value in metrics.items():
            self.stream.log(self._series("episode", name), rr.Scalars(float(value)))

    def learning(self, step: int, entry: dict[str, Any]) -> None:
        rr = self.rr
        self.stream.set_time("step", sequence=step)
        for name in LEARNING_SERIES:
            value = entry.get(name)
            if value is not None:
                self.stream.log(self._series("learning", name), rr.Scalars(float(value)))

    def car_view(
        self,
        step: int,
        obs: dict[str, np.ndarray],
        action: int,
        q: np.ndarray,
        reward: float,
        terms: dict[str, float],
    ) -> None:
        """One environment's latest frame (``obs`` unbatched: ``lidar`` (R,) metres, ``camera``
        (H, W[, 3]) uint8, ``ego`` the ego vector), the action it took, the Q-values
        of every action, and the reward it got for it with each term."""
        self.stream.set_time("step", sequence=step)
        self.car.log(obs, action, q, reward, terms)


def open_training_recording(
    config: RecordingConfig,
    rrd: Path,
    run_name: str,
    algo: str,
    ego_fields: Sequence[str],
    arenas: tuple[str, tuple[int, ...]] | None,
    road: tuple[str, float] | None = None,
    pictures: Collection[str] = CAR_PICTURES,
    action_names: Sequence[str] = ACTION_NAMES,
) -> tuple[Recording | None, TrainingRecording | None]:
    """A training run's recording (to ``rrd`` with a file sink) and its view: coloured by
    algorithm (DQN, Double DQN and Dueling keep their colours in every recording that holds
    several runs), with the server's ``arenas`` environment 0 lies among (None in-process).
    No footer: a run may write for days, and the SDK would hold the footer's index in memory
    until the end (overtake.viz.recording, on footers; bench/reliability/recording_memory.py).
    ``road``: an in-process run's road (its entity path and width, m), drawn above its car's
    view; ``pictures``: which of the camera and the LIDAR its car observes (the view shows
    those, and the speed where the ego vector has it); ``action_names``: the behaviour
    spec's."""
    if config.sink == "off":  # before the blueprint: it imports Rerun (0.6 CPU-s a process)
        return None, None
    layout = training_blueprint(
        run_name, road=road, pictures=pictures, show_speed="speed_mps" in ego_fields
    )
    recording = open_recording(APPLICATION_ID, config, rrd, layout, footer=False)
    if recording is None:
        return None, None
    view = TrainingRecording(
        recording.stream,
        run_name,
        colour_index=list(ALGOS).index(algo),
        ego_fields=tuple(ego_fields),
        action_names=action_names,
    )
    if arenas is not None:
        view.arenas(*arenas)
    return recording, view
