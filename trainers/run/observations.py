"""What the learner reads of the environment's observation space.

:func:`frame_shapes` picks the observations a network of the given inputs uses (the ego vector
with camera and/or LIDAR, or the occupancy grid with the action stack) as the replay and the
frame stacker store them, for training and evaluation alike; :func:`describe_space` is the space
as plain data for the run record and the checkpoint.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

from overtake.cli import UsageError
from overtake.client.policies.frames import FrameShapes, describe_space

__all__ = ["describe_space", "frame_shapes"]
from overtake.protocol import ACTION_COUNT

from ..learning.network import Inputs, observations_read


def frame_shapes(
    space: gym.spaces.Dict, inputs: Inputs, where: str = "this preset's environment"
) -> FrameShapes:
    """The per-frame observations the learner uses, as the replay stores them; ``where`` names
    the environment in the error for one it does not send."""
    wanted = set(observations_read(inputs))
    missing = wanted - set(space.spaces)
    if missing:
        raise UsageError(
            f"--inputs {inputs} needs the observation(s) {sorted(missing)}, which "
            f"{where} does not send (it sends {sorted(space.spaces)}; check the preset and "
            "its sensors' <sensor>.enabled)"
        )
    boxes = {name: _box(space, name) for name in sorted(wanted)}
    return FrameShapes(
        {name: (box.shape, np.dtype(box.dtype)) for name, box in boxes.items()},
        actions=ACTION_COUNT,
    )


def _box(space: gym.spaces.Dict, name: str) -> gym.spaces.Box:
    box = space[name]
    if not isinstance(box, gym.spaces.Box):
        raise UsageError(f"observation {name!r} must be a Box space, got {box}")
    return box
