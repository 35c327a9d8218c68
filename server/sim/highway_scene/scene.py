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
    ACTION_COUNT,
    AGENT_KIND,
    HIGHWAY_ENV_ACTION_NAMES,
    LANE_RIGHT,
)

from ..decision import StepResult
from ..state import SimState
from ..validation import ConfigError
from . import episode_kernels as ek
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
    p[k.P_CHECK_ALL] = float(scene.collisions == "all")
    p[k.P_AGENTS_IDM] = float(scene.ego_driver == "idm")
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

    spawner_count = 0  # the state's spawner clocks (Min et al.'s spawners): none here

    def __init__(self, config: SimConfig, agents: int, vehicles: int, tracker) -> None:
        self.scene = config.highway_scene
        self.lanes = config.road.lane_count
        self.lane_width = config.road.lane_width_m
        self.agents, self.vehicles = agents, vehicles
        self.tracker = tracker
        self.spacing_factor = math.exp(-5.0 / 40.0 * self.lanes)
        self.target_speeds = np.asarray(self.scene.target_speeds_mps, dtype=np.float64)
        # The order cars are placed in: each controlled car followed by its share of traffic.
        traffic = vehicles - agents
        order: list[int] = []
        slot = agents
        for agent in range(agents):
            share = traffic // agents + (1 if agent < traffic % agents else 0)
            order.append(agent)
            order.extend(range(slot, slot + share))
            slot += share
        self.order = np.asarray(order, dtype=np.int64)

    def reset_arenas(self, rngs: list[np.random.Generator]) -> SimState:
        """New episodes' states, one arena per generator, each drawn from its own
        (:func:`.episode_kernels.place_cars`, compiled)."""
        scene = self.scene
        fresh = SimState.empty(len(rngs), self.agents, self.vehicles)
        low, high = scene.idm_delta_range
        for row, rng in enumerate(rngs):
            ek.place_cars(
                rng, row, self.order, self.agents, self.lanes, self.lane_width,
                self.spacing_factor, scene.ego_initial_speed_mps, scene.ego_spacing,
                1.0 / scene.vehicles_density, scene.speed_limit_mps, self.target_speeds,
                scene.lane_change_delay_s, low, high, AGENT_KIND, fresh.x_m, fresh.y_m,
                fresh.speed_mps, fresh.desired_speed_mps, fresh.lane, fresh.target_lane,
                fresh.active, fresh.kind, fresh.speed_index, fresh.timer_s, fresh.idm_delta,
            )  # fmt: skip
        if scene.ego_driver == "idm":
            self.drive_by_idm(fresh, np.arange(len(rngs)), np.arange(self.agents))
        self.tracker.start(fresh, np.ones((len(rngs), self.vehicles), dtype=bool))
        return fresh

    def drive_by_idm(self, st: SimState, arenas: np.ndarray, slots: np.ndarray) -> None:
        """The agents' cars ``slots`` of ``arenas`` as ``IDMVehicle.create_from`` makes them
        (ego_driver idm): the class's IDM exponent, and the lane-change timer its constructor
        starts from the car's position (highway-env's y grows from the left lane)."""
        scene = self.scene
        rows, columns = np.ix_(arenas, slots)
        y_highway_env = (self.lanes - 1 - st.lane[rows, columns]) * self.lane_width
        st.timer_s[rows, columns] = (
            (st.x_m[rows, columns] + y_highway_env) * math.pi
        ) % scene.lane_change_delay_s
        st.idm_delta[rows, columns] = scene.ego_idm_delta

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
            if scene.ego_driver == "idm":
                self.drive_by_idm(st, np.array([arena]), np.array([slot]))
            self.tracker.start_agent(st, arena, int(slot))


