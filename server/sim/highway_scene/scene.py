"""highway-env's scene as the simulator's parts: where the cars start (:class:`ScenePlacement`,
``Vehicle.create_random``), what the actions do and when they can be taken
(:class:`MetaActions`, ``DiscreteMetaAction``), and a decision (:class:`SceneDecision`: the
compiled frames of :mod:`.kernels`, then highway-env's reward and the episode's end).

A traffic car keeps its kind (``kind``: the first behaviour) for rendering; what it does is
highway-env's IDM and MOBIL whatever the traffic section says.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import (
    AGENT_KIND,
    CRUISE_DOWN,
    CRUISE_UP,
    KEEP,
    LANE_LEFT,
    LANE_RIGHT,
)

from ..decision import StepResult
from ..state import SimState
from ..validation import ConfigError
from . import kernels as k

if TYPE_CHECKING:
    from ..config import SimConfig
    from ..core import HighwaySim

# The reward's terms, reported each step (envs/highway_env.py, _rewards).
REWARD_TERMS = ("collision", "right_lane", "high_speed", "on_road")


def kernel_parameters(config: SimConfig) -> np.ndarray:
    """The parameters :func:`.kernels.play_decision` reads (its P_* order)."""
    scene, ego = config.highway_scene, config.ego
    p = np.zeros(k.P_COUNT)
    p[k.P_LANE_WIDTH] = config.road.lane_width_m
    p[k.P_SPEED_LIMIT] = scene.speed_limit_mps
    p[k.P_MAX_SPEED] = scene.max_speed_mps
    p[k.P_LENGTH] = ego.length_m
    p[k.P_WIDTH] = ego.width_m
    p[k.P_KP_A] = 1.0 / scene.tau_acceleration_s
    p[k.P_KP_HEADING] = 1.0 / scene.tau_heading_s
    p[k.P_KP_LATERAL] = 1.0 / scene.tau_lateral_s
    p[k.P_TAU_PURSUIT] = 0.5 * scene.tau_heading_s
    p[k.P_MAX_STEERING] = scene.max_steering_rad
    p[k.P_ACC_MAX] = scene.idm_max_accel_mps2
    p[k.P_COMFORT_ACC] = scene.idm_comfort_accel_mps2
    p[k.P_COMFORT_DEC] = scene.idm_comfort_decel_mps2
    p[k.P_DISTANCE_WANTED] = scene.idm_distance_wanted_m
    p[k.P_TIME_WANTED] = scene.idm_time_wanted_s
    p[k.P_POLITENESS] = scene.mobil_politeness
    p[k.P_MIN_GAIN] = scene.mobil_min_accel_gain_mps2
    p[k.P_MAX_BRAKING] = scene.mobil_max_braking_imposed_mps2
    p[k.P_CHANGE_DELAY] = scene.lane_change_delay_s
    return p


def check_scene(config: SimConfig) -> None:
    """What the scene needs of the other sections: one size for every car (highway-env's
    Vehicle.LENGTH and WIDTH)."""
    ego, traffic = config.ego, config.traffic
    if (ego.length_m, ego.width_m) != (traffic.vehicle_length_m, traffic.vehicle_width_m):
        raise ConfigError(
            "highway_scene.enabled = True is not allowed with cars of two sizes: expected "
            f"ego.length_m, ego.width_m equal to traffic.vehicle_length_m, vehicle_width_m, got "
            f"{ego.length_m} x {ego.width_m} and {traffic.vehicle_length_m} x "
            f"{traffic.vehicle_width_m}"
        )


def speed_to_index(speeds: tuple[float, ...], speed: float) -> int:
    """MDPVehicle.speed_to_index (controller.py): the nearest of evenly spaced speeds."""
    top = len(speeds) - 1
    ratio = (speed - speeds[0]) / (speeds[-1] - speeds[0])
    return int(np.clip(np.round(ratio * top), 0, top))


class ScenePlacement:
    """highway-env's ``Vehicle.create_random``, car after car: the controlled cars first, each
    followed by its share of the traffic; every car in a random lane, ahead of the foremost
    so far by a spacing that grows with its speed and shrinks with the lanes
    (``(12 + speed) * exp(-5/40 * lanes)``, times 0.9-1.1 at random, over the density)."""

    def __init__(self, config: SimConfig, agents: int, vehicles: int, tracker) -> None:
        self.scene = config.highway_scene
        self.lanes = config.road.lane_count
        self.lane_width = config.road.lane_width_m
        self.agents, self.vehicles = agents, vehicles
        self.tracker = tracker
        self.spacing_factor = math.exp(-5.0 / 40.0 * self.lanes)

    def reset_arena(self, rng: np.random.Generator) -> SimState:
        """A new episode's state of one arena, drawn from ``rng``."""
        scene, n = self.scene, self.agents
        fresh = SimState.empty(1, n, self.vehicles)
        traffic = self.vehicles - n
        shares = [traffic // n + (1 if i < traffic % n else 0) for i in range(n)]
        order: list[int] = []
        slot = n
        for agent, share in enumerate(shares):
            order.append(agent)
            order.extend(range(slot, slot + share))
            slot += share
        foremost: float | None = None
        limit = scene.speed_limit_mps
        for column in order:
            is_agent = column < n
            if is_agent:
                speed, spacing = scene.ego_initial_speed_mps, scene.ego_spacing
            else:
                speed, spacing = rng.uniform(0.7 * limit, 0.8 * limit), 1.0 / scene.vehicles_density
            lane = self.lanes - 1 - int(rng.integers(self.lanes))
            offset = spacing * (12.0 + speed) * self.spacing_factor
            x = 3.0 * offset if foremost is None else foremost
            x += offset * rng.uniform(0.9, 1.1)
            foremost = x if foremost is None else max(foremost, x)
            self._put(fresh, column, x, lane, speed)
            if not is_agent:
                fresh.idm_delta[0, column] = rng.uniform(*scene.idm_delta_range)
        self.tracker.start(fresh, np.ones((1, self.vehicles), dtype=bool))
        return fresh

    def _put(self, st: SimState, column: int, x: float, lane: int, speed: float) -> None:
        n = self.agents
        st.x_m[0, column] = x
        st.y_m[0, column] = (lane + 0.5) * self.lane_width
        st.lane[0, column] = st.target_lane[0, column] = lane
        st.speed_mps[0, column] = speed
        st.desired_speed_mps[0, column] = speed
        st.active[0, column] = True
        if column < n:
            st.kind[0, column] = AGENT_KIND
            index = speed_to_index(self.scene.target_speeds_mps, speed)
            st.speed_index[0, column] = index
            st.desired_speed_mps[0, column] = self.scene.target_speeds_mps[index]
        else:
            # IDMVehicle's lane-change timer starts from its position (behavior.py), in
            # highway-env's coordinates, whose y grows from the left lane.
            y_highway_env = (self.lanes - 1 - lane) * self.lane_width
            st.timer_s[0, column] = ((x + y_highway_env) * math.pi) % self.scene.lane_change_delay_s

    def place_agents(
        self, st: SimState, arena: int, slots: np.ndarray, rng: np.random.Generator
    ) -> None:
        """Put agents' cars back on a shared road while it goes on (chosen here: highway-env
        has no such thing): each behind the hindmost car by its spacing, in a random lane, at
        the initial speed."""
        scene = self.scene
        for slot in np.asarray(slots, dtype=np.int64):
            st.active[arena, slot] = False
            present = st.x_m[arena, st.active[arena]]
            hindmost = present.min() if present.size else st.x_m[arena, slot]
            speed = scene.ego_initial_speed_mps
            offset = scene.ego_spacing * (12.0 + speed) * self.spacing_factor
            lane = int(rng.integers(self.lanes))
            st.x_m[arena, slot] = hindmost - offset
            st.y_m[arena, slot] = (lane + 0.5) * self.lane_width
            st.lane[arena, slot] = st.target_lane[arena, slot] = lane
            st.speed_mps[arena, slot] = speed
            st.heading_rad[arena, slot] = 0.0
            st.crashed[arena, slot] = st.has_impact[arena, slot] = False
            index = speed_to_index(scene.target_speeds_mps, speed)
            st.speed_index[arena, slot] = index
            st.desired_speed_mps[arena, slot] = scene.target_speeds_mps[index]
            st.active[arena, slot] = True
            self.tracker.start_agent(st, arena, int(slot))


class MetaActions:
    """``DiscreteMetaAction`` on the simulator's action numbers (keep is IDLE, cruise up
    FASTER, cruise down SLOWER): which can be taken now (``get_available_actions``: IDLE
    always, a lane change where there is a lane beyond the target lane, FASTER and SLOWER
    where the car's speed index can move)."""

    def __init__(self, config: SimConfig, agents: int) -> None:
        self.lanes = config.road.lane_count
        self.top = len(config.highway_scene.target_speeds_mps) - 1
        self.agents = agents

    def check(self, actions: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        actions = np.asarray(actions)
        if actions.shape != shape:
            raise ValueError(f"expected actions of shape {shape}, got {actions.shape}")
        bad = (actions < 0) | (actions > LANE_RIGHT)
        if bad.any():
            raise ValueError(f"actions are 0..{LANE_RIGHT}, got {actions[bad].tolist()}")
        return actions.astype(np.int64)

    def mask(self, st: SimState) -> np.ndarray:
        n = self.agents
        target, index = st.target_lane[:, :n], st.speed_index[:, :n]
        mask = np.zeros(target.shape + (LANE_RIGHT + 1,), dtype=np.int8)
        mask[..., KEEP] = 1
        mask[..., LANE_LEFT] = target < self.lanes - 1
        mask[..., LANE_RIGHT] = target > 0
        mask[..., CRUISE_UP] = index < self.top
        mask[..., CRUISE_DOWN] = index > 0
        return mask


class SceneDecision:
    """One decision of highway-env's scene: the compiled frames, then the reward
    (envs/highway_env.py, _rewards and _reward), the episode's end (a crash of the controlled
    car terminates, offroad too where asked) and the metrics' bookkeeping."""

    uses_uniforms = False  # nothing random after the placement

    def __init__(self, sim: HighwaySim) -> None:
        config = sim.config
        self.scene = config.highway_scene
        self.agents, self.frames, self.dt = sim.agents, sim.frames, sim.dt
        self.lanes = config.road.lane_count
        self.lane_width = config.road.lane_width_m
        self.parameters = kernel_parameters(config)
        self.target_speeds = np.asarray(self.scene.target_speeds_mps, dtype=np.float64)
        self.check_all = self.scene.collisions == "all"
        self.tracker, self.episodes = sim.tracker, sim.episodes
        self.actions = MetaActions(config, sim.agents)

    def advance(self, st: SimState, actions: np.ndarray, uniforms: np.ndarray | None) -> StepResult:
        n = self.agents
        # What the car does with each action: one the mask rules out does nothing (highway-env
        # clips the lane or the speed index), as keep does.
        allowed = np.take_along_axis(self.actions.mask(st), actions[..., None], axis=-1)[..., 0]
        applied = np.where(allowed == 1, actions, KEEP)
        started = np.zeros(actions.shape, dtype=bool)
        scratch = np.zeros(st.x_m.shape)
        k.play_decision(
            st.x_m, st.y_m, st.speed_mps, st.heading_rad, st.lane, st.target_lane,
            st.desired_speed_mps, st.timer_s, st.idm_delta, st.crashed, st.impact_x_m,
            st.impact_y_m, st.has_impact, st.active, st.distance_m, st.speed_index, actions,
            self.target_speeds, n, self.lanes, self.frames, self.dt, self.check_all,
            self.parameters, started, scratch, np.zeros(st.x_m.shape),
        )  # fmt: skip
        st.frame += self.frames
        st.decisions += 1
        st.agent_decisions += 1
        gained, undone, _passed = self.tracker.track(st)
        reward, terms = self.reward(st)
        crashed = st.crashed[:, :n] & st.active[:, :n]
        ended = crashed
        if self.scene.offroad_terminal:
            ended = ended | (terms["on_road"] == 0.0)
        truncated = self.episodes.close_decision(
            st, reward, started, crashed, gained - undone, np.zeros(crashed.shape, dtype=np.int64)
        )
        return StepResult(
            reward=reward,
            reward_terms=terms,
            terminated=ended,
            truncated=truncated & ~ended,
            action_applied=applied,
        )

    def reward(self, st: SimState) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """highway-env's reward: the weighted terms, normalised to [0, 1], times on-road."""
        scene, n = self.scene, self.agents
        crashed = st.crashed[:, :n].astype(np.float64)
        # highway-env's lane index of the target lane, over the last lane: 1 on the right.
        right = (self.lanes - 1 - st.target_lane[:, :n]) / max(self.lanes - 1, 1)
        forward = st.speed_mps[:, :n] * np.cos(st.heading_rad[:, :n])
        low, high = scene.reward_speed_range_mps
        fast = np.clip((forward - low) / (high - low), 0.0, 1.0)
        centre = (st.lane[:, :n] + 0.5) * self.lane_width
        on_road = (np.abs(st.y_m[:, :n] - centre) <= self.lane_width / 2).astype(np.float64)
        reward = (
            scene.collision_reward * crashed
            + scene.right_lane_reward * right
            + scene.high_speed_reward * fast
        )
        if scene.normalize_reward:
            best = scene.high_speed_reward + scene.right_lane_reward
            reward = (reward - scene.collision_reward) / (best - scene.collision_reward)
        reward = reward * on_road
        terms = {"collision": crashed, "right_lane": right, "high_speed": fast, "on_road": on_road}
        return reward, terms
