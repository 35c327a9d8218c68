"""Where vehicles appear: the start of an episode, traffic's treadmill, agents joining a road.

- At reset the agents stand 30 m apart in distinct lanes (where there are enough) at the
  initial cruise speed, and traffic is spread over the kept window around them with a minimum
  spacing per lane; cars that would crowd an agent wait to spawn later.
- Under ``traffic.entry = "comfortable"`` (a treadmill) each decision traffic that fell out of
  every agent's range (``traffic.keep_ahead_m`` / ``keep_behind_m``, along the road) is
  recycled at once, so the road holds its count where gaps allow: it is placed by a drawn
  agent on a side drawn evenly, ahead or behind whichever side it left by, in the spawn window
  of that side (``traffic.spawn_ahead_m``, 30-90 m, or ``spawn_behind_m``, 30-60 m). (The numpy code
  before issue 58 meant a car left behind to come back ahead and one left ahead to come back
  behind, but read that from a view it had just cleared, so it drew every side evenly; the
  kept tables ran so, and the compiled loop keeps it.) A spot is taken only if it keeps
  IDM-comfortable gaps to everyone in its lane; when the window has none, the rest of the
  kept range on that side is tried, and a slot that still finds none tries again the next
  decision: the road holds the density it is labelled with.
- Under ``traffic.entry = "spawners"`` (Min et al.'s code) the road starts with the agents
  alone; cars out of range or touching another leave it, and eight spawners bring new ones
  on their own timing, up to the count (:mod:`.spawners`).
- Under ``traffic.entry = "free_zone"`` (Ho's code) the road starts with the agents alone, a
  car out of range leaves it, and new cars enter by his rule instead (:mod:`.entry`).
- An agent joining or restarting on a shared road is placed behind the agents still on it, at
  the first spot with comfortable gaps.

Every random number comes from the arena's own generator, at reset directly and while stepping
from the decision's block of uniforms (:mod:`.randomness`).
"""

from __future__ import annotations

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from .config import SimConfig
from .entry import FreeZoneEntry
from .overtakes import OvertakeTracker
from .randomness import SPAWN_CANDIDATES, U_ANCHOR, U_BEHAVIOUR, U_LANE, U_OFFSET, U_SIDE, U_SPEED
from .road import Road
from .spawners import Spawners
from .spawning_kernels import kept_in_range, respawn
from .state import SimState
from .traffic.car_following import idm_desired_gap
from .units import KMH
from .vehicles import VehicleKinds

SPAWN_SEPARATION_M = 25.0  # spawns of one decision in one lane keep this far apart
AGENT_SPACING_M = 30.0  # agents start this far apart; a joining car tries steps of it
JOIN_STEPS_BACK = 8  # ... this many steps behind the agents on the road


