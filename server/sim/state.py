"""The one state every part of the simulation reads and writes: structure of arrays.

Rows are arenas; per-vehicle arrays have one column per vehicle slot, the agents' cars first
(columns ``0 .. agents-1``), then traffic. Per-agent arrays are (arenas, agents), and the
overtake bookkeeping is (arenas, agents, vehicles). Nothing here is a per-vehicle object: every
part updates whole arrays at once.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

# The actions each agent's recent past holds (Ho's action stack: the last four).
ACTION_HISTORY = 4
# Fields added since snapshots were first kept, and the issue that added each: a snapshot of
# older code has none of them, and its simulator used none (:mod:`.snapshot` restores them
# as :meth:`SimState.empty` makes them).
ADDED_FIELDS = {"spawner_wait_s": 68}


@dataclass
class SimState:
    """Everything that evolves; arrays are (arenas, ...). Columns 0..agents-1 are agents."""

    x_m: np.ndarray  # (A, V) float64, position along the road
    y_m: np.ndarray  # (A, V) lateral position, 0 at the right road edge
    speed_mps: np.ndarray  # (A, V)
    desired_speed_mps: np.ndarray  # (A, V) traffic's own; agents' cruise target
    own_speed_mps: np.ndarray  # (A, V) traffic's draw from its behaviour's range, at entry
    accel_mps2: np.ndarray  # (A, V) last frame's acceleration
    lane: np.ndarray  # (A, V) int64 lane (the origin lane during a change)
    target_lane: np.ndarray  # (A, V) int64 == lane unless changing
    change_progress: np.ndarray  # (A, V) 0..1 through a lane change
    active: np.ndarray  # (A, V) bool; inactive traffic slots wait to spawn
    kind: np.ndarray  # (A, V) int64: behaviour index, AGENT_KIND for agents
    frame: np.ndarray  # (A,) int64 physics frames since reset
    decisions: np.ndarray  # (A,) int64 decisions since reset
    # Per agent (A, N) and per agent and vehicle (A, N, V):
    agent_decisions: np.ndarray  # (A, N) decisions in the agent's current episode
    ahead: np.ndarray  # (A, N, V) bool: vehicle was ahead of the agent last frame
    credited: np.ndarray  # (A, N, V) bool: the agent's overtake of it was counted
    distance_m: np.ndarray  # (A, N) episode accumulators
    lane_changes: np.ndarray
    overtakes: np.ndarray
    collisions: np.ndarray
    emergency_brakes: np.ndarray
    lane_change_aborts: np.ndarray  # changes turned back (ego.lane_change_watch)
    episode_return: np.ndarray
    traffic_cars_sum: np.ndarray  # (A, N) traffic cars on the road, summed over decisions
    # (A, N, 3) bool: the left, right and forward warnings each agent was shown with its last
    # observation (:class:`~.assist.DriverWarnings`); kept by the simulation only where the
    # reward needs them (all False otherwise).
    warnings: np.ndarray
    # (A, N, ACTION_HISTORY) int64: each agent's last actions applied, oldest first (keep, 0,
    # before its episode's first decisions); kept only where a sensor or the reward reads them.
    recent_actions: np.ndarray
    # highway-env's scene (highway_scene.enabled; zeros otherwise): each car's heading
    # (radians, left positive), its lane-change timer (s), its IDM exponent, whether it
    # crashed, the push a predicted collision gives it at its next step (m, and whether there
    # is one), and each agent's index among the target speeds.
    heading_rad: np.ndarray  # (A, V)
    timer_s: np.ndarray  # (A, V)
    idm_delta: np.ndarray  # (A, V)
    crashed: np.ndarray  # (A, V) bool
    impact_x_m: np.ndarray  # (A, V)
    impact_y_m: np.ndarray  # (A, V)
    has_impact: np.ndarray  # (A, V) bool
    speed_index: np.ndarray  # (A, N) int64
    # Min et al.'s spawners (traffic.entry = "spawners"; (A, 0) otherwise): the seconds until
    # each spawner's next try.
    spawner_wait_s: np.ndarray  # (A, S) float64

    @classmethod
    def empty(cls, arenas: int, agents: int, vehicles: int, spawners: int = 0) -> SimState:
        """All zeros: no vehicle on the road yet."""
        a, n, v = arenas, agents, vehicles
        return cls(
            x_m=_f64(a, v),
            y_m=_f64(a, v),
            speed_mps=_f64(a, v),
            desired_speed_mps=_f64(a, v),
            own_speed_mps=_f64(a, v),
            accel_mps2=_f64(a, v),
            lane=_i64(a, v),
            target_lane=_i64(a, v),
            change_progress=_f64(a, v),
            active=_bool(a, v),
            kind=_i64(a, v),
            frame=_i64(a),
            decisions=_i64(a),
            agent_decisions=_i64(a, n),
            ahead=_bool(a, n, v),
            credited=_bool(a, n, v),
            distance_m=_f64(a, n),
            lane_changes=_i64(a, n),
            overtakes=_i64(a, n),
            collisions=_i64(a, n),
            emergency_brakes=_i64(a, n),
            lane_change_aborts=_i64(a, n),
            episode_return=_f64(a, n),
            traffic_cars_sum=_f64(a, n),
            warnings=_bool(a, n, 3),
            recent_actions=_i64(a, n, ACTION_HISTORY),
            heading_rad=_f64(a, v),
            timer_s=_f64(a, v),
            idm_delta=_f64(a, v),
            crashed=_bool(a, v),
            impact_x_m=_f64(a, v),
            impact_y_m=_f64(a, v),
            has_impact=_bool(a, v),
            speed_index=_i64(a, n),
            spawner_wait_s=_f64(a, spawners),
        )

    @classmethod
    def stack(cls, states: list[SimState]) -> SimState:
        """The arenas of ``states``, one after the other."""
        return cls(
            **{
                f.name: np.concatenate([getattr(s, f.name) for s in states])
                for f in dataclasses.fields(cls)
            }
        )

    def select(self, rows: np.ndarray) -> SimState:
        """A copy of some arenas' rows."""
        return SimState(**{f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)})

    def assign(self, rows: np.ndarray, other: SimState) -> None:
        """Write ``other`` (as many arenas as ``rows``) back into those rows."""
        for f in dataclasses.fields(self):
            getattr(self, f.name)[rows] = getattr(other, f.name)


def _f64(*shape: int) -> np.ndarray:
    return np.zeros(shape, dtype=np.float64)


def _i64(*shape: int) -> np.ndarray:
    return np.zeros(shape, dtype=np.int64)


def _bool(*shape: int) -> np.ndarray:
    return np.zeros(shape, dtype=bool)
