"""The safety shield in a training run (``overtake-train --shield``): the shield of
:mod:`overtake.client.policies.shield` judging from the run's stacked frames, and the count of the
decisions where it forbade the network's greedy choice."""

from __future__ import annotations

import numpy as np

from overtake.client.commands import UsageError
from overtake.client.policies.shield import Shield, overridden
from overtake.protocol.messages import BehaviourSpec

from .replay import FrameStacker


class TrainingShield:
    """The shield of a run whose frames ``stacker`` stacks; ``overrides`` counts the decisions
    where it forbade the network's greedy choice."""

    def __init__(self, spec: BehaviourSpec | None, stacker: FrameStacker, inputs: str) -> None:
        if spec is None:
            raise UsageError(
                "--shield reads the environment's behaviour spec (its road, car and LIDAR); "
                "this environment has none"
            )
        missing = [name for name in ("lidar", "ego") if name not in stacker.observation()]
        if missing:
            raise UsageError(
                f"--shield reads the stacked LIDAR scans and the ego vector; inputs "
                f"{inputs} keep no {' or '.join(missing)}"
            )
        self.shield, self.stacker = Shield(spec), stacker
        self.overrides = 0

    def mask(self, envs: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The environments' action mask of ``envs`` and the shield's together (judged from
        their stacked frames, which must already hold the newest)."""
        stacked = self.stacker.observation()
        return mask & self.shield.mask(stacked["lidar"][envs], stacked["ego"][envs])

    def count(self, q: np.ndarray, env_mask: np.ndarray, mask: np.ndarray) -> int:
        """Count (and return) the decisions of this batch where the shield forbade the
        network's greedy choice."""
        count = int(overridden(q, env_mask, mask).sum())
        self.overrides += count
        return count
