"""Action semantics: what each discrete action asks of the car.

Min et al.'s five DAS-level actions (§II.C), in the order of
:data:`~overtake.protocol.vocabulary.ACTION_NAMES`: keep, cruise target +5 km/h, cruise target
-5 km/h, change lane left, change lane right. An action only asks; driver assistance
(:mod:`.assist`) does the driving, and may refuse a lane change (no lane there, one under way,
or the side not clear), in which case the car keeps its lane and ``applied`` says keep.
"""

from __future__ import annotations

import numpy as np

from overtake.protocol.vocabulary import (
    ACTION_COUNT,
    ACTION_NAMES,
    CRUISE_DOWN,
    CRUISE_UP,
    KEEP,
    LANE_LEFT,
    LANE_RIGHT,
)

from .assist import CruiseControl, DriverWarnings, EgoConfig, LaneChangeAssist
from .state import SimState
from .units import KMH


class DasActions:
    """Min et al.'s actions: cruise target steps and lane-change requests."""

    names = ACTION_NAMES
    count = ACTION_COUNT

    def __init__(self, ego: EgoConfig, agents: int, lane_changes: LaneChangeAssist) -> None:
        self.cruise_step_mps = ego.cruise_step_kmh * KMH
        self.cruise = CruiseControl(ego, agents)
        # Under Ho's speed steps the speed actions act frame by frame in the physics
        # (:class:`~.assist.SpeedSteps`): there is no cruise target to move.
        self.moves_cruise_target = ego.speed_control == "cruise"
        self.lane_changes = lane_changes
        self.mask_refusals = ego.mask_refusals

    def check(self, actions: np.ndarray, expected: tuple[int, ...]) -> np.ndarray:
        """``actions`` as int64 if they are integers of shape ``expected`` in range; else a
        ValueError saying what came."""
        actions = np.asarray(actions)
        if actions.shape != expected or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(
                f"expected integer actions of shape {expected}, got {actions.dtype} {actions.shape}"
            )
        if actions.size and (actions.min() < 0 or actions.max() >= self.count):
            bad = actions[(actions < 0) | (actions >= self.count)]
            raise ValueError(
                f"actions must be in [0, {self.count}) "
                f"({', '.join(self.names)}), got {bad.tolist()}"
            )
        return actions.astype(np.int64)

    def apply(self, st: SimState, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Apply (A, N) actions to the agents of ``st``; returns the lane changes that started
        and the actions applied (a refused lane change becomes keep)."""
        if self.moves_cruise_target:
            step = self.cruise_step_mps
            self.cruise.adjust(st, step * (actions == CRUISE_UP) - step * (actions == CRUISE_DOWN))
        started = self.lane_changes.start(st, actions == LANE_LEFT, actions == LANE_RIGHT)
        lateral = (actions == LANE_LEFT) | (actions == LANE_RIGHT)
        applied = np.where(lateral & ~started, KEEP, actions)
        return started, applied

    def mask(self, st: SimState) -> np.ndarray:
        """(A, N, actions) int8: 1 where the action can be taken now (with
        ``ego.mask_refusals``, also 0 where driver assistance would refuse it)."""
        changes = self.lane_changes
        left, right = changes.allowed(st) if self.mask_refusals else changes.possible(st)
        mask = np.ones(left.shape + (self.count,), dtype=np.int8)
        mask[..., LANE_LEFT] = left
        mask[..., LANE_RIGHT] = right
        return mask

    def against_warnings(self, actions: np.ndarray, warnings: np.ndarray) -> np.ndarray:
        """(A, N) bool: the actions that went against a warning the agent had (a lane change
        towards a side warning, accelerating with a forward warning)."""
        return (
            ((actions == LANE_LEFT) & warnings[..., DriverWarnings.LEFT])
            | ((actions == LANE_RIGHT) & warnings[..., DriverWarnings.RIGHT])
            | ((actions == CRUISE_UP) & warnings[..., DriverWarnings.FORWARD])
        )
