"""Safety in a training run: the shield of :mod:`overtake.client.policies.shield` judging from
the run's stacked frames (``overtake-train --shield``), the count of the decisions where it
forbade the network's greedy choice, and what the replay stores where safety stepped in
(:class:`SafetyLayer`)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from overtake.cli import UsageError
from overtake.client.episodes.records import EventCounts
from overtake.client.policies.shield import Shield, overridden
from overtake.protocol.messages import BehaviourSpec
from overtake.protocol.vocabulary import WATCH_METRICS

from ..learning.replay_memory import FrameStacker

if TYPE_CHECKING:
    from ..learning.learner import DQNConfig

(LANE_CHANGE_ABORTS,) = WATCH_METRICS


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

    def count(self, q: np.ndarray, env_mask: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The decisions of this batch where the shield forbade the network's greedy choice,
        (N,) bool; counted in :attr:`overrides`."""
        flags = overridden(q, env_mask, mask)
        self.overrides += int(flags.sum())
        return flags


class SafetyLayer:
    """What a training run does about safety: the shield's mask (where ``shield`` is given),
    the count of its overrides, and what the replay stores where safety stepped in
    (``dqn.store_applied``, ``dqn.intervention_penalty``), for ``num_envs`` environments."""

    def __init__(self, shield: TrainingShield | None, dqn: DQNConfig, num_envs: int) -> None:
        self.shield = shield
        self.store_applied = dqn.store_applied
        self.penalty = dqn.intervention_penalty
        # Per environment: where the shield overrode the greedy choice at its last decision,
        # and the lane changes driver assistance had turned back in its episode so far.
        self.overridden = np.zeros(num_envs, dtype=bool)
        self.aborts = EventCounts(num_envs, names=(LANE_CHANGE_ABORTS,))

    def state(self) -> dict[str, Any]:
        """What it carries from one decision to the next (a training run's checkpoint keeps
        it): the marks per environment and the shield's count."""
        return {
            "overridden": self.overridden.copy(),
            "aborts": {name: value.copy() for name, value in self.aborts.counts.items()},
            "shield_overrides": self.overrides,
        }

    def load_state(self, state: dict[str, Any]) -> None:
        self.overridden[:] = state["overridden"]
        for name, value in self.aborts.counts.items():
            value[:] = state["aborts"][name]
        if self.shield is not None:
            self.shield.overrides = int(state["shield_overrides"] or 0)

    @property
    def overrides(self) -> int | None:
        """The shield's overrides so far (None without a shield)."""
        return self.shield.overrides if self.shield is not None else None

    def mask(self, envs: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """The action mask of the environments ``envs`` to act and learn under."""
        return mask if self.shield is None else self.shield.mask(envs, mask)

    def count(self, envs: np.ndarray, q: np.ndarray, env_mask: np.ndarray, mask: np.ndarray) -> int:
        """Note (and return how many) of the environments ``envs`` had their greedy choice
        overridden by the shield at this decision."""
        if self.shield is None:
            return 0
        flags = self.shield.count(q, env_mask, mask)
        self.overridden[envs] = flags
        return int(flags.sum())

    def stored(
        self, envs: np.ndarray, actions: np.ndarray, reward: np.ndarray, info: dict[str, Any]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The actions and rewards of a step of ``envs`` to store: with ``store_applied`` the
        actions the cars applied; less ``penalty`` where safety stepped in (the shield
        overrode the greedy choice, driver assistance refused the action or turned a lane
        change back)."""
        applied = np.asarray(info.get("action_applied", actions))
        chosen = actions
        if self.store_applied:
            # -1: the autoreset step, whose action was ignored (and is not stored).
            actions = np.where(applied >= 0, applied, actions)
        turned_back = self.aborts.rose(info, envs).get(
            LANE_CHANGE_ABORTS, np.zeros(len(envs), dtype=bool)
        )
        if self.penalty > 0.0:
            # A late action (the trainer missed the server's deadline) was replaced by keep:
            # not safety stepping in.
            late = np.asarray(info.get("late", False))
            stepped_in = ((applied >= 0) & (applied != chosen) & ~late) | turned_back
            stepped_in |= self.overridden[envs]
            reward = reward - self.penalty * stepped_in
        return actions, reward
