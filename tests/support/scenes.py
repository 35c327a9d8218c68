"""Scripted scenes written straight into a simulation's state arrays: one agent and exactly
the traffic a test places, which keeps to its lane and speed unless told otherwise (the
simulation core's tests, the papers' and the drivers')."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND, BEHAVIOUR_NAMES
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.traffic.config import NEVER_MPS2
from overtake.server.sim.units import KMH

LANE_WIDTH = 3.5
HALF_LENGTH = 2.25  # 4.5 m cars and ego
HALF_WIDTH = 0.9  # 1.8 m cars and ego
STEADY, ROAD_MAX, LANE_CHANGER = range(3)

# Scripted traffic keeps to its lane and its speed: MOBIL never finds a change worth it,
# nobody picks a new desired speed or walks it, and nobody holds a speed it was slowed to, so
# a scene only moves the way the test says.
CALM_TRAFFIC: dict[str, Any] = {}
for _name in BEHAVIOUR_NAMES:
    CALM_TRAFFIC[f"traffic.{_name}.lane_change_threshold_mps2"] = NEVER_MPS2
    CALM_TRAFFIC[f"traffic.{_name}.politeness"] = 0.0
    CALM_TRAFFIC[f"traffic.{_name}.speed_change_rate_per_s"] = 0.0
    CALM_TRAFFIC[f"traffic.{_name}.random_lane_change_rate_per_s"] = 0.0
    CALM_TRAFFIC[f"traffic.{_name}.speed_steps_per_s"] = 0.0
    CALM_TRAFFIC[f"traffic.{_name}.keeps_current_speed"] = False


@dataclass(frozen=True)
class Car:
    """A traffic car placed relative to the ego: ``dx`` metres ahead (centre to centre)."""

    dx: float
    lane: int
    speed_kmh: float
    kind: int = ROAD_MAX
    desired_kmh: float | None = None


def lane_centre(lane: float) -> float:
    return (lane + 0.5) * LANE_WIDTH


def scripted_sim(
    cars: list[Car] | tuple[Car, ...] = (),
    *,
    ego_lane: int = 2,
    ego_speed_kmh: float = 60.0,
    cruise_kmh: float | None = None,
    overrides: dict[str, Any] | None = None,
    calm: bool = True,
    preset: str = "min2018",
    ego_fields: tuple[str, ...] = (),
) -> HighwaySim:
    """One arena, one agent at x = 0 in ``ego_lane``, and exactly ``cars`` as traffic;
    ``ego_fields``: the ego vector's, as a trainer asks for them (none: the preset's)."""
    all_overrides: dict[str, Any] = dict(CALM_TRAFFIC) if calm else {}
    all_overrides["traffic.vehicle_count"] = len(cars)
    all_overrides.update(overrides or {})
    config = make_config(preset, overrides=all_overrides).reading_ego_fields(ego_fields)
    sim = HighwaySim(config, num_arenas=1)
    sim.reset(seeds=[0])
    st = sim.state
    cruise = ego_speed_kmh if cruise_kmh is None else cruise_kmh
    place(
        sim, 0, x=0.0, lane=ego_lane, speed_kmh=ego_speed_kmh, desired_kmh=cruise, kind=AGENT_KIND
    )
    for i, car in enumerate(cars):
        place(
            sim,
            1 + i,
            x=car.dx,
            lane=car.lane,
            speed_kmh=car.speed_kmh,
            desired_kmh=car.speed_kmh if car.desired_kmh is None else car.desired_kmh,
            kind=car.kind,
        )
    # Min et al.'s spawners (min2018's traffic) bring no car of their own into the scene.
    st.spawner_wait_s[:] = np.inf
    st.frame[:] = 0
    st.decisions[:] = 1  # not a respawn-retry decision (there are no empty slots anyway)
    st.agent_decisions[:] = 0
    retrack(sim)
    return sim


def place(
    sim: HighwaySim,
    column: int,
    *,
    x: float,
    lane: int,
    speed_kmh: float,
    desired_kmh: float | None = None,
    kind: int | None = None,
    arena: int = 0,
) -> None:
    """Put vehicle ``column`` of ``arena`` centred in ``lane`` at ``x``, not changing lanes."""
    st = sim.state
    st.x_m[arena, column] = x
    st.lane[arena, column] = lane
    st.target_lane[arena, column] = lane
    st.change_progress[arena, column] = 0.0
    st.y_m[arena, column] = lane_centre(lane)
    st.speed_mps[arena, column] = speed_kmh * KMH
    st.desired_speed_mps[arena, column] = (speed_kmh if desired_kmh is None else desired_kmh) * KMH
    st.own_speed_mps[arena, column] = st.desired_speed_mps[arena, column]
    st.accel_mps2[arena, column] = 0.0
    st.active[arena, column] = True
    if kind is not None:
        st.kind[arena, column] = kind
    sim.state_written([arena])


def retrack(sim: HighwaySim) -> None:
    """Restart overtake bookkeeping after positions were written by hand."""
    st, n = sim.state, sim.agents
    st.ahead[:] = st.x_m[:, None, :] > st.x_m[:, :n, None]
    st.credited[:] = False


def keep(sim: HighwaySim, action: int = 0):
    """One decision with the same action for every agent of every arena."""
    return sim.step(np.full((sim.num_arenas, sim.agents), action, dtype=np.int64))


def lidar_of(sim: HighwaySim) -> np.ndarray:
    return sim.observe()["lidar"][0, 0]


def camera_of(sim: HighwaySim) -> np.ndarray:
    return sim.observe()["camera"][0, 0]
