"""The highway simulation: many independent arenas advanced together by vectorised numpy.

State is structure-of-arrays, one row per arena and one column per vehicle slot: columns
``0 .. agents-1`` are the controlled cars (agents), the rest are traffic. Each arena owns one
``np.random.Generator``; every random number an arena uses per decision is drawn from it in one
fixed-size block, so an arena's episode depends only on its seed and actions, bit for bit,
whatever other arenas share the batch.

One :meth:`HighwaySim.step` is one decision: the agents' actions are applied, then
``frames_per_decision`` physics frames run (IDM car-following with adaptive cruise and
emergency braking for agents, MOBIL lane changes for traffic, minimum-jerk lateral moves), then
traffic that fell out of range is recycled around the agents, then sensors and rewards.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from overtake.protocol.messages import ACTION_COUNT, ACTION_NAMES

from .camera import Camera
from .config import BEHAVIOURS, SimConfig
from .lidar import Lidar
from .traffic import (NO_GAP_M, LaneIndex, LaneSorter, idm_accel, idm_desired_gap, leaders, min_jerk,
                      min_jerk_rate, neighbours_at)

KMH = 1.0 / 3.6  # m/s per km/h

# Min et al.'s five DAS-level actions (the wire contract names them, in this order).
KEEP, CRUISE_UP, CRUISE_DOWN, LANE_LEFT, LANE_RIGHT = range(ACTION_COUNT)

# The ego vector: the agent's own state, as Min et al.'s code adds scalars to its LIDAR rays.
EGO_FIELDS: tuple[str, ...] = ("speed_mps", "cruise_target_mps", "lane_index", "lane_count",
                               "lane_change_progress", "lane_change_direction")
REWARD_TERMS: tuple[str, ...] = ("speed", "collision", "lane_change", "overtake", "passed")
METRIC_FIELDS: tuple[str, ...] = ("avg_speed_kmh", "lane_changes", "overtakes", "collisions",
                                  "emergency_brakes", "distance_m", "return", "decisions")

AGENT_KIND = len(BEHAVIOURS)       # kind index of agents in the per-kind parameter tables
RESPAWN_RETRY_DECISIONS = 5       # an empty traffic slot looks for a free spot this often
SPAWN_CANDIDATES = 5               # positions tried per traffic (re)spawn
SPAWN_SEPARATION_M = 25.0          # spawns of one decision in one lane keep this far apart
# Per-vehicle uniforms per decision: side, anchor agent, candidate lanes and offsets,
# behaviour, desired speed, speed-change event and value.
_U_SIDE, _U_ANCHOR = 0, 1
_U_LANE = 2
_U_OFFSET = _U_LANE + SPAWN_CANDIDATES
_U_BEHAVIOUR = _U_OFFSET + SPAWN_CANDIDATES
_U_SPEED, _U_CHANGE, _U_NEW_SPEED = _U_BEHAVIOUR + 1, _U_BEHAVIOUR + 2, _U_BEHAVIOUR + 3
UNIFORMS_PER_VEHICLE = _U_NEW_SPEED + 1


@dataclass
class SimState:
    """Everything that evolves; arrays are (arenas, ...). Columns 0..agents-1 are agents."""

    x_m: np.ndarray                 # (A, V) float64, position along the road
    y_m: np.ndarray                 # (A, V) lateral position, 0 at the right road edge
    speed_mps: np.ndarray           # (A, V)
    desired_speed_mps: np.ndarray   # (A, V) traffic's own; agents' cruise target
    accel_mps2: np.ndarray          # (A, V) last frame's acceleration
    lane: np.ndarray                # (A, V) int64 lane (the origin lane during a change)
    target_lane: np.ndarray         # (A, V) int64 == lane unless changing
    change_progress: np.ndarray     # (A, V) 0..1 through a lane change
    active: np.ndarray              # (A, V) bool; inactive traffic slots wait to spawn
    kind: np.ndarray                # (A, V) int64: behaviour index, AGENT_KIND for agents
    frame: np.ndarray               # (A,) int64 physics frames since reset
    decisions: np.ndarray           # (A,) int64 decisions since reset
    # Per agent (A, N) and per agent and vehicle (A, N, V):
    agent_decisions: np.ndarray     # (A, N) decisions in the agent's current episode
    ahead: np.ndarray               # (A, N, V) bool: vehicle was ahead of the agent last frame
    credited: np.ndarray            # (A, N, V) bool: the agent's overtake of it was counted
    braking: np.ndarray             # (A, N) bool: emergency braking last frame
    distance_m: np.ndarray          # (A, N) episode accumulators
    lane_changes: np.ndarray
    overtakes: np.ndarray
    collisions: np.ndarray
    emergency_brakes: np.ndarray
    episode_return: np.ndarray

    def select(self, rows: np.ndarray) -> "SimState":
        return SimState(**{f.name: getattr(self, f.name)[rows] for f in dataclasses.fields(self)})

    def assign(self, rows: np.ndarray, other: "SimState") -> None:
        for f in dataclasses.fields(self):
            getattr(self, f.name)[rows] = getattr(other, f.name)


@dataclass(frozen=True, slots=True)
class _VehicleParams:
    """Per-vehicle (A, V) parameters of one decision, gathered from the per-kind tables."""

    headway: np.ndarray
    min_gap: np.ndarray
    max_accel: np.ndarray
    two_sqrt_ab: np.ndarray
    half_length: np.ndarray
    half_width: np.ndarray
    change_rate: np.ndarray   # lane-change progress per frame
    is_traffic: np.ndarray


@dataclass(frozen=True)
class StepResult:
    """What one decision produced, per arena and agent: (A, N) unless noted."""

    reward: np.ndarray                   # float64
    reward_terms: dict[str, np.ndarray]  # name -> float64
    terminated: np.ndarray               # bool: collided
    truncated: np.ndarray                # bool: the episode reached its decision limit
    action_applied: np.ndarray           # int64: the action actually taken (masked -> keep)


class HighwaySim:
    """``num_arenas`` independent highways with ``agents_per_arena`` controlled cars each."""

    def __init__(self, config: SimConfig, num_arenas: int = 1, agents_per_arena: int = 1) -> None:
        if num_arenas < 1:
            raise ValueError(f"num_arenas must be >= 1, got {num_arenas}")
        if not 1 <= agents_per_arena <= config.road.lane_count * 4:
            raise ValueError(f"agents_per_arena must be from 1 to {config.road.lane_count * 4} "
                             f"(4 per lane), got {agents_per_arena}")
        self.config = config
        self.num_arenas = num_arenas
        self.agents = agents_per_arena
        self.traffic_slots = config.traffic.resolved_vehicle_count
        self.vehicles = self.agents + self.traffic_slots
        road, traffic, ego = config.road, config.traffic, config.ego
        self.lane_count = road.lane_count
        self.lane_width = road.lane_width_m
        self.dt = config.episode.physics_dt_s
        self.frames = config.episode.frames_per_decision
        self.decision_period_s = config.episode.decision_period_s

        # Per-kind parameter tables: traffic behaviours, then agents.
        behaviours = traffic.behaviours
        def table(traffic_value: float, agent_value: float) -> np.ndarray:
            return np.array([traffic_value] * len(behaviours) + [agent_value])
        self.k_headway = table(traffic.time_headway_s, ego.time_headway_s)
        self.k_min_gap = table(traffic.min_gap_m, ego.min_gap_m)
        self.k_accel = table(traffic.max_accel_mps2, ego.max_accel_mps2)
        self.k_decel = table(traffic.comfort_decel_mps2, ego.comfort_decel_mps2)
        self.k_half_length = table(traffic.vehicle_length_m / 2, ego.length_m / 2)
        self.k_half_width = table(traffic.vehicle_width_m / 2, ego.width_m / 2)
        self.k_two_sqrt_ab = 2.0 * np.sqrt(self.k_accel * self.k_decel)
        self.k_change_duration = table(traffic.lane_change_duration_s, ego.lane_change_duration_s)
        self.k_politeness = np.array([b.politeness for b in behaviours] + [0.0])
        self.k_threshold = np.array([b.lane_change_threshold_mps2 for b in behaviours] + [0.0])
        self.k_speed_lo = np.array([b.desired_speed_kmh[0] * KMH for b in behaviours] + [0.0])
        self.k_speed_hi = np.array([b.desired_speed_kmh[1] * KMH for b in behaviours] + [0.0])
        rates = np.array([b.speed_change_rate_per_s for b in behaviours] + [0.0])
        self.k_change_prob = 1.0 - np.exp(-rates * self.decision_period_s)
        shares = np.array([b.share for b in behaviours])
        self.behaviour_cdf = np.cumsum(shares / shares.sum())

        self._lanes = LaneSorter(self.lane_count)
        self.lidar = Lidar(config.lidar.ray_count, config.lidar.max_range_m) \
            if config.lidar.enabled else None
        self.camera = Camera(config.camera, road) if config.camera.enabled else None
        self.rail_left_y = road.lane_count * road.lane_width_m + road.barrier_offset_m
        self.rail_right_y = -road.barrier_offset_m

        # (1, N, V): False where an agent would be compared with itself.
        self._not_self = np.ones((1, self.agents, self.vehicles), dtype=bool)
        self._not_self[0, np.arange(self.agents), np.arange(self.agents)] = False
        self.rngs: list[np.random.Generator] = [np.random.default_rng() for _ in range(num_arenas)]
        self.state = self._empty_state(num_arenas)
        self._needs_reset = np.ones(num_arenas, dtype=bool)

    # --- construction and reset ----------------------------------------------------------------

    def _empty_state(self, arenas: int) -> SimState:
        a, n, v = arenas, self.agents, self.vehicles
        f64 = lambda *shape: np.zeros(shape, dtype=np.float64)  # noqa: E731
        i64 = lambda *shape: np.zeros(shape, dtype=np.int64)  # noqa: E731
        b = lambda *shape: np.zeros(shape, dtype=bool)  # noqa: E731
        return SimState(
            x_m=f64(a, v), y_m=f64(a, v), speed_mps=f64(a, v), desired_speed_mps=f64(a, v),
            accel_mps2=f64(a, v), lane=i64(a, v), target_lane=i64(a, v),
            change_progress=f64(a, v), active=b(a, v), kind=i64(a, v), frame=i64(a),
            decisions=i64(a), agent_decisions=i64(a, n), ahead=b(a, n, v), credited=b(a, n, v),
            braking=b(a, n), distance_m=f64(a, n), lane_changes=i64(a, n), overtakes=i64(a, n),
            collisions=i64(a, n), emergency_brakes=i64(a, n), episode_return=f64(a, n))

    def reset(self, arenas: np.ndarray | list[int] | None = None,
              seeds: list[int | None] | None = None) -> None:
        """Start new episodes in ``arenas`` (all by default).

        A seed re-creates that arena's generator; None continues its stream, so that a sequence
        of episodes after one seeded reset is reproducible too.
        """
        rows = np.arange(self.num_arenas) if arenas is None else np.asarray(arenas, dtype=np.int64)
        if seeds is not None and len(seeds) != rows.size:
            raise ValueError(f"expected {rows.size} seeds (one per arena reset), got {len(seeds)}")
        for i, row in enumerate(rows):
            seed = None if seeds is None else seeds[i]
            if seed is not None:
                self.rngs[row] = np.random.default_rng(seed)
            self._reset_arena(int(row))
        self._needs_reset[rows] = False

    def agents_present(self) -> np.ndarray:
        """(A, N) bool: which agent slots have a car on the road."""
        return self.state.active[:, :self.agents].copy()

    def remove_agents(self, arena: int, slots: list[int] | np.ndarray) -> None:
        """Take agents' cars off the road of ``arena`` (a shared arena's trainer left).

        A removed car is invisible to sensors and other cars, cannot collide and anchors no
        traffic; its slot keeps stepping unseen until :meth:`respawn_agents` brings it back.
        """
        self.state.active[arena, np.asarray(slots, dtype=np.int64)] = False

    def restore_agents(self, arena: int, slots: list[int] | np.ndarray) -> None:
        """Put removed cars back where the arena's last reset placed them (right after it)."""
        self.state.active[arena, np.asarray(slots, dtype=np.int64)] = True

    def respawn_agents(self, arena: int, slots: list[int] | np.ndarray) -> None:
        """Start new episodes for some agents of ``arena`` while the road goes on.

        Each car is placed, at the initial cruise speed, at the first spot (lanes in a random
        order, then farther back) that keeps IDM-comfortable gaps to everything on the road,
        behind the agents still present. Its episode counters start from zero.
        """
        st, cfg, n = self.state, self.config, self.agents
        rng = self.rngs[arena]
        row = np.array([arena])
        speed = cfg.ego.initial_speed_kmh * KMH
        for slot in np.asarray(slots, dtype=np.int64):
            st.active[arena, slot] = False
            present = np.flatnonzero(st.active[arena, :n])
            base = st.x_m[arena, present].min() if present.size else st.x_m[arena, slot]
            lanes = rng.permutation(self.lane_count)
            offsets = -30.0 * np.arange(1, 9)
            # Every lane at 30 m back, then every lane at 60 m, ...: the nearest free spot.
            lane = np.tile(lanes, offsets.size)[None, :]
            x = (base + np.repeat(offsets, lanes.size))[None, :]
            ok = self._clearance_ok(st, row, lane, x, np.full(lane.shape, speed),
                                    np.full(lane.shape, AGENT_KIND), st.active[row])[0]
            # With no comfortable gap anywhere, the last spot tried (farthest back) is used.
            pick = int(np.argmax(ok)) if ok.any() else lane.size - 1
            st.x_m[arena, slot] = x[0, pick]
            st.lane[arena, slot] = st.target_lane[arena, slot] = lane[0, pick]
            st.y_m[arena, slot] = (lane[0, pick] + 0.5) * self.lane_width
            st.change_progress[arena, slot] = 0.0
            st.speed_mps[arena, slot] = st.desired_speed_mps[arena, slot] = speed
            st.accel_mps2[arena, slot] = 0.0
            st.active[arena, slot] = True
            for name in ("agent_decisions", "braking", "distance_m", "lane_changes", "overtakes",
                         "collisions", "emergency_brakes", "episode_return"):
                getattr(st, name)[arena, slot] = 0
            # Overtake tracking starts afresh both ways: what this car has ahead of it, and
            # whether it is ahead of each other agent (a respawn is never a pass).
            st.ahead[arena, slot] = st.x_m[arena] > st.x_m[arena, slot]
            st.credited[arena, slot] = False
            st.ahead[arena, :n, slot] = st.x_m[arena, slot] > st.x_m[arena, :n]
            st.credited[arena, :n, slot] = False

    def _reset_arena(self, row: int) -> None:
        rng = self.rngs[row]
        cfg = self.config
        fresh = self._empty_state(1)
        n, lanes = self.agents, self.lane_count
        # Agents: distinct lanes where possible, 30 m apart, at the initial cruise speed.
        agent_lanes = rng.permutation(np.resize(np.arange(lanes), max(n, lanes)))[:n]
        fresh.x_m[0, :n] = -30.0 * np.arange(n)
        fresh.lane[0, :n] = agent_lanes
        fresh.speed_mps[0, :n] = cfg.ego.initial_speed_kmh * KMH
        fresh.desired_speed_mps[0, :n] = cfg.ego.initial_speed_kmh * KMH
        fresh.kind[0, :n] = AGENT_KIND
        fresh.active[0, :n] = True

        # Traffic: spread over the kept window with a minimum spacing per lane: the k-th smallest
        # uniform of a lane is shifted by k spacings, so neighbours are at least that far apart.
        # Cars that would crowd an agent are left to spawn later.
        count = self.traffic_slots
        if count:
            lo = fresh.x_m[0, :n].min() - cfg.traffic.keep_behind_m
            hi = fresh.x_m[0, :n].max() + cfg.traffic.keep_ahead_m
            spacing = cfg.traffic.vehicle_length_m + 20.0
            lane = rng.integers(0, lanes, size=count)
            u = rng.random(count)
            kind = np.searchsorted(self.behaviour_cdf, rng.random(count), side="right")
            kind = np.minimum(kind, len(BEHAVIOURS) - 1)
            speed = self.k_speed_lo[kind] + rng.random(count) * (self.k_speed_hi[kind] - self.k_speed_lo[kind])
            order = np.lexsort((u, lane))
            per_lane = np.bincount(lane, minlength=lanes)
            rank = np.empty(count, dtype=np.int64)
            rank[order] = np.arange(count) - np.repeat(np.cumsum(per_lane) - per_lane, per_lane)
            free_length = (hi - lo) - per_lane[lane] * spacing
            x = lo + u * np.maximum(free_length, 0.0) + rank * spacing
            cols = slice(n, n + count)
            fresh.x_m[0, cols] = x
            fresh.lane[0, cols] = lane
            fresh.kind[0, cols] = kind
            fresh.speed_mps[0, cols] = speed
            fresh.desired_speed_mps[0, cols] = speed
            fresh.active[0, cols] = x <= hi
        fresh.target_lane[:] = fresh.lane
        fresh.y_m[:] = (fresh.lane + 0.5) * self.lane_width
        self._clear_agent_zones(fresh)
        self._start_tracking(fresh, np.ones((1, self.vehicles), dtype=bool))
        self.state.assign(np.array([row]), fresh)

    def _clearance_ok(self, st: SimState, arena: np.ndarray, lane: np.ndarray, x: np.ndarray,
                      speed: np.ndarray, kind: np.ndarray, others: np.ndarray) -> np.ndarray:
        """Whether candidate spots (K, M) keep an IDM-comfortable gap to every other vehicle.

        ``arena`` (K,) rows of ``st``; lane, x, speed, kind (K, M) the candidates; ``others``
        (K, V) the vehicles to keep clear of. A candidate must leave its new leader at least
        its own desired gap, and its new follower at least the follower's desired gap.
        """
        o_x = st.x_m[arena][:, None, :]
        o_lane = st.lane[arena][:, None, :]
        o_target = st.target_lane[arena][:, None, :]
        o_speed = st.speed_mps[arena][:, None, :]
        o_kind = st.kind[arena][:, None, :]
        c_lane, c_x, c_speed, c_kind = (a[..., None] for a in (lane, x, speed, kind))
        shares_lane = ((o_lane == c_lane) | (o_target == c_lane)) & others[:, None, :]
        dx = o_x - c_x
        bodies = self.k_half_length[o_kind] + self.k_half_length[c_kind]
        need_ahead = idm_desired_gap(c_speed, c_speed - o_speed, self.k_headway[c_kind],
                                     self.k_min_gap[c_kind], self.k_two_sqrt_ab[c_kind])
        need_behind = idm_desired_gap(o_speed, o_speed - c_speed, self.k_headway[o_kind],
                                      self.k_min_gap[o_kind], self.k_two_sqrt_ab[o_kind])
        clear = np.where(dx >= 0.0, dx - bodies >= need_ahead, -dx - bodies >= need_behind)
        return np.all(clear | ~shares_lane, axis=-1)

    def _clear_agent_zones(self, st: SimState) -> None:
        """Deactivate traffic placed where it would crowd an agent (it spawns again later)."""
        n = self.agents
        arenas, vehicles = st.x_m.shape
        traffic = np.arange(n, vehicles)
        if traffic.size == 0:
            return
        rows = np.repeat(np.arange(arenas), traffic.size)
        cols = np.tile(traffic, arenas)
        others = np.zeros((rows.size, vehicles), dtype=bool)
        others[:, :n] = True
        ok = self._clearance_ok(st, rows, st.lane[rows, cols][:, None], st.x_m[rows, cols][:, None],
                                st.speed_mps[rows, cols][:, None], st.kind[rows, cols][:, None],
                                others)[:, 0]
        st.active[rows, cols] &= ok

    def _start_tracking(self, st: SimState, vehicles: np.ndarray) -> None:
        """Reset overtake tracking for the (A, V) ``vehicles`` that just appeared."""
        ahead_now = st.x_m[:, None, :] > st.x_m[:, :self.agents, None]
        mask = vehicles[:, None, :]
        st.ahead[:] = np.where(mask, ahead_now, st.ahead)
        st.credited[:] = st.credited & ~mask

    # --- stepping ---------------------------------------------------------------------------

    def step(self, actions: np.ndarray, arenas: np.ndarray | None = None) -> StepResult:
        """Advance one decision. ``actions`` is (A, N) ints in [0, 5) for the stepped arenas.

        ``arenas`` selects a subset to step (the others do not move and use no randomness);
        by default all arenas step.
        """
        rows = np.arange(self.num_arenas) if arenas is None else np.asarray(arenas, dtype=np.int64)
        actions = np.asarray(actions)
        expected = (rows.size, self.agents)
        if actions.shape != expected or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(f"expected integer actions of shape {expected}, got "
                             f"{actions.dtype} {actions.shape}")
        if actions.size and (actions.min() < 0 or actions.max() >= ACTION_COUNT):
            bad = actions[(actions < 0) | (actions >= ACTION_COUNT)]
            raise ValueError(f"actions must be in [0, {ACTION_COUNT}) "
                             f"({', '.join(ACTION_NAMES)}), got {bad.tolist()}")
        if self._needs_reset[rows].any():
            raise RuntimeError(f"arenas {rows[self._needs_reset[rows]].tolist()} must be reset "
                               "before they can step")
        whole = arenas is None
        st = self.state if whole else self.state.select(rows)
        uniforms = np.empty((rows.size, self.vehicles, UNIFORMS_PER_VEHICLE))
        for i, row in enumerate(rows):
            self.rngs[row].random(out=uniforms[i])
        result = self._advance(st, actions.astype(np.int64), uniforms)
        if not whole:
            self.state.assign(rows, st)
        return result

    def _vehicle_params(self, kind: np.ndarray) -> "_VehicleParams":
        """Per-vehicle parameters looked up once per decision (kinds change only on spawn)."""
        return _VehicleParams(
            headway=self.k_headway[kind], min_gap=self.k_min_gap[kind],
            max_accel=self.k_accel[kind], two_sqrt_ab=self.k_two_sqrt_ab[kind],
            half_length=self.k_half_length[kind], half_width=self.k_half_width[kind],
            change_rate=self.dt / self.k_change_duration[kind], is_traffic=kind < AGENT_KIND)

    def _advance(self, st: SimState, actions: np.ndarray, uniforms: np.ndarray) -> StepResult:
        cfg = self.config
        n, lanes = self.agents, self.lane_count
        arenas = st.x_m.shape[0]
        kmh_step = cfg.ego.cruise_step_kmh * KMH

        # Actions: cruise target steps, and lane changes where a lane is free to start one.
        cruise = st.desired_speed_mps[:, :n]
        cruise += kmh_step * (actions == CRUISE_UP) - kmh_step * (actions == CRUISE_DOWN)
        np.minimum(np.maximum(cruise, cfg.ego.cruise_min_kmh * KMH, out=cruise),
                   cfg.ego.cruise_max_kmh * KMH, out=cruise)
        agent_lane = st.lane[:, :n]
        idle = st.target_lane[:, :n] == agent_lane
        go_left = (actions == LANE_LEFT) & idle & (agent_lane < lanes - 1)
        go_right = (actions == LANE_RIGHT) & idle & (agent_lane > 0)
        if cfg.ego.lane_change_check and (go_left | go_right).any():
            clear = self.side_clear(st)
            go_left &= clear[..., 1]
            go_right &= clear[..., 0]
            if n > 1:
                self._one_agent_per_gap(st, go_left, go_right)
        started = go_left | go_right
        st.target_lane[:, :n] += go_left.astype(np.int64) - go_right
        st.change_progress[:, :n] = np.where(started, 0.0, st.change_progress[:, :n])
        lateral = (actions == LANE_LEFT) | (actions == LANE_RIGHT)
        applied = np.where(lateral & ~started, KEEP, actions)

        # Traffic now and then picks a new desired speed (Min et al.'s random accelerate/brake).
        change = (st.kind < AGENT_KIND) & st.active \
            & (uniforms[..., _U_CHANGE] < self.k_change_prob[st.kind])
        if change.any():
            new_speed = self.k_speed_lo[st.kind] + uniforms[..., _U_NEW_SPEED] * (
                self.k_speed_hi[st.kind] - self.k_speed_lo[st.kind])
            st.desired_speed_mps[:] = np.where(change, new_speed, st.desired_speed_mps)

        params = self._vehicle_params(st.kind)
        collided = np.zeros((arenas, n), dtype=bool)
        brakes = np.zeros((arenas, n), dtype=np.int64)
        # Who follows whom is sorted out once per decision. Within a decision lanes only lose
        # members (changes that finish), so a frame-0 leader is never farther than the true
        # one: keeping it for the decision's frames is conservative. Traffic that starts a
        # change at frame 0 is seen in its new lane from the next decision: 0.3 s at most,
        # less than a driver's reaction time, while it has moved sideways by under 2 cm.
        x_rel = st.x_m - st.x_m[:, :1]
        index = self._lanes.build(x_rel, st.lane, st.target_lane, st.active)
        lead, valid = leaders(index)
        for frame in range(self.frames):
            self._frame(st, params, lead, valid, collided, brakes,
                        mobil_index=index if frame == 0 else None)

        gained, undone, passed = self._track_overtakes(st)
        self._recycle(st, uniforms)
        st.decisions += 1
        st.agent_decisions += 1

        # Rewards: Min et al. Eq. (1)-(5), each term on its own.
        rc = cfg.reward
        speed_kmh = st.speed_mps[:, :n] / KMH
        speed_term = (speed_kmh - rc.speed_min_kmh) / (rc.speed_max_kmh - rc.speed_min_kmh)
        if rc.clip_speed_term:
            speed_term = np.clip(speed_term, 0.0, 1.0)
        terms = {
            "speed": speed_term * rc.speed_reward_max,
            "collision": rc.collision * collided,
            "lane_change": rc.lane_change * started,
            "overtake": rc.overtake * (gained - undone),
            "passed": rc.passed * passed.astype(np.float64),
        }
        reward = terms["speed"] + terms["collision"] + terms["lane_change"] + terms["overtake"] \
            + terms["passed"]
        st.episode_return += reward
        st.lane_changes += started
        st.collisions += collided
        st.overtakes += gained - undone
        st.emergency_brakes += brakes
        truncated = st.agent_decisions >= cfg.episode.max_decisions
        return StepResult(reward=reward, reward_terms=terms, terminated=collided,
                          truncated=truncated & ~collided, action_applied=applied)

    def _frame(self, st: SimState, p: "_VehicleParams", lead: np.ndarray, valid: np.ndarray,
               collided: np.ndarray, brakes: np.ndarray, mobil_index: LaneIndex | None) -> None:
        """One physics frame for every arena of ``st``; event counters are updated in place.

        ``lead``/``valid`` (A, 2V): each lane entry's leader; with ``mobil_index`` traffic also
        considers lane changes this frame.
        """
        cfg = self.config
        n, dt = self.agents, self.dt
        arenas, vehicles = st.x_m.shape
        x_rel = st.x_m - st.x_m[:, :1]
        speed = st.speed_mps

        # Gaps: the nearer of the leaders in the vehicle's lane and, while changing, target.
        rear = (x_rel - p.half_length).reshape(-1)
        front = x_rel + p.half_length
        entry_gap = np.where(valid, rear[lead] - np.concatenate([front, front], axis=1), NO_GAP_M)
        first, second = entry_gap[:, :vehicles], entry_gap[:, vehicles:]
        gap = np.minimum(first, second)
        leader = np.where(second < first, lead[:, vehicles:], lead[:, :vehicles])  # flat index
        has_leader = gap < NO_GAP_M
        leader_speed = np.where(has_leader, speed.reshape(-1)[leader], speed)
        closing = speed - leader_speed

        accel = idm_accel(speed, st.desired_speed_mps, gap, closing, p.headway, p.min_gap,
                          p.max_accel, p.two_sqrt_ab)
        # Agents: autonomous emergency braking when the time to collision gets short.
        agent_closing = closing[:, :n]
        aeb = (agent_closing > 0.0) & (gap[:, :n] < agent_closing * cfg.ego.aeb_time_to_collision_s)
        if aeb.any():
            accel[:, :n] = np.where(aeb, np.minimum(accel[:, :n], -cfg.ego.aeb_decel_mps2),
                                    accel[:, :n])
        accel = np.maximum(np.minimum(accel, p.max_accel), -cfg.traffic.max_decel_mps2)

        if mobil_index is not None:
            # Traffic considers changing left on even decisions and right on odd ones: cars
            # from both sides never start into the same gap at the same moment.
            direction = np.where(st.decisions % 2 == 0, 1, -1)
            self._mobil(st, p, mobil_index, direction, x_rel, accel, gap, leader, has_leader)

        new_speed = np.maximum(speed + accel * dt, 0.0)
        # Traffic never drives into traffic: a speed cap keeps it behind a traffic leader even
        # if that leader brakes as hard as it can (Ho's simulator has the same safety rule).
        # An agent ahead gets no such courtesy: a reckless cut-in can be rear-ended.
        capped = p.is_traffic & has_leader & p.is_traffic.reshape(-1)[leader]
        cap = np.maximum(leader_speed - cfg.traffic.max_decel_mps2 * dt + (gap - 0.2) / dt, 0.0)
        new_speed = np.where(capped, np.minimum(new_speed, cap), new_speed)
        travelled = np.where(st.active, 0.5 * (speed + new_speed) * dt, 0.0)
        st.accel_mps2[:] = (new_speed - speed) / dt
        st.x_m += travelled
        st.speed_mps[:] = new_speed
        st.distance_m += travelled[:, :n]

        # Lateral: minimum-jerk moves between lane centres.
        changing = st.target_lane != st.lane
        if changing.any():
            progress = np.where(changing, st.change_progress + p.change_rate, 0.0)
            finished = progress >= 1.0
            st.lane[:] = np.where(finished, st.target_lane, st.lane)
            st.change_progress[:] = np.where(finished, 0.0, progress)
            shift = (st.target_lane - st.lane) * min_jerk(st.change_progress)
            st.y_m[:] = (st.lane + 0.5 + shift) * self.lane_width
        st.frame += 1

        # Agents' collisions with any other vehicle (boxes overlap). Two boxes can only
        # overlap if they share a lane, and then some gap in that lane is negative: the exact
        # test runs only on frames where one is.
        if (gap < 0.0).any():
            ax, ay = st.x_m[:, :n, None], st.y_m[:, :n, None]
            overlap = (np.abs(st.x_m[:, None, :] - ax)
                       < p.half_length[:, :n, None] + p.half_length[:, None, :]) \
                & (np.abs(st.y_m[:, None, :] - ay)
                   < p.half_width[:, :n, None] + p.half_width[:, None, :])
            overlap &= st.active[:, None, :] & self._not_self & st.active[:, :n, None]
            collided |= overlap.any(axis=-1)

        # Ho's emergency brakes: the onset of hard braking with a big speed difference ahead.
        braking = st.accel_mps2[:, :n] <= -cfg.ego.emergency_decel_mps2
        onset = braking & ~st.braking
        if onset.any():
            big_difference = has_leader[:, :n] & (
                closing[:, :n] >= cfg.ego.emergency_speed_diff_kmh * KMH)
            brakes += onset & big_difference
        st.braking[:] = braking

    def _track_overtakes(self, st: SimState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Count, per agent, cars it passed (once per car), overtakes undone, and cars passing it.

        A pass is a car's centre moving from ahead of the agent's centre to behind it, between
        two decisions. Recycled cars restart their tracking, so a respawn is never a pass.
        """
        n = self.agents
        ahead_now = st.x_m[:, None, :] > st.x_m[:, :n, None]
        live = st.active[:, None, :] & self._not_self
        overtook = st.ahead & ~ahead_now & live
        got_passed = ~st.ahead & ahead_now & live
        gained = (overtook & ~st.credited).sum(axis=-1)
        st.credited |= overtook
        passed = got_passed.sum(axis=-1)
        undone = np.zeros_like(gained)
        if self.config.reward.undo_overtake_when_passed_back:
            taken_back = got_passed & st.credited
            undone = taken_back.sum(axis=-1)
            st.credited &= ~taken_back
        st.ahead[:] = ahead_now
        return gained, undone, passed

    def _mobil(self, st: SimState, p: "_VehicleParams", index: LaneIndex, direction: np.ndarray,
               x_rel: np.ndarray, accel: np.ndarray, gap: np.ndarray, leader: np.ndarray,
               has_leader: np.ndarray) -> None:
        """MOBIL lane changes for traffic, towards ``direction`` (A,): +1 left, -1 right."""
        target = st.lane + direction[:, None]
        candidate = p.is_traffic & st.active & (st.target_lane == st.lane) \
            & (target >= 0) & (target < self.lane_count)
        flat = np.flatnonzero(candidate)
        if flat.size == 0:
            return
        vehicles = st.x_m.shape[1]
        arena = flat // vehicles
        g = {name: getattr(p, name).reshape(-1) for name in
             ("headway", "min_gap", "max_accel", "two_sqrt_ab", "half_length")}
        xf, vf = x_rel.reshape(-1), st.speed_mps.reshape(-1)
        v0f, af = st.desired_speed_mps.reshape(-1), accel.reshape(-1)

        def idm(i: np.ndarray, gap_m: np.ndarray, closing: np.ndarray) -> np.ndarray:
            return idm_accel(vf[i], v0f[i], gap_m, closing, g["headway"][i], g["min_gap"][i],
                             g["max_accel"][i], g["two_sqrt_ab"][i])

        x, v, half = xf[flat], vf[flat], g["half_length"][flat]
        new_lane = target.reshape(-1)[flat]
        new_leader, new_follower = neighbours_at(index, arena, new_lane, x)
        _, old_follower = neighbours_at(index, arena, st.lane.reshape(-1)[flat], x)

        has_nl = new_leader >= 0
        nl = np.maximum(new_leader, 0)
        gap_new = np.where(has_nl, xf[nl] - x - g["half_length"][nl] - half, NO_GAP_M)
        accel_new = idm(flat, gap_new, np.where(has_nl, v - vf[nl], 0.0))

        has_nf = new_follower >= 0
        nf = np.maximum(new_follower, 0)
        gap_nf = np.where(has_nf, x - xf[nf] - half - g["half_length"][nf], NO_GAP_M)
        nf_accel_new = idm(nf, gap_nf, vf[nf] - v)
        nf_gain = np.where(has_nf, nf_accel_new - af[nf], 0.0)

        # The old follower would follow the old leader across the gap this car leaves.
        has_of = old_follower >= 0
        of = np.maximum(old_follower, 0)
        own_gap = gap.reshape(-1)[flat]
        own_has_leader = has_leader.reshape(-1)[flat]
        of_gap_after = np.where(own_has_leader, own_gap + 2 * half, NO_GAP_M) \
            + (x - xf[of] - half - g["half_length"][of])
        ol_speed = np.where(own_has_leader, vf[leader.reshape(-1)[flat]], vf[of])
        of_gain = np.where(has_of, idm(of, of_gap_after, vf[of] - ol_speed) - af[of], 0.0)

        kind = st.kind.reshape(-1)[flat]
        min_gap = g["min_gap"][flat]
        safe = (gap_new > min_gap) & (gap_nf > min_gap) \
            & (~has_nf | (nf_accel_new >= -self.config.traffic.safe_decel_mps2))
        incentive = accel_new - af[flat] + self.k_politeness[kind] * (nf_gain + of_gain)
        accept = safe & (incentive > self.k_threshold[kind])
        st.target_lane.reshape(-1)[flat[accept]] = new_lane[accept]
        st.change_progress.reshape(-1)[flat[accept]] = 0.0

    def _recycle(self, st: SimState, uniforms: np.ndarray) -> None:
        """Respawn traffic that is out of every agent's range, and fill empty slots."""
        cfg = self.config.traffic
        n = self.agents
        arenas, vehicles = st.x_m.shape
        if vehicles == n:
            return
        dx = st.x_m[:, None, n:] - st.x_m[:, :n, None]  # (A, N, T) traffic relative to agents
        # Agents off the road (a shared arena's free slots) anchor nothing, unless none is on.
        present = st.active[:, :n]
        anchors = (present | ~present.any(axis=1, keepdims=True))[:, :, None]
        kept = ((dx <= cfg.keep_ahead_m) & (dx >= -cfg.keep_behind_m) & anchors).any(axis=1)
        was_active = st.active[:, n:]
        # Out-of-range cars move at once; empty slots (no free spot found earlier) retry now
        # and then rather than every decision.
        retry = (st.decisions % RESPAWN_RETRY_DECISIONS == 0)[:, None]
        need = (was_active & ~kept) | (~was_active & retry)
        arena, tcol = np.nonzero(need)
        if arena.size == 0:
            return
        col = tcol + n
        st.active[arena, col] = False
        u = uniforms[arena, col]
        # A car that fell behind every agent comes back ahead, and one left ahead comes back
        # behind; an empty slot picks a side at random.
        fell_behind = ((dx[arena, :, tcol] < 0.0) | ~anchors[arena, :, 0]).all(axis=1)
        ahead_side = np.where(was_active[arena, tcol], fell_behind, u[:, _U_SIDE] < 0.5)
        anchor = np.minimum((u[:, _U_ANCHOR] * n).astype(np.int64), n - 1)
        anchor = np.where(anchors[arena, anchor, 0], anchor,
                          np.argmax(anchors[arena, :, 0], axis=1))
        lane = np.minimum((u[:, _U_LANE:_U_LANE + SPAWN_CANDIDATES] * self.lane_count)
                          .astype(np.int64), self.lane_count - 1)
        window = np.where(ahead_side[:, None], np.array(cfg.spawn_ahead_m), np.array(cfg.spawn_behind_m))
        distance = window[:, :1] + u[:, _U_OFFSET:_U_OFFSET + SPAWN_CANDIDATES] * (window[:, 1:] - window[:, :1])
        x = st.x_m[arena, anchor][:, None] + np.where(ahead_side[:, None], distance, -distance)
        kind = np.minimum(np.searchsorted(self.behaviour_cdf, u[:, _U_BEHAVIOUR], side="right"),
                          len(BEHAVIOURS) - 1)
        speed = self.k_speed_lo[kind] + u[:, _U_SPEED] * (self.k_speed_hi[kind] - self.k_speed_lo[kind])
        shape = lane.shape
        ok = self._clearance_ok(st, arena, lane, x, np.broadcast_to(speed[:, None], shape),
                                np.broadcast_to(kind[:, None], shape), st.active[arena])
        found = ok.any(axis=1)
        pick = np.argmax(ok, axis=1)
        pick_lane = lane[np.arange(arena.size), pick]
        pick_x = x[np.arange(arena.size), pick]
        # Two spawns of this decision may not land on each other: the later one waits.
        same_place = (arena[:, None] == arena[None, :]) & (pick_lane[:, None] == pick_lane[None, :]) \
            & (np.abs(pick_x[:, None] - pick_x[None, :]) < SPAWN_SEPARATION_M) \
            & found[:, None] & found[None, :]
        found &= ~np.tril(same_place, k=-1).any(axis=1)
        a, c = arena[found], col[found]
        st.x_m[a, c] = pick_x[found]
        st.lane[a, c] = pick_lane[found]
        st.target_lane[a, c] = pick_lane[found]
        st.change_progress[a, c] = 0.0
        st.y_m[a, c] = (pick_lane[found] + 0.5) * self.lane_width
        st.speed_mps[a, c] = speed[found]
        st.desired_speed_mps[a, c] = speed[found]
        st.accel_mps2[a, c] = 0.0
        st.kind[a, c] = kind[found]
        st.active[a, c] = True
        spawned = np.zeros((arenas, vehicles), dtype=bool)
        spawned[a, c] = True
        self._start_tracking(st, spawned)

    # --- what agents see ----------------------------------------------------------------------

    def headings(self) -> np.ndarray:
        """Agents' headings (A, N) in radians from the road's direction, left positive."""
        st, n = self.state, self.agents
        kind = st.kind[:, :n]
        lateral_mps = (st.target_lane[:, :n] - st.lane[:, :n]) * self.lane_width \
            * min_jerk_rate(st.change_progress[:, :n]) / self.k_change_duration[kind]
        return np.arctan2(lateral_mps, np.maximum(st.speed_mps[:, :n], 1e-3))

    def ego_vector(self) -> np.ndarray:
        """(A, N, 6) float32: the fields of :data:`EGO_FIELDS`."""
        st, n = self.state, self.agents
        out = np.empty((st.x_m.shape[0], n, len(EGO_FIELDS)), dtype=np.float32)
        out[..., 0] = st.speed_mps[:, :n]
        out[..., 1] = st.desired_speed_mps[:, :n]
        out[..., 2] = np.minimum(np.maximum(np.floor(st.y_m[:, :n] / self.lane_width), 0.0),
                                 self.lane_count - 1)
        out[..., 3] = self.lane_count
        out[..., 4] = st.change_progress[:, :n]
        out[..., 5] = st.target_lane[:, :n] - st.lane[:, :n]
        return out

    def side_clear(self, st: SimState | None = None) -> np.ndarray:
        """(A, N, 2) bool: whether the lane to each agent's right [0] and left [1] is clear for
        starting a lane change (see ``EgoConfig.lane_change_check``): no other vehicle in it,
        or moving into it, from ``lane_change_clear_behind_m`` behind the agent's rear bumper
        to ``lane_change_clear_ahead_m`` ahead of its front bumper, each window growing by the
        speed at which a car there closes in times ``lane_change_closing_time_s``. A lane that
        does not exist counts as clear here; the mask refuses it anyway. ``st``: the state of
        the arenas being stepped (default: all)."""
        st = self.state if st is None else st
        n, ego = self.agents, self.config.ego
        half = self.k_half_length[st.kind]                           # (A, V)
        dx = st.x_m[:, None, :] - st.x_m[:, :n, None]                 # (A, N, V): other - agent
        reach = half[:, None, :] + half[:, :n, None]
        # Positive when the other car gains on the agent from behind (or the agent on a car
        # ahead): the gap it needs grows with that speed.
        closing_mps = st.speed_mps[:, None, :] - st.speed_mps[:, :n, None]
        ahead_m = ego.lane_change_clear_ahead_m \
            + np.maximum(-closing_mps, 0.0) * ego.lane_change_closing_time_s
        behind_m = ego.lane_change_clear_behind_m \
            + np.maximum(closing_mps, 0.0) * ego.lane_change_closing_time_s
        near = (dx - reach < ahead_m) & (-dx - reach < behind_m)
        near &= st.active[:, None, :]
        near[:, np.arange(n), np.arange(n)] = False                  # not the agent itself
        clear = np.empty(near.shape[:2] + (2,), dtype=bool)
        for side, step in enumerate((-1, 1)):
            lane = (st.lane[:, :n] + step)[:, :, None]
            there = (st.lane[:, None, :] == lane) | (st.target_lane[:, None, :] == lane)
            clear[..., side] = ~(near & there).any(axis=2)
        return clear

    def _one_agent_per_gap(self, st: SimState, go_left: np.ndarray,
                           go_right: np.ndarray) -> None:
        """Agents cleared into the same lane at the same decision, near each other (from
        opposite sides), would meet there: the lower-numbered agent goes, the other keeps its
        lane. Changes ``go_left``/``go_right`` (A, N) in place."""
        n, ego = self.agents, self.config.ego
        started = go_left | go_right
        if not (started.sum(axis=1) > 1).any():
            return
        target = st.lane[:, :n] + go_left.astype(np.int64) - go_right
        half = self.k_half_length[st.kind[:, :n]]
        dx = np.abs(st.x_m[:, None, :n] - st.x_m[:, :n, None]) - half[:, None, :] \
            - half[:, :, None]
        window = max(ego.lane_change_clear_ahead_m, ego.lane_change_clear_behind_m)
        lower = np.tri(n, k=-1, dtype=bool)          # [i, j]: j < i
        conflict = lower & (dx < window) & started[:, None, :] & started[:, :, None] \
            & (target[:, None, :] == target[:, :, None])
        yields = conflict.any(axis=2)
        go_left &= ~yields
        go_right &= ~yields

    def action_mask(self) -> np.ndarray:
        """(A, N, 5) int8: 1 where the action can be taken now (a lane change needs a lane
        there, none under way, and, with ``ego.lane_change_check``, a clear side)."""
        st, n = self.state, self.agents
        idle = st.target_lane[:, :n] == st.lane[:, :n]
        mask = np.ones((self.num_arenas, n, ACTION_COUNT), dtype=np.int8)
        left = idle & (st.lane[:, :n] < self.lane_count - 1)
        right = idle & (st.lane[:, :n] > 0)
        if self.config.ego.lane_change_check:
            clear = self.side_clear()
            left &= clear[..., 1]
            right &= clear[..., 0]
        mask[..., LANE_LEFT] = left
        mask[..., LANE_RIGHT] = right
        return mask

    def _observer_views(self) -> tuple[np.ndarray, ...]:
        """Per observer (arena-major, agent-minor): its origin and the cars it can see."""
        st, n = self.state, self.agents
        arenas = self.num_arenas
        x_rel = st.x_m - st.x_m[:, :1]
        origin_x = x_rel[:, :n].reshape(-1)
        origin_y = st.y_m[:, :n].reshape(-1)
        heading = self.headings().reshape(-1)
        car_x = np.repeat(x_rel, n, axis=0)
        car_y = np.repeat(st.y_m, n, axis=0)
        kind = np.repeat(st.kind, n, axis=0)
        visible = np.repeat(st.active, n, axis=0)
        visible[np.arange(arenas * n), np.tile(np.arange(n), arenas)] = False
        return (origin_x, origin_y, heading, car_x, car_y, self.k_half_length[kind],
                self.k_half_width[kind], visible)

    def observe(self) -> dict[str, np.ndarray]:
        """Observations of every agent: lidar (A, N, R), camera (A, N, H, W[, 3]), ego (A, N, 6)."""
        arenas, n = self.num_arenas, self.agents
        out: dict[str, np.ndarray] = {}
        views = self._observer_views() if (self.lidar or self.camera) else None
        if self.lidar is not None:
            assert views is not None
            scan = self.lidar.scan(*views, rail_left_y=self.rail_left_y,
                                   rail_right_y=self.rail_right_y)
            out["lidar"] = scan.reshape(arenas, n, -1)
        if self.camera is not None:
            assert views is not None
            road_x = np.repeat(self.state.x_m[:, 0], self.agents)
            image = self.camera.render(*views, road_x=road_x)
            out["camera"] = image.reshape((arenas, n) + image.shape[1:])
        out["ego"] = self.ego_vector()
        return out

    def metrics(self) -> dict[str, np.ndarray]:
        """Each agent's episode so far: the papers' metrics, (A, N) per name in METRIC_FIELDS."""
        table = self.metrics_table()
        return {name: table[..., i] for i, name in enumerate(METRIC_FIELDS)}

    def metrics_table(self) -> np.ndarray:
        """(A, N, len(METRIC_FIELDS)) float64: :meth:`metrics` as one table (what travels)."""
        st = self.state
        elapsed_s = st.agent_decisions * self.decision_period_s
        with np.errstate(divide="ignore", invalid="ignore"):
            avg_speed = np.where(elapsed_s > 0, st.distance_m / elapsed_s / KMH, 0.0)
        columns = {"avg_speed_kmh": avg_speed, "lane_changes": st.lane_changes,
                   "overtakes": st.overtakes, "collisions": st.collisions,
                   "emergency_brakes": st.emergency_brakes, "distance_m": st.distance_m,
                   "return": st.episode_return, "decisions": st.agent_decisions}
        table = np.empty(elapsed_s.shape + (len(METRIC_FIELDS),))
        for i, name in enumerate(METRIC_FIELDS):
            table[..., i] = columns[name]
        return table

    def traffic_overlaps(self) -> np.ndarray:
        """(A,) pairs of traffic cars whose boxes overlap now: zero in normal flow."""
        st, n = self.state, self.agents
        x, y = st.x_m[:, n:], st.y_m[:, n:]
        kind, active = st.kind[:, n:], st.active[:, n:]
        half_l, half_w = self.k_half_length[kind], self.k_half_width[kind]
        overlap = (np.abs(x[:, :, None] - x[:, None, :]) < half_l[:, :, None] + half_l[:, None, :]) \
            & (np.abs(y[:, :, None] - y[:, None, :]) < half_w[:, :, None] + half_w[:, None, :]) \
            & active[:, :, None] & active[:, None, :]
        return np.triu(overlap, k=1).sum(axis=(1, 2))
