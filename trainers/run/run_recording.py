"""What a training run logs to Rerun: its episodes and learning (:mod:`.visual`'s plots), and
every ``record_every`` iterations what environment 0's car saw and did, with, in process,
environment 0's road from above (a remote run's road is a server's or a spectator's to
record)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from overtake.protocol.messages import BehaviourSpec
from overtake.protocol.vocabulary import ACTION_NAMES
from overtake.viz.recording import Recording, RecordingConfig, close_recording
from overtake.viz.training_layout import CAR_PICTURES
from overtake.viz.world_view import WorldRecording

from .env_parts import EnvParts
from .visual import TrainingRecording, open_training_recording

# Where an in-process run's recording draws environment 0's road (a world frame's entities).
IN_PROCESS_ROAD = "/world/in-process/arena0/road"


def _ego_fields(spec: BehaviourSpec | None) -> tuple[str, ...]:
    """The fields of the ego vector observation, in order, from the environment's behaviour
    spec (none where it has no ego vector, or no spec: an environment of the caller's)."""
    return spec.observation("ego").columns if spec is not None and spec.has("ego") else ()


class RunRecording:
    """A training run's Rerun recording and its views; :meth:`open` gives None where the
    run records nothing (``--sink off``)."""

    def __init__(
        self,
        recording: Recording,
        view: TrainingRecording,
        world: WorldRecording | None,
        env: EnvParts,
    ) -> None:
        self.recording, self.view, self.world, self.env = recording, view, world, env

    @classmethod
    def open(
        cls, config: RecordingConfig, path: Path, run_name: str, algo: str, env: EnvParts
    ) -> RunRecording | None:
        spec = env.behaviour_spec
        road = (
            (IN_PROCESS_ROAD, spec.road.lane_count * spec.road.lane_width_m)
            if env.road is not None and spec is not None and spec.road is not None
            else None
        )
        # The pictures the car has (an environment of the caller's: both panels, as ever).
        pictures = CAR_PICTURES if spec is None else [p for p in CAR_PICTURES if spec.has(p)]
        # The actions as the preset names them (highway-env's names in its scenes).
        names = spec.action_names if spec is not None else ACTION_NAMES
        recording, view = open_training_recording(
            config,
            path,
            run_name,
            algo,
            _ego_fields(spec),
            env.recorded_arenas(),
            road,
            pictures,
            names,
        )
        if recording is None or view is None:
            return None
        world = (
            WorldRecording(recording.stream, rays=False, lay_out=False, action_names=names)
            if road is not None
            else None
        )
        return cls(recording, view, world, env)

    def car_view(
        self,
        step: int,
        seen: dict[str, np.ndarray],
        actions: np.ndarray,
        q: np.ndarray,
        reward: np.ndarray,
        info: dict[str, Any],
    ) -> None:
        """Environment 0's view (``seen``: what the network read), action, Q-values, reward
        and reward terms; in process also its road after the step."""
        terms = {name: float(v[0]) for name, v in info.get("reward_terms", {}).items()}
        self.view.car_view(
            step,
            {k: v[0] for k, v in seen.items()},
            int(actions[0]),
            q[0],
            float(reward[0]),
            terms,
        )
        if self.world is not None and self.env.road is not None:
            # The road after the step, its frame on the run's step (EnvParts.label_step).
            self.world.log(self.env.road.world_frame(0))

    def episode(self, step: int, metrics: dict[str, float]) -> None:
        self.view.episode(step, metrics)

    def learning(self, step: int, entry: dict[str, Any]) -> None:
        self.view.learning(step, entry)

    def close(self) -> None:
        close_recording(self.recording)