class Spawner:
    """Places vehicles for :class:`~overtake.server.sim.core.HighwaySim`."""

    def __init__(
        self,
        config: SimConfig,
        kinds: VehicleKinds,
        road: Road,
        agents: int,
        tracker: OvertakeTracker,
    ) -> None:
        self.traffic = config.traffic
        self.kinds = kinds
        self.road = road
        self.agents = agents
        self.traffic_slots = config.traffic.resolved_vehicle_count
        self.vehicles = agents + self.traffic_slots
        self.tracker = tracker
        self.initial_speed_mps = config.ego.initial_speed_kmh * KMH
        # (2, SPAWN_CANDIDATES) near and far edges (m from the anchor agent) per candidate.
        traffic = config.traffic
        half = SPAWN_CANDIDATES // 2

        def windows(spawn: tuple[float, float], keep_m: float) -> np.ndarray:
            far = keep_m - traffic.vehicle_length_m
            return np.array(
                [
                    [spawn[0]] * SPAWN_CANDIDATES,
                    [spawn[1]] * half + [far] * (SPAWN_CANDIDATES - half),
                ]
            )

        self._ahead_windows = windows(traffic.spawn_ahead_m, traffic.keep_ahead_m)
        self._behind_windows = windows(traffic.spawn_behind_m, traffic.keep_behind_m)
        self._lane_centre_y = road.centre_y(np.arange(road.lane_count))
        self.entry = (
            FreeZoneEntry(traffic, kinds, road, agents, config.episode.frames_per_decision, tracker)
            if traffic.entry == "free_zone"
            else None
        )
        self.spawners = (
            Spawners(traffic, kinds, road, agents, config.episode.decision_period_s, tracker)
            if traffic.entry == "spawners"
            else None
        )
        # The state's spawner clocks: one per spawner where they run, none otherwise.
        self.spawner_count = 0 if self.spawners is None else self.spawners.count

    def reset_arenas(self, rngs: list[np.random.Generator]) -> SimState:
        """New episodes' states, one arena per generator, each drawn from its own."""
        return SimState.stack([self.reset_arena(rng) for rng in rngs])

    def reset_arena(self, rng: np.random.Generator) -> SimState:
        """A new episode's state of one arena, drawn from ``rng``."""
        traffic = self.traffic
        fresh = SimState.empty(1, self.agents, self.vehicles, self.spawner_count)
        n, lanes = self.agents, self.road.lane_count
        # Agents: distinct lanes where possible, 30 m apart, at the initial cruise speed.
        agent_lanes = rng.permutation(np.resize(np.arange(lanes), max(n, lanes)))[:n]
        fresh.x_m[0, :n] = -AGENT_SPACING_M * np.arange(n)
        fresh.lane[0, :n] = agent_lanes
        fresh.speed_mps[0, :n] = self.initial_speed_mps
        fresh.desired_speed_mps[0, :n] = self.initial_speed_mps
        fresh.kind[0, :n] = AGENT_KIND
        fresh.active[0, :n] = True

        # Traffic: spread over the kept window with a minimum spacing per lane: the k-th
        # smallest uniform of a lane is shifted by k spacings, so neighbours are at least that
        # far apart. Cars that would crowd an agent are left to spawn later. Ho's free zones
        # and Min et al.'s spawners start from an empty road (a reset destroys every car).
        count = self.traffic_slots if self.entry is None and self.spawners is None else 0
        if self.spawners is not None:
            fresh.spawner_wait_s[0] = self.spawners.first_waits(rng)
        # Empty slots (free_zone, spawners: all of them) move at a speed of their own until a
        # car enters them: the car-following's arithmetic needs one.
        fresh.speed_mps[0, n:] = fresh.desired_speed_mps[0, n:] = self.initial_speed_mps
        if count:
            lo = fresh.x_m[0, :n].min() - traffic.keep_behind_m
            hi = fresh.x_m[0, :n].max() + traffic.keep_ahead_m
            spacing = traffic.vehicle_length_m + 20.0
            lane = rng.integers(0, lanes, size=count)
            u = rng.random(count)
            kind = self.kinds.behaviour_of(rng.random(count))
            speed = self.kinds.desired_speed(kind, rng.random(count))
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
            fresh.own_speed_mps[0, cols] = speed
            fresh.active[0, cols] = x <= hi
        fresh.target_lane[:] = fresh.lane
        fresh.y_m[:] = self.road.centre_y(fresh.lane)
        self._clear_agent_zones(fresh)
        self.tracker.start(fresh, np.ones((1, self.vehicles), dtype=bool))
        return fresh

    def place_agents(
        self, st: SimState, arena: int, slots: np.ndarray, rng: np.random.Generator
    ) -> None:
        """Put agents' cars back on the road of ``arena`` while it goes on.

        Each car is placed, at the initial cruise speed, at the first spot (lanes in a random
        order, then farther back) that keeps IDM-comfortable gaps to everything on the road,
        behind the agents still present. Its tracking starts afresh; its episode counters are
        the caller's.
        """
        n = self.agents
        row = np.array([arena])
        speed = self.initial_speed_mps
        for slot in np.asarray(slots, dtype=np.int64):
            st.active[arena, slot] = False
            present = np.flatnonzero(st.active[arena, :n])
            base = st.x_m[arena, present].min() if present.size else st.x_m[arena, slot]
            lanes = rng.permutation(self.road.lane_count)
            offsets = -AGENT_SPACING_M * np.arange(1, JOIN_STEPS_BACK + 1)
            # Every lane at 30 m back, then every lane at 60 m, ...: the nearest free spot.
            lane = np.tile(lanes, offsets.size)[None, :]
            x = (base + np.repeat(offsets, lanes.size))[None, :]
            ok = self.clearance_ok(
                st,
                row,
                lane,
                x,
                np.full(lane.shape, speed),
                np.full(lane.shape, AGENT_KIND),
                st.active[row],
            )[0]
            # With no comfortable gap anywhere, the last spot tried (farthest back) is used.
            pick = int(np.argmax(ok)) if ok.any() else lane.size - 1
            st.x_m[arena, slot] = x[0, pick]
            st.lane[arena, slot] = st.target_lane[arena, slot] = lane[0, pick]
            st.y_m[arena, slot] = self.road.centre_y(lane[0, pick])
            st.change_progress[arena, slot] = 0.0
            st.speed_mps[arena, slot] = st.desired_speed_mps[arena, slot] = speed
            st.accel_mps2[arena, slot] = 0.0
            st.active[arena, slot] = True
            self.tracker.start_agent(st, arena, int(slot))

    def recycle(self, st: SimState, uniforms: np.ndarray) -> None:
        """Respawn traffic that is out of every agent's range, and fill empty slots: one
        compiled loop (:func:`.spawning_kernels.respawn`); or, with ``traffic.entry =
        "free_zone"`` or ``"spawners"``, take it off the road and let new cars enter by that
        rule."""
        cfg = self.traffic
        n = self.agents
        arenas, vehicles = st.x_m.shape
        if vehicles == n:
            return
        if self.spawners is not None:
            self.spawners.step(st, uniforms)
            return
        if self.entry is not None:
            kept = np.empty((arenas, vehicles - n), dtype=bool)
            kept_in_range(st.x_m, st.active, n, cfg.keep_ahead_m, cfg.keep_behind_m, kept)
            st.active[:, n:] &= kept
            self.entry.enter(st, uniforms)
            return
        spawned = np.zeros((arenas, vehicles), dtype=bool)
        k = self.kinds
        if respawn(
            st.x_m, st.lane, st.target_lane, st.change_progress, st.y_m, st.speed_mps,
            st.desired_speed_mps, st.own_speed_mps, st.accel_mps2, st.kind, st.active, n,
            cfg.keep_ahead_m, cfg.keep_behind_m, uniforms, U_SIDE, U_ANCHOR, U_LANE, U_OFFSET,
            U_BEHAVIOUR, U_SPEED, self._ahead_windows, self._behind_windows, self._lane_centre_y,
            k.behaviour_cdf, k.speed_lo, k.speed_hi, k.half_length, k.headway, k.min_gap,
            k.two_sqrt_ab, cfg.enter_at_leader_speed, SPAWN_SEPARATION_M, spawned,
        ):  # fmt: skip
            self.tracker.start(st, spawned)

    def clearance_ok(
        self,
        st: SimState,
        arena: np.ndarray,
        lane: np.ndarray,
        x: np.ndarray,
        speed: np.ndarray,
        kind: np.ndarray,
        others: np.ndarray,
    ) -> np.ndarray:
        """Whether candidate spots (K, M) keep an IDM-comfortable gap to every other vehicle.

        ``arena`` (K,) rows of ``st``; lane, x, speed, kind (K, M) the candidates; ``others``
        (K, V) the vehicles to keep clear of. A candidate must leave its new leader at least
        its own desired gap, and its new follower at least the follower's desired gap.
        """
        k = self.kinds
        o_x = st.x_m[arena][:, None, :]
        o_lane = st.lane[arena][:, None, :]
        o_target = st.target_lane[arena][:, None, :]
        o_speed = st.speed_mps[arena][:, None, :]
        o_kind = st.kind[arena][:, None, :]
        c_lane, c_x, c_speed, c_kind = (a[..., None] for a in (lane, x, speed, kind))
        shares_lane = ((o_lane == c_lane) | (o_target == c_lane)) & others[:, None, :]
        dx = o_x - c_x
        bodies = k.half_length[o_kind] + k.half_length[c_kind]
        need_ahead = idm_desired_gap(
            c_speed, c_speed - o_speed, k.headway[c_kind], k.min_gap[c_kind], k.two_sqrt_ab[c_kind]
        )
        need_behind = idm_desired_gap(
            o_speed, o_speed - c_speed, k.headway[o_kind], k.min_gap[o_kind], k.two_sqrt_ab[o_kind]
        )
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
        ok = self.clearance_ok(
            st,
            rows,
            st.lane[rows, cols][:, None],
            st.x_m[rows, cols][:, None],
            st.speed_mps[rows, cols][:, None],
            st.kind[rows, cols][:, None],
            others,
        )[:, 0]
        st.active[rows, cols] &= ok
