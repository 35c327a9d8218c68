"""Ho's action stack (2018, §5): the agent's last actions, a second input beside the grid.

The last :data:`~overtake.server.sim.state.ACTION_HISTORY` actions the agent's car took (the
action applied: a refused lane change reads keep, and under ``ego.applied_as_driven`` an
action his safety rule changed reads what it became), oldest first, as action indices of
:data:`~overtake.protocol.vocabulary.ACTION_NAMES` in float32, the way Ho's network reads its
stack of action indices. Before an episode's first decisions the stack holds keep (Ho's code
starts it with his "maintain").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from overtake.protocol.vocabulary import ACTION_COUNT

from ..state import ACTION_HISTORY
from ..validation import check_flag
from .base import Scene, SensorConfig, SensorFacts, SensorSpace

if TYPE_CHECKING:
    from ..config import SimConfig


@dataclass(frozen=True, slots=True)
class ActionHistoryConfig(SensorConfig):
    """The ``actions`` observation: (ACTION_HISTORY,) float32 action indices per agent."""

    OBSERVATION: ClassVar[str] = "actions"

    enabled: bool = False

    def __post_init__(self) -> None:
        check_flag("action_history.enabled", self.enabled)

    def build(self, config: SimConfig) -> ActionHistory:
        return ActionHistory()


class ActionHistory:
    key = "actions"

    def space(self) -> SensorSpace:
        return SensorSpace.uniform((ACTION_HISTORY,), np.float32, 0.0, ACTION_COUNT - 1)

    def facts(self) -> SensorFacts:
        """The last actions, oldest first: nothing of the road."""
        return SensorFacts()

    def observe(self, scene: Scene) -> np.ndarray:
        return scene.state.recent_actions.astype(np.float32)