class MetaActions:
    """``DiscreteMetaAction`` on the simulator's action numbers (keep is IDLE, cruise up
    FASTER, cruise down SLOWER): which can be taken now (``get_available_actions``: IDLE
    always, a lane change where there is a lane beyond the lane the car is in, FASTER and
    SLOWER where the car's speed index can move; ``highway_scene.action_mask_lane = "target"``
    reads the lane it is changing into instead, as this scene did before issue 68)."""

    names = HIGHWAY_ENV_ACTION_NAMES  # the actions as highway-env names them
    count = ACTION_COUNT

    def __init__(self, config: SimConfig, agents: int) -> None:
        self.lanes = config.road.lane_count
        self.top = len(config.highway_scene.target_speeds_mps) - 1
        self.agents = agents
        self.from_current_lane = config.highway_scene.action_mask_lane == "current"

    def check(self, actions: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        actions = np.asarray(actions)
        if actions.shape != shape:
            raise ValueError(f"expected actions of shape {shape}, got {actions.shape}")
        bad = (actions < 0) | (actions > LANE_RIGHT)
        if bad.any():
            raise ValueError(f"actions are 0..{LANE_RIGHT}, got {actions[bad].tolist()}")
        return actions.astype(np.int64)

    def mask(self, st: SimState) -> np.ndarray:
        return self._available(st.lane if self.from_current_lane else st.target_lane, st)

    def doable(self, st: SimState) -> np.ndarray:
        """What each car can do now, as the mask marks it: a lane change where there is a lane
        beyond the one it is changing into (``ControlledVehicle.act`` moves the target lane
        and clips it at the road's edge), FASTER and SLOWER where its speed index can move."""
        return self._available(st.target_lane, st)

    def _available(self, from_lane: np.ndarray, st: SimState) -> np.ndarray:
        mask = np.zeros(st.speed_index.shape + (LANE_RIGHT + 1,), dtype=np.int8)
        ek.available(from_lane, st.speed_index, self.lanes, self.top, mask)
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
        self.tracker, self.episodes = sim.tracker, sim.episodes
        self.actions = MetaActions(config, sim.agents)
        # The agents' cars drive themselves (ego_driver idm): the actions sent are not read.
        self.agents_idm = self.scene.ego_driver == "idm"
        scene = self.scene
        self.weights = np.array(
            [scene.collision_reward, scene.right_lane_reward, scene.high_speed_reward]
        )

    def advance(
        self,
        st: SimState,
        actions: np.ndarray,
        uniforms: np.ndarray | None,
        rows: np.ndarray | None = None,
    ) -> StepResult:
        """One decision of the arenas ``rows`` of ``st`` (None: all), ``actions`` theirs; the
        other arenas do not move. The result is the stepped arenas'."""
        n, arenas = self.agents, st.x_m.shape[0]
        stepping = np.ones(arenas, dtype=bool)
        if rows is not None:
            stepping[:] = False
            stepping[rows] = True
            every = np.zeros((arenas, n), dtype=np.int64)
            every[rows] = actions
            actions = every
        # What the car does with each action: one it cannot take does nothing (highway-env
        # clips the target lane or the speed index), as keep does. Read from the lane the car
        # is changing into, whichever lane the action mask reads.
        applied = np.empty_like(actions)
        ek.applied_actions(self.actions.doable(st), actions, applied)
        started = np.zeros(actions.shape, dtype=bool)
        driven = np.empty_like(actions)
        blocks = k.arena_blocks(arenas)
        if len(blocks) == 1:
            self._play(st, actions, started, stepping, driven, blocks[0])
        else:
            # The compiled decision lets go of the GIL: blocks of arenas on as many threads.
            pool = k.thread_pool(len(blocks) - 1)
            others = [
                pool.submit(self._play, st, actions, started, stepping, driven, b)
                for b in blocks[1:]
            ]
            self._play(st, actions, started, stepping, driven, blocks[0])
            for other in others:
                other.result()
        if self.agents_idm:
            applied = driven  # the meta-action each car's own decision stands for
        where = slice(None) if rows is None else rows
        st.frame[where] += self.frames
        st.decisions[where] += 1
        st.agent_decisions[where] += 1
        gained, undone, _passed = self.tracker.track(st, stepping)
        reward, terms = self.reward(st)
        crashed = st.crashed[:, :n] & st.active[:, :n]
        ended = crashed
        if self.scene.offroad_terminal:
            ended = ended | (terms["on_road"] == 0.0)
        if rows is not None:
            reward, crashed, ended = reward[rows], crashed[rows], ended[rows]
            applied = applied[rows]
            terms = {name: value[rows] for name, value in terms.items()}
            started, gained, undone = started[rows], gained[rows], undone[rows]
        truncated = self.episodes.close_decision(
            st, reward, started, crashed, gained - undone,
            np.zeros(crashed.shape, dtype=np.int64), rows=rows,
        )  # fmt: skip
        return StepResult(
            reward=reward,
            reward_terms=terms,
            terminated=ended,
            truncated=truncated & ~ended,
            action_applied=applied,
        )

    def _play(
        self,
        st: SimState,
        actions: np.ndarray,
        started: np.ndarray,
        stepping: np.ndarray,
        driven: np.ndarray,
        rows: slice,
    ) -> None:
        """:func:`.kernels.play_decision` on the arenas ``rows`` (views: written in place)."""
        arenas, cars = rows.stop - rows.start, st.x_m.shape[1]
        k.play_decision(
            st.x_m[rows], st.y_m[rows], st.speed_mps[rows], st.heading_rad[rows],
            st.lane[rows], st.target_lane[rows], st.desired_speed_mps[rows], st.timer_s[rows],
            st.idm_delta[rows], st.crashed[rows], st.impact_x_m[rows], st.impact_y_m[rows],
            st.has_impact[rows], st.active[rows], st.distance_m[rows], st.speed_index[rows],
            actions[rows], self.target_speeds, self.agents, self.lanes, self.frames, self.dt,
            self.parameters, started[rows], np.empty((arenas, cars)),
            np.empty((arenas, cars)), np.empty((arenas, self.lanes, cars), dtype=np.int64),
            np.empty((arenas, self.lanes), dtype=np.int64), stepping[rows], driven[rows],
        )  # fmt: skip

    def reward(self, st: SimState) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """highway-env's reward: the weighted terms, normalised to [0, 1], times on-road."""
        shape = st.speed_index.shape
        reward = np.empty(shape)
        terms = {name: np.empty(shape) for name in REWARD_TERMS}
        low, high = self.scene.reward_speed_range_mps
        ek.rewards(
            st.crashed, st.target_lane, st.lane, st.y_m, st.speed_mps, st.heading_rad,
            self.lanes, self.lane_width, low, high, self.weights, self.scene.normalize_reward,
            reward, terms["collision"], terms["right_lane"], terms["high_speed"],
            terms["on_road"],
        )  # fmt: skip
        return reward, terms
