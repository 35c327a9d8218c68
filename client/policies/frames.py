"""Frames as policies see them: the last few observations of each environment, stacked.

The environment sends one frame per decision; a policy acting on stacked frames keeps the last
``stack`` of them per environment (:class:`FrameStacker`), and the replay of
:mod:`overtake.trainers.learning.replay_memory` rebuilds the same stacks when it samples.
Both follow one rule at an episode's start: the slots before the first frame hold copies of
that first frame (a LIDAR of zeros would read as a wall at 0 m). This lives in the client,
without PyTorch, so that an exported policy (:mod:`overtake.client.policies.onnx_policy`)
stacks exactly as its trainer did.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

Frames = Mapping[str, np.ndarray]  # name -> (k, ...) one frame per listed environment


@dataclass(frozen=True)
class FrameShapes:
    """Per-frame observations the replay stores: name -> (shape, dtype)."""

    shapes: Mapping[str, tuple[tuple[int, ...], np.dtype]]
    actions: int


class FrameStacker:
    """The last ``stack`` frames of each stacked observation, per environment (acting side).

    ``stacked`` observations (camera, lidar) come out as (N, stack, ...), oldest first; the
    others (ego) as the latest frame only.
    """

    def __init__(
        self, num_envs: int, shapes: FrameShapes, stack: int, stacked: tuple[str, ...]
    ) -> None:
        self.stack, self.stacked = stack, stacked
        self.frames = {
            name: np.zeros((num_envs, stack) + tuple(shape), dtype=dtype)
            for name, (shape, dtype) in shapes.shapes.items()
            if name in stacked
        }
        self.latest = {
            name: np.zeros((num_envs,) + tuple(shape), dtype=dtype)
            for name, (shape, dtype) in shapes.shapes.items()
            if name not in stacked
        }

    def reset(self, envs: np.ndarray, frames: Frames) -> None:
        """Start episodes in ``envs``: every slot of their stacks holds the first frame."""
        for name, stack in self.frames.items():
            stack[envs] = frames[name][:, None]
        for name, latest in self.latest.items():
            latest[envs] = frames[name]

    def push(self, envs: np.ndarray, frames: Frames) -> None:
        for name, stack in self.frames.items():
            stack[envs, :-1] = stack[envs, 1:]
            stack[envs, -1] = frames[name]
        for name, latest in self.latest.items():
            latest[envs] = frames[name]

    def take(self, frames: Frames, starting: np.ndarray) -> dict[str, np.ndarray]:
        """Every environment's new frame (``frames``: a row each): those ``starting`` an
        episode restart their stacks with it, the others push it; returns the stacked
        observation a policy acts on."""
        fresh, moving = np.flatnonzero(starting), np.flatnonzero(~np.asarray(starting))
        if fresh.size:
            self.reset(fresh, {name: frames[name][fresh] for name in self._names})
        if moving.size:
            self.push(moving, {name: frames[name][moving] for name in self._names})
        return self.observation()

    @property
    def _names(self) -> tuple[str, ...]:
        return (*self.frames, *self.latest)

    def observation(self) -> dict[str, np.ndarray]:
        return {**self.frames, **self.latest}

    def state(self) -> dict[str, np.ndarray]:
        """Copies of every stack and latest frame (a training run's checkpoint keeps them)."""
        return {name: value.copy() for name, value in self.observation().items()}

    def load_state(self, state: Mapping[str, np.ndarray]) -> None:
        """Back to a :meth:`state` of a stacker of the same shapes."""
        for name, value in self.observation().items():
            saved = np.asarray(state[name])
            if saved.shape != value.shape or saved.dtype != value.dtype:
                raise ValueError(
                    f"the saved stack {name} is {saved.dtype}{saved.shape}, this stacker's "
                    f"{value.dtype}{value.shape}"
                )
            value[...] = saved


def describe_space(space: gym.spaces.Dict) -> dict[str, Any]:
    """Each observation's shape, dtype and bounds, as JSON-ready data."""
    described: dict[str, Any] = {}
    for name, box in space.spaces.items():
        if not isinstance(box, gym.spaces.Box):
            raise ValueError(f"observation {name!r} must be a Box space, got {box}")
        described[name] = {
            "shape": list(box.shape),
            "dtype": np.dtype(box.dtype).name,
            "low": float(np.min(box.low)),
            "high": float(np.max(box.high)),
        }
    return described
