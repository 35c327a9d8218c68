"""Episodes: their length, and each agent's bookkeeping of the papers' metrics.

Per agent and episode: decisions, distance, lane changes started, overtakes, collisions,
emergency brakes (Ho 2018, §6.2, "the speed difference to the car in front is at least 20 km/h
and a brake is applied", counted per decision: a decision in which some frame braked at least
``ego.emergency_decel_mps2`` while the car ahead was slower by at least
``ego.emergency_speed_diff_kmh``), the return, and the traffic cars on the road on average.
:meth:`EpisodeBook.metrics_table` reports them as
:data:`~overtake.protocol.vocabulary.METRIC_FIELDS`, with the average speed derived from
distance and time. An episode is truncated after ``episode.max_decisions``, or once the agent
has driven ``episode.max_distance_m``; it terminates on a collision (the caller's
``terminated``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import KEEP, METRIC_FIELDS, WATCH_METRICS

from .kernels import close_episodes, fill_metrics
from .units import KMH
from .validation import check, check_range

if TYPE_CHECKING:
    from .assist import EgoConfig
    from .state import SimState
    from .traffic.car_following import Following

# The per-agent accumulators an episode starts from zero.
EPISODE_COUNTERS = (
    "agent_decisions",
    "distance_m",
    "lane_changes",
    "overtakes",
    "collisions",
    "emergency_brakes",
    "lane_change_aborts",
    "episode_return",
    "traffic_cars_sum",
)


@dataclass(frozen=True, slots=True)
class EpisodeConfig:
    """Time: one decision spans ``frames_per_decision`` physics frames of ``physics_dt_s``."""

    max_decisions: int = 1000
    frames_per_decision: int = 4
    physics_dt_s: float = 0.1
    # An episode also ends (truncated) once the agent has driven this far (Min et al.'s code,
    # VehicleAgent.cs: 2,600 m); None: only the decision limit ends it.
    max_distance_m: float | None = None

    def __post_init__(self) -> None:
        check(
            isinstance(self.max_decisions, int) and self.max_decisions >= 1,
            "episode.max_decisions",
            self.max_decisions,
            "an integer >= 1",
        )
        check(
            isinstance(self.frames_per_decision, int) and 1 <= self.frames_per_decision <= 100,
            "episode.frames_per_decision",
            self.frames_per_decision,
            "an integer from 1 to 100",
        )
        # highway-fast-v0's frames are 0.2 s (5 Hz); the papers' 0.1 s or less.
        check_range("episode.physics_dt_s", self.physics_dt_s, 0.0, 0.2, low_open=True)
        if self.max_distance_m is not None:
            check_range("episode.max_distance_m", self.max_distance_m, 0.0, 1e7, low_open=True)

    @property
    def decision_period_s(self) -> float:
        """Simulated seconds per decision."""
        return self.frames_per_decision * self.physics_dt_s


class EpisodeBook:
    """Each agent's episode so far, kept in the state's per-agent arrays."""

    def __init__(self, episode: EpisodeConfig, ego: EgoConfig, agents: int) -> None:
        self.max_decisions = episode.max_decisions
        self.max_distance_m = episode.max_distance_m
        self.decision_period_s = episode.decision_period_s
        self.brake_decel_mps2 = ego.emergency_decel_mps2
        self.brake_speed_diff_kmh = ego.emergency_speed_diff_kmh
        self.counts_forced_brakes = ego.emergency_brake_count == "forced"
        self.agents = agents
        # The columns of the metrics table: the papers' metrics, and the watch's where it runs.
        self.fields = METRIC_FIELDS + (WATCH_METRICS if ego.lane_change_watch else ())

    def restart(self, st: SimState, arena: int, slot: int) -> None:
        """Start an agent's episode counters from zero."""
        for name in EPISODE_COUNTERS:
            getattr(st, name)[arena, slot] = 0
        st.recent_actions[arena, slot] = KEEP

    def note_emergency_brakes(
        self, st: SimState, following: Following, brakes: np.ndarray, forced: np.ndarray | None
    ) -> None:
        """After a frame: count in ``brakes`` (A, N) the agents' emergency brakes as
        ``ego.emergency_brake_count`` says: "forced", the frames in which the safety rule made
        the car take a slower car's speed (``forced``, from the physics); "deliberate", a mark
        (1) for the agents that braked (at least ``ego.emergency_decel_mps2``) with a car ahead
        slower by at least ``ego.emergency_speed_diff_kmh``, a decision with such a frame being
        one emergency brake."""
        if self.counts_forced_brakes:
            assert forced is not None, "forced brakes are counted from the physics' safety rule"
            brakes += forced
            return
        n = self.agents
        braking = st.accel_mps2[:, :n] <= -self.brake_decel_mps2
        if braking.any():
            brakes |= (
                braking
                & following.has_leader[:, :n]
                & (following.closing_mps[:, :n] >= self.brake_speed_diff_kmh * KMH)
            )

    def close_decision(
        self,
        st: SimState,
        reward: np.ndarray,
        lane_changes: np.ndarray,
        collided: np.ndarray,
        overtakes: np.ndarray,
        emergency_brakes: np.ndarray,
        rows: np.ndarray | None = None,
    ) -> np.ndarray:
        """Add one decision's events (A, N) to the episodes; returns which reached their
        decision limit (truncated). With ``rows``, the events are those arenas' (rows of the
        state), the others untouched."""
        if rows is None:
            rows = np.arange(st.x_m.shape[0])
        truncated = np.empty(reward.shape, dtype=bool)
        close_episodes(
            rows, reward, lane_changes, collided, overtakes, emergency_brakes, st.active,
            st.agent_decisions, st.distance_m, self.max_decisions,
            np.inf if self.max_distance_m is None else self.max_distance_m, st.episode_return,
            st.lane_changes, st.collisions, st.overtakes, st.emergency_brakes,
            st.traffic_cars_sum, truncated,
        )  # fmt: skip
        return truncated

    def metrics_table(self, st: SimState) -> np.ndarray:
        """(A, N, len(fields)) float64: each agent's episode so far, columns :attr:`fields`
        (every round: :func:`fill_metrics`, compiled)."""
        table = np.empty(st.distance_m.shape + (len(self.fields),))
        fill_metrics(
            st.agent_decisions, st.distance_m, st.lane_changes, st.overtakes, st.collisions,
            st.emergency_brakes, st.episode_return, st.traffic_cars_sum, st.lane_change_aborts,
            self.decision_period_s, KMH, len(self.fields) > len(METRIC_FIELDS), table,
        )  # fmt: skip
        return table


# The columns fill_metrics writes, in its order.
assert METRIC_FIELDS + WATCH_METRICS == (
    "avg_speed_kmh", "lane_changes", "overtakes", "collisions", "emergency_brakes",
    "distance_m", "return", "decisions", "traffic_cars", "lane_change_aborts",
)  # fmt: skip
