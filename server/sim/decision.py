"""One decision of the simulation, in order: the actions, traffic's manoeuvres, the physics
frames, overtakes and traffic's treadmill, the reward and the episodes' books.

:class:`Decision` holds the parts :class:`~.core.HighwaySim` built and steps them on the state
of the arenas that step (:meth:`~.core.HighwaySim.step` picks them and draws their uniforms).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import LANE_LEFT, LANE_RIGHT

from .lane_index import LaneSorter, leaders
from .rewards import StepFacts

if TYPE_CHECKING:
    from .core import HighwaySim
    from .state import SimState


@dataclass(frozen=True)
class StepResult:
    """What one decision produced, per arena and agent: (A, N) unless noted."""

    reward: np.ndarray  # float64
    reward_terms: dict[str, np.ndarray]  # name -> float64, in the preset's order
    terminated: np.ndarray  # bool: collided
    truncated: np.ndarray  # bool: the episode reached its decision limit
    action_applied: np.ndarray  # int64: the action actually taken (refused -> keep; with
    # ego.applied_as_driven, as the car drove it in the decision's first frame)

    @property
    def ended(self) -> np.ndarray:
        """(A, N) bool: episodes that ended (with an autoreset, they restart next round)."""
        return self.terminated | self.truncated


class Decision:
    """The order of one decision's parts, over the parts of ``sim``."""

    uses_uniforms = True  # each decision's block of random numbers (randomness.py)

    def __init__(self, sim: HighwaySim) -> None:
        self.agents = sim.agents
        self.frames = sim.frames
        self.actions = sim.actions
        self.kinds = sim.kinds
        self.manoeuvres = sim.manoeuvres
        self.physics = sim.physics
        self.tracker = sim.tracker
        self.spawner = sim.spawner
        self.rewards = sim.rewards
        self.episodes = sim.episodes
        self.keeps_warnings = sim.keeps_warnings
        self.note_warnings: Callable[[SimState], None] = sim._note_warnings
        # The agents' recent actions are kept where the reward or a sensor reads them.
        self.keeps_recent_actions = (
            sim.rewards.needs_recent_actions or sim.config.action_history.enabled
        )
        # Ho's speed steps: each frame's speed commands come from the decision's actions.
        self.speed_steps = sim.physics.speed_steps
        # Ho's code: the action applied is what the car did in the decision's first frame, and
        # the skipped frames repeat it (ego.applied_as_driven).
        self.as_driven = sim.config.ego.applied_as_driven
        self._lanes = LaneSorter(sim.road.lane_count)
        # Whether some lane change ends within its first frame (see advance).
        self.instant_changes = bool((sim.kinds.change_duration <= sim.dt).any())

    def advance(
        self,
        st: SimState,
        actions: np.ndarray,
        uniforms: np.ndarray | None,
        rows: np.ndarray | None = None,
    ) -> StepResult:
        """One decision of the arenas ``rows`` of ``st`` (None: all; the others do not move):
        their ``actions`` and uniforms. A subset is stepped on a copy of its rows, written
        back after."""
        if rows is None:
            return self._advance(st, actions, uniforms)
        subset = st.select(rows)
        result = self._advance(subset, actions, uniforms)
        st.assign(rows, subset)
        return result

    def _advance(
        self, st: SimState, actions: np.ndarray, uniforms: np.ndarray | None
    ) -> StepResult:
        assert uniforms is not None, "the papers' decision draws its random numbers (uses_uniforms)"
        n = self.agents
        # What the agents were warned of when they chose (the observation they acted on).
        warned = st.warnings.copy() if self.keeps_warnings else None
        started, applied = self.actions.apply(st, actions)
        # Ho's alternation reads the lane change chosen (car.py's ``result``), not as driven.
        alternated = self._alternated(st, applied)
        if self.as_driven:
            applied = applied.copy()
        steps = self.speed_steps
        first_command, later_command = (None, None) if steps is None else steps.commands(actions)
        random_movers = self.manoeuvres.decide(st, uniforms)
        params = self.kinds.params(st.kind)
        collided = np.zeros((st.x_m.shape[0], n), dtype=bool)
        brakes = np.zeros((st.x_m.shape[0], n), dtype=np.int64)
        # Who follows whom is sorted out once per decision. Within a decision lanes only lose
        # members (changes that finish), so a frame-0 leader is never farther than the true
        # one: keeping it for the decision's frames is conservative. Traffic that starts a
        # change at frame 0 is seen in its new lane from the next decision: 0.3 s at most,
        # less than a driver's reaction time, while it has moved sideways by under 2 cm. A
        # lane change done within one frame (Ho's) moves a car wholly into its new lane on
        # frame 0: who follows whom is sorted out again after it, where some car did.
        index = self._lanes.build(st.x_m - st.x_m[:, :1], st.lane, st.target_lane, st.active)
        lead, valid = leaders(index)
        lanes_before = st.lane.copy() if self.instant_changes and self.frames > 1 else None
        for frame in range(self.frames):
            self.physics.frame(
                st,
                params,
                lead,
                valid,
                collided,
                brakes,
                mobil_index=index if frame == 0 else None,
                random_movers=random_movers,
                speed_command=first_command if frame == 0 else later_command,
                as_driven=applied if self.as_driven and frame == 0 else None,
            )
            if frame == 0 and self.as_driven and steps is not None:
                later_command = steps.skipped[applied]  # his action_cache: the action as driven
            if frame == 0 and lanes_before is not None and (st.lane != lanes_before).any():
                x_rel = st.x_m - st.x_m[:, :1]
                index = self._lanes.build(x_rel, st.lane, st.target_lane, st.active)
                lead, valid = leaders(index)
        self._remember_actions(st, applied)
        gained, undone, passed = self.tracker.track(st)
        self.spawner.recycle(st, uniforms)
        self.note_warnings(st)
        st.decisions += 1
        st.agent_decisions += 1
        reward, terms = self.rewards.compute(
            StepFacts(
                speed_mps=st.speed_mps[:, :n],
                collided=collided,
                lane_change_started=started,
                overtakes=gained,
                overtakes_undone=undone,
                passed_by=passed,
                against_warning=(
                    self.actions.against_warnings(actions, warned)
                    if warned is not None
                    else np.zeros_like(collided)
                ),
                alternated=np.zeros_like(collided) if alternated is None else alternated,
                applied=applied,
            )
        )
        truncated = self.episodes.close_decision(
            st, reward, started, collided, gained - undone, brakes
        )
        return StepResult(
            reward=reward,
            reward_terms=terms,
            terminated=collided,
            truncated=truncated & ~collided,
            action_applied=applied,
        )

    def _alternated(self, st: SimState, applied: np.ndarray) -> np.ndarray | None:
        """Which agents changed lanes opposite to a change among their recent actions (Ho's
        alternation), or None where those are not kept."""
        if not self.keeps_recent_actions:
            return None
        recent = st.recent_actions
        return ((applied == LANE_LEFT) & (recent == LANE_RIGHT).any(axis=-1)) | (
            (applied == LANE_RIGHT) & (recent == LANE_LEFT).any(axis=-1)
        )

    def _remember_actions(self, st: SimState, applied: np.ndarray) -> None:
        """Push the decision's applied actions onto the agents' recent actions, where they are
        kept."""
        if not self.keeps_recent_actions:
            return
        recent = st.recent_actions
        recent[..., :-1] = recent[..., 1:]
        recent[..., -1] = applied
