"""Rewards: terms computed from one decision's facts, each weighted, listed by the preset.

A term is a function of :class:`StepFacts` and the reward configuration that returns its
weighted value per agent (A, N). The preset lists the terms it uses (``reward.terms``), in the
order they are added up and reported (``info["reward_terms"]``, the spec's ``reward_terms``);
each term's weight and parameters are fields of :class:`RewardConfig`. Adding a term is a
function and an entry in :data:`TERMS` here, its weight below, and its name in a preset.

Min et al. (2018) Table I is the default: the speed term (Eq. 1, linear from 40 to 80 km/h),
collision -10, lane change -0.25 (Eq. 3), overtake +0.5 (Eq. 4, once per car passed); and,
from the authors' code, -0.1 for acting against a warning (a lane change to a side with a side
warning, or accelerating with a forward warning). Ho (2018, §7.2 and Table 6) rewards +1 for
every car passed and -1 for every car that passes (``overtake`` and ``passed``, every crossing
counted: ``overtakes_counted = "every_pass"``) and -0.00001 for a lane change opposite to one
among the last four actions (``alternation``). Fayjie et al. (2018, §III.B) reward each
action taken (``action``: keep going the speed / 5, accelerate +1, brake -0.4, left -0.6,
right -0.2) and a hit -6 (``collision``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from overtake.protocol.vocabulary import KEEP

from .units import KMH
from .validation import check, check_flag, check_range


# Built every decision: a plain record (a frozen one pays a setattr call per field).
@dataclass(slots=True)
class StepFacts:
    """What one decision did, per agent (A, N): what reward terms are computed from."""

    speed_mps: np.ndarray  # float64, after the decision
    collided: np.ndarray  # bool
    lane_change_started: np.ndarray  # bool
    overtakes: np.ndarray  # int64: cars passed (each counted once)
    overtakes_undone: np.ndarray  # int64: earlier overtakes taken back
    passed_by: np.ndarray  # int64: cars that passed the agent
    against_warning: np.ndarray  # bool: the action went against a warning the agent had
    alternated: np.ndarray  # bool: a lane change opposite to one among the recent actions
    applied: np.ndarray  # int64: the action the car took (a refused lane change: keep)


@dataclass(frozen=True, slots=True)
class RewardConfig:
    """Min et al. (2018) Table I by default; every term is reported on its own in info."""

    # The terms this preset rewards, in the order they are summed and reported.
    terms: tuple[str, ...] = ("speed", "collision", "lane_change", "overtake", "warning")
    speed_min_kmh: float = 40.0
    speed_max_kmh: float = 80.0
    speed_reward_max: float = 1.0
    # Min et al.'s code keeps the speed term in [0, r_v,max]; False leaves Eq. (1) unclipped.
    clip_speed_term: bool = True
    collision: float = -10.0
    lane_change: float = -0.25
    overtake: float = 0.5
    # Reward per car that passes the agent (Ho: -1; Min et al.: none, not in their terms).
    passed: float = 0.0
    # Acting against a warning (the authors' code's "violation reward").
    warning: float = -0.1
    # When a car the agent overtook passes it back, take that overtake back (count and reward).
    undo_overtake_when_passed_back: bool = False
    # Which passes count as overtakes (count and reward): "once_per_car" (Min et al.: a car
    # passed again after it passed the agent is not counted again), or "every_pass" (Ho: his
    # score moves by one at every crossing, whichever car it is).
    overtakes_counted: Literal["once_per_car", "every_pass"] = "once_per_car"
    # A lane change to one side while a change to the other side is among the agent's last
    # ACTION_HISTORY actions (Ho, Table 6: "line switching penalty", -0.00001).
    alternation: float = -0.00001
    # Fayjie et al. (2018, §III.B): a reward per action taken. Keep going earns the speed
    # (m/s, Unity's unit) times action_keep_per_mps (their "speed/5"); the others a constant.
    action_keep_per_mps: float = 0.2
    action_accelerate: float = 1.0
    action_brake: float = -0.4
    action_left: float = -0.6
    action_right: float = -0.2

    def __post_init__(self) -> None:
        check(
            len(self.terms) >= 1
            and len(set(self.terms)) == len(self.terms)
            and all(term in TERMS for term in self.terms),
            "reward.terms",
            self.terms,
            f"distinct names from {sorted(TERMS)}, at least one",
        )
        check_range("reward.speed_min_kmh", self.speed_min_kmh, 0.0, 300.0)
        check_range(
            "reward.speed_max_kmh", self.speed_max_kmh, self.speed_min_kmh, 300.0, low_open=True
        )
        weights = (
            "speed_reward_max",
            "collision",
            "lane_change",
            "overtake",
            "passed",
            "warning",
            "alternation",
            "action_keep_per_mps",
            "action_accelerate",
            "action_brake",
            "action_left",
            "action_right",
        )
        for name in weights:
            check_range(f"reward.{name}", getattr(self, name), -1000.0, 1000.0)
        for name in ("clip_speed_term", "undo_overtake_when_passed_back"):
            check_flag(f"reward.{name}", getattr(self, name))
        check(
            self.overtakes_counted in ("once_per_car", "every_pass"),
            "reward.overtakes_counted",
            self.overtakes_counted,
            "once_per_car or every_pass",
        )


def _speed(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    """Eq. (1): linear in the speed from ``speed_min_kmh`` (0) to ``speed_max_kmh`` (1)."""
    speed_kmh = facts.speed_mps / KMH
    term = (speed_kmh - rc.speed_min_kmh) / (rc.speed_max_kmh - rc.speed_min_kmh)
    if rc.clip_speed_term:
        term = np.clip(term, 0.0, 1.0)
    return term * rc.speed_reward_max


def _collision(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    return rc.collision * facts.collided


def _lane_change(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    return rc.lane_change * facts.lane_change_started


def _overtake(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    return rc.overtake * (facts.overtakes - facts.overtakes_undone)


def _passed(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    return rc.passed * facts.passed_by.astype(np.float64)


def _warning(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    return rc.warning * facts.against_warning


def _alternation(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    return rc.alternation * facts.alternated


def _action(facts: StepFacts, rc: RewardConfig) -> np.ndarray:
    """Fayjie et al.'s reward per action: keep going earns its speed, the others a constant."""
    constants = np.array(
        [0.0, rc.action_accelerate, rc.action_brake, rc.action_left, rc.action_right]
    )
    keep = facts.applied == KEEP
    return np.where(keep, rc.action_keep_per_mps * facts.speed_mps, constants[facts.applied])


# Every term the simulator can reward, by name.
TERMS: dict[str, Callable[[StepFacts, RewardConfig], np.ndarray]] = {
    "speed": _speed,
    "collision": _collision,
    "lane_change": _lane_change,
    "overtake": _overtake,
    "passed": _passed,
    "warning": _warning,
    "alternation": _alternation,
    "action": _action,
}


class Rewards:
    """The preset's reward: its terms, computed and summed in the preset's order."""

    def __init__(self, config: RewardConfig) -> None:
        self.config = config
        self.names = config.terms
        self._terms = tuple(TERMS[name] for name in config.terms)
        # The warnings at each decision's start are worked out only for a reward that uses them.
        self.needs_warnings = "warning" in config.terms
        # ... and the agents' recent actions only for one that uses them.
        self.needs_recent_actions = "alternation" in config.terms

    def compute(self, facts: StepFacts) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """The reward (A, N) float64 and each term's weighted value, by name."""
        values = {
            name: term(facts, self.config)
            for name, term in zip(self.names, self._terms, strict=True)
        }
        parts = iter(values.values())
        reward = np.array(next(parts), dtype=np.float64)
        for part in parts:
            reward += part
        return reward, values
