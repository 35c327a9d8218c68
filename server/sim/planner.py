"""A privileged planner: an upper reference for what the agents could do, not a policy to train.

It reads the true state of every car (no sensor, no noise) and plans by simulating: each
decision it copies every arena into a shadow simulation, once per option, and drives each copy
``horizon_s`` of simulated time ahead (6 s: 15 of Min et al.'s decisions, 75 of Ho's) with the
agents' own actions:

- stay: keep the lane; accelerate whenever there is no forward warning (as below);
- for each agent, change lanes left, or right, now, then the same (the others stay).

Traffic in the copies acts with the same random draws in every option (the real future's are
not used: the planner does not know them). An agent takes the option in which it travels
farthest without colliding; a lane change must win by ``better_by_m``. With no lane change
worth it, it accelerates below the limit unless a car ahead is within its forward warning
(the reward's "warning" term costs the agents for that), and leaves braking to cruise control
and emergency braking (under Ho's speed steps: to his safety rule, warnings not heeded).

``overtake-eval --policy planner`` runs it beside the trained rows (in-process only: a remote
simulator keeps its state to itself). Each decision costs ``1 + 2 * agents`` shadow copies
times the horizon in simulated decisions, without sensors.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass
from typing import Any

import numpy as np

from overtake.protocol.vocabulary import CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT

from .assist import DriverWarnings
from .core import HighwaySim
from .state import SimState
from .units import KMH


@dataclass(frozen=True, slots=True)
class PlannerConfig:
    """How far ahead the planner simulates, and what a lane change must gain."""

    horizon_s: float = 6.0
    better_by_m: float = 3.0
    # An option ends worth its distance plus its final speed for this long: being stuck
    # behind a slow car at the horizon costs what it will cost after it.
    terminal_time_s: float = 0.0
    seed: int = 0


class Planner:
    """Actions (A, N) for every agent of ``sim``, planned on copies of its true state."""

    def __init__(self, sim: HighwaySim, config: PlannerConfig = PlannerConfig()) -> None:
        self.sim = sim
        self.config = config
        self.limit_mps = sim.config.ego.cruise_max_kmh * KMH
        self.horizon_decisions = max(1, round(config.horizon_s / sim.decision_period_s))
        arenas, n = sim.num_arenas, sim.agents
        self.options = 1 + 2 * n  # stay; then agent j left, agent j right
        # The copies need no sensors: the planner reads their state (SimConfig wants one on:
        # the ego vector, the cheapest, which nothing reads).
        off: dict[str, Any] = {
            name: dataclasses.replace(typing.cast(Any, section), enabled=False)
            for name, section in sim.config.sensor_sections().items()
        }
        off["ego_vector"] = dataclasses.replace(sim.config.ego_vector, enabled=True)
        shadow_config = dataclasses.replace(sim.config, **off)
        self.shadow = HighwaySim(shadow_config, self.options * arenas, n)
        self.shadow._needs_reset[:] = False
        self._rng = np.random.default_rng(config.seed)

    def _greedy(self, sim: HighwaySim) -> np.ndarray:
        """(A, N) accelerate below the limit unless warned of a car ahead; else keep. Under
        Ho's speed steps the safety rule keeps the car behind the one ahead: no warning is
        heeded (the preset's reward has no warning term)."""
        st, n = sim.state, sim.agents
        below = st.speed_mps[:, :n] < self.limit_mps - 1e-3
        if sim.physics.speed_steps is None:
            warnings = st.warnings if sim.keeps_warnings else sim.warnings.compute(st)
            below &= ~warnings[..., DriverWarnings.FORWARD]
        return np.where(below, CRUISE_UP, KEEP).astype(np.int64)

    def _copy_state(self) -> None:
        """Every option's copy of every arena, with common random draws across options."""
        real, shadow = self.sim.state, self.shadow.state
        arenas = self.sim.num_arenas
        for field in dataclasses.fields(SimState):
            source = getattr(real, field.name)
            getattr(shadow, field.name)[:] = np.concatenate([source] * self.options)
        states = [
            np.random.default_rng(self._rng.integers(2**63)).bit_generator.state
            for _ in range(arenas)
        ]
        for option in range(self.options):
            for arena, state in enumerate(states):
                self.shadow.rngs[option * arenas + arena].bit_generator.state = state

    def act(self) -> np.ndarray:
        sim, shadow = self.sim, self.shadow
        arenas, n = sim.num_arenas, sim.agents
        greedy = self._greedy(sim)
        first = np.tile(greedy, (self.options, 1))  # (options * A, N)
        for agent in range(n):
            first[(1 + 2 * agent) * arenas : (2 + 2 * agent) * arenas, agent] = LANE_LEFT
            first[(2 + 2 * agent) * arenas : (3 + 2 * agent) * arenas, agent] = LANE_RIGHT
        self._copy_state()
        start = shadow.state.x_m[:, :n].copy()
        crashed = np.zeros((self.options * arenas, n), dtype=bool)
        changes = shadow.state.lane_changes[:, :n].copy()
        result = shadow.step(first)
        # A lane change that cannot start (no lane, one under way) is no option at all. (Told
        # by the changes started: with ego.applied_as_driven a started change braked by the
        # safety rule is applied as decelerate.)
        lateral = (first == LANE_LEFT) | (first == LANE_RIGHT)
        possible = ~lateral | (shadow.state.lane_changes[:, :n] > changes)
        crashed |= result.terminated
        for _ in range(self.horizon_decisions - 1):
            crashed |= shadow.step(self._greedy(shadow)).terminated
        value = shadow.state.x_m[:, :n] - start
        value += self.config.terminal_time_s * shadow.state.speed_mps[:, :n]
        travelled = np.where(crashed, -np.inf, value)
        travelled = np.where(possible, travelled, -np.inf)
        by_option = travelled.reshape(self.options, arenas, n)
        stay = by_option[0]
        actions = greedy.copy()
        for agent in range(n):
            left = by_option[1 + 2 * agent, :, agent]
            right = by_option[2 + 2 * agent, :, agent]
            bar = stay[:, agent] + self.config.better_by_m
            go_left = (left >= bar) & (left >= right)
            go_right = ~go_left & (right >= bar)
            actions[:, agent] = np.where(
                go_left, LANE_LEFT, np.where(go_right, LANE_RIGHT, actions[:, agent])
            )
        return actions
