"""The highway simulation: many independent arenas advanced together by vectorised numpy.

:class:`HighwaySim` is the orchestrator: it builds the parts its configuration chooses and
steps them in order, on one structure-of-arrays state (:mod:`.state`), rows for arenas and
columns for vehicle slots (the agents' cars first, then traffic). One :meth:`HighwaySim.step`
is one decision (:mod:`.decision` holds its order):

1. the actions ask driver assistance for cruise targets and lane changes (:mod:`.actions`,
   :mod:`.assist`; the warnings the agents had are noted for the reward), and traffic now and
   then picks a new desired speed or wants a lane change (:mod:`.traffic.manoeuvres`);
2. ``frames_per_decision`` physics frames run (:mod:`.physics`: car-following, emergency
   braking, traffic's MOBIL lane changes on the first frame, lateral moves, collisions);
3. overtakes are counted (:mod:`.overtakes`) and traffic out of range is recycled around the
   agents, or leaves the road while new cars come on (:mod:`.spawning`);
4. the reward's terms are computed from what happened (:mod:`.rewards`) and the episodes'
   metrics updated (:mod:`.episodes`).

Observations come from the configuration's sensors (:mod:`.sensors`). Each arena owns one
``np.random.Generator``: an arena's episode depends only on its seed and actions, bit for bit,
whatever other arenas share the batch (:mod:`.randomness`).
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from .actions import DasActions
from .assist import DriverWarnings, LaneChangeAssist
from .config import SimConfig
from .decision import Decision, StepResult
from .episodes import EpisodeBook
from .highway_scene import (
    REWARD_TERMS,
    MetaActions,
    SceneDecision,
    ScenePlacement,
    check_scene,
)
from .overtakes import OvertakeTracker
from .physics import Physics, headings
from .randomness import draw_uniforms
from .rewards import Rewards
from .road import Road
from .sensors.base import Scene, Sensor, SensorFacts, SensorSpace
from .snapshot import SimSnapshot
from .spawning import Spawner
from .state import SimState
from .traffic.manoeuvres import RandomManoeuvres
from .vehicles import VehicleKinds

MAX_AGENTS_PER_LANE = 4


@dataclass(frozen=True)
class WorldSnapshot:
    """One arena's road and every vehicle on it now, for whoever shows it (world frames,
    recordings): copies, in the wire's dtypes; vehicle slots in order, agents first."""

    sim_time_s: float
    lane_count: int
    lane_width_m: float
    agent_active: np.ndarray  # (N,) bool: the agents' cars on the road
    x_m: np.ndarray  # (V,) float64
    y_m: np.ndarray  # (V,) float64
    speed_mps: np.ndarray  # (V,) float32
    kind: np.ndarray  # (V,) int8: a traffic behaviour, or AGENT_KIND
    active: np.ndarray  # (V,) bool
    half_length_m: np.ndarray  # (V,) float32
    half_width_m: np.ndarray  # (V,) float32
    agent_heading_rad: np.ndarray  # (N,) float32


class HighwaySim:
    """``num_arenas`` independent highways with ``agents_per_arena`` controlled cars each."""

    def __init__(self, config: SimConfig, num_arenas: int = 1, agents_per_arena: int = 1) -> None:
        most = config.road.lane_count * MAX_AGENTS_PER_LANE
        if num_arenas < 1:
            raise ValueError(f"num_arenas must be >= 1, got {num_arenas}")
        if not 1 <= agents_per_arena <= most:
            raise ValueError(
                f"agents_per_arena must be from 1 to {most} "
                f"({MAX_AGENTS_PER_LANE} per lane), got {agents_per_arena}"
            )
        self.config = config
        self.num_arenas = num_arenas
        self.agents = n = agents_per_arena
        self.traffic_slots = config.traffic.resolved_vehicle_count
        self.vehicles = n + self.traffic_slots
        self.dt = config.episode.physics_dt_s
        self.frames = config.episode.frames_per_decision
        self.decision_period_s = config.episode.decision_period_s

        self.road = road = Road(config.road)
        self.kinds = kinds = VehicleKinds(
            config.traffic, config.ego, self.decision_period_s, self.dt
        )
        self.tracker = OvertakeTracker(
            n,
            self.vehicles,
            config.reward.undo_overtake_when_passed_back,
            every_pass=config.reward.overtakes_counted == "every_pass",
        )
        self.spawner = Spawner(config, kinds, road, n, self.tracker)
        self.episodes = EpisodeBook(config.episode, config.ego, n)
        self.lane_changes = LaneChangeAssist(config.ego, kinds, road.lane_count, n)
        self.actions = DasActions(config.ego, n, self.lane_changes)
        self.warnings = DriverWarnings(config.ego, kinds, self.lane_changes, n)
        self.manoeuvres = RandomManoeuvres(kinds)
        self.physics = Physics(config, kinds, road, n, self.episodes, self.lane_changes.watch)
        self.rewards = Rewards(config.reward)
        # The state holds the agents' warnings (worked out once per decision) where the reward
        # needs them; otherwise a sensor that reads them works them out when it observes.
        self.keeps_warnings = self.rewards.needs_warnings
        self.sensors: list[Sensor] = [
            section.build(config)
            for section in config.sensor_sections().values()
            if section.enabled
        ]
        self.decision: Decision | SceneDecision = Decision(self)
        self.reward_names = self.rewards.names
        if config.highway_scene.enabled:  # highway-env's scene in place of the papers' parts
            check_scene(config)
            self.spawner = ScenePlacement(config, n, self.vehicles, self.tracker)  # type: ignore[assignment]
            self.actions = MetaActions(config, n)  # type: ignore[assignment]
            self.decision = SceneDecision(self)
            self.reward_names = REWARD_TERMS
            self.keeps_warnings = False  # its reward reads none
        self.rngs = [np.random.default_rng() for _ in range(num_arenas)]
        self.state = SimState.empty(num_arenas, n, self.vehicles, self.spawner.spawner_count)
        self._needs_reset = np.ones(num_arenas, dtype=bool)
        self._config_json = json.dumps(dataclasses.asdict(config), sort_keys=True)

    @property
    def reward_terms(self) -> tuple[str, ...]:
        """The names of the reward's terms, in order."""
        return self.reward_names

    def observation_spaces(self) -> dict[str, SensorSpace]:
        """One agent's observation, sensor by sensor (the observation's keys, in order)."""
        return {sensor.key: sensor.space() for sensor in self.sensors}

    def observation_facts(self) -> dict[str, SensorFacts]:
        """Each observation's named columns and reach, sensor by sensor."""
        return {sensor.key: sensor.facts() for sensor in self.sensors}

    # --- episodes and cars ----------------------------------------------------------------------

    def reset(
        self, arenas: np.ndarray | list[int] | None = None, seeds: list[int | None] | None = None
    ) -> None:
        """Start new episodes in ``arenas`` (all by default).

        A seed re-creates that arena's generator; None continues its stream, so that a
        sequence of episodes after one seeded reset is reproducible too.
        """
        rows = np.arange(self.num_arenas) if arenas is None else np.asarray(arenas, dtype=np.int64)
        if seeds is not None and len(seeds) != rows.size:
            raise ValueError(f"expected {rows.size} seeds (one per arena reset), got {len(seeds)}")
        for i, row in enumerate(rows):
            seed = None if seeds is None else seeds[i]
            if seed is not None:
                self.rngs[row] = np.random.default_rng(seed)
        if rows.size:
            fresh = self.spawner.reset_arenas([self.rngs[row] for row in rows])
            self._note_warnings(fresh)
            self.state.assign(rows, fresh)
        self._needs_reset[rows] = False

    def agents_present(self) -> np.ndarray:
        """(A, N) bool: which agent slots have a car on the road."""
        return self.state.active[:, : self.agents].copy()

    def remove_agents(self, arena: int, slots: list[int] | np.ndarray) -> None:
        """Take agents' cars off the road of ``arena`` (a shared arena's trainer left).

        A removed car is invisible to sensors and other cars, cannot collide and anchors no
        traffic; its slot keeps stepping unseen until it is restored or respawned.
        """
        slots = np.asarray(slots, dtype=np.int64)
        if slots.size:  # (a reset of an arena alone on its road removes none)
            self.state.active[arena, slots] = False
            self.state_written([arena])

    def restore_agents(self, arena: int, slots: list[int] | np.ndarray) -> None:
        """Put removed cars back where the arena's last reset placed them (right after it)."""
        self.state.active[arena, np.asarray(slots, dtype=np.int64)] = True
        self.state_written([arena])

    def respawn_agents(self, arena: int, slots: list[int] | np.ndarray) -> None:
        """Start new episodes for some agents of ``arena`` while the road goes on: each car
        is placed behind the others, clear of everyone (:meth:`Spawner.place_agents`)."""
        slots = np.asarray(slots, dtype=np.int64)
        self.spawner.place_agents(self.state, arena, slots, self.rngs[arena])
        for slot in slots:
            self.episodes.restart(self.state, arena, int(slot))
        self.state_written([arena])

    def _note_warnings(self, st: SimState) -> None:
        """Work out the warnings the agents of ``st`` are shown now, where the reward needs
        them: with their next actions it looks back at them (:class:`.decision.Decision`), and
        the observation reads the same ones rather than working them out again."""
        if self.keeps_warnings:
            st.warnings[:] = self.warnings.compute(st)

    def state_written(self, arenas: np.ndarray | list[int] | None = None) -> None:
        """Call after writing cars' positions, lanes or speeds into :attr:`state` by hand (a
        scripted scene): what the simulation keeps from them, the warnings the agents are
        shown, is worked out again for ``arenas`` (all by default)."""
        if self.keeps_warnings:
            rows = np.arange(self.num_arenas) if arenas is None else np.asarray(arenas, np.int64)
            self.state.warnings[rows] = self.warnings.compute(self.state.select(rows))

    # --- a moment kept ------------------------------------------------------------------------

    def snapshot(self) -> SimSnapshot:
        """Every arena as it is now, generators included (:mod:`.snapshot`)."""
        return SimSnapshot.take(self._config_json, self.state, self.rngs, self._needs_reset)

    def restore(self, snapshot: SimSnapshot) -> None:
        """Put every arena back as ``snapshot`` took it: the next steps are those that
        followed it (raises :class:`~.snapshot.SnapshotMismatch` for another configuration or
        size, changing nothing)."""
        snapshot.put_back(self._config_json, self.state, self.rngs, self._needs_reset)

    # --- stepping -------------------------------------------------------------------------------

    def step(self, actions: np.ndarray, arenas: np.ndarray | None = None) -> StepResult:
        """Advance one decision. ``actions`` is (A, N) ints for the stepped arenas.

        ``arenas`` selects a subset to step (the others do not move and use no randomness);
        by default all arenas step.
        """
        rows = np.arange(self.num_arenas) if arenas is None else np.asarray(arenas, dtype=np.int64)
        actions = self.actions.check(actions, (rows.size, self.agents))
        if self._needs_reset[rows].any():
            raise RuntimeError(
                f"arenas {rows[self._needs_reset[rows]].tolist()} must be reset "
                "before they can step"
            )
        uniforms = (
            draw_uniforms(self.rngs, rows, self.vehicles) if self.decision.uses_uniforms else None
        )
        return self.decision.advance(
            self.state, actions, uniforms, rows=None if arenas is None else rows
        )

    # --- what agents see ------------------------------------------------------------------------

    def observe(self) -> dict[str, np.ndarray]:
        """Every agent's observation, sensor by sensor: (A, N, *shape) each."""
        scene = Scene(
            self.state,
            self.kinds,
            self.road,
            self.agents,
            self.warnings,
            warnings=self.state.warnings if self.keeps_warnings else None,
            vehicle_headings=self.vehicle_headings,
        )
        return {sensor.key: sensor.observe(scene) for sensor in self.sensors}

    def world_snapshot(self, arena: int) -> WorldSnapshot:
        """Arena ``arena``'s road and vehicles now (:class:`WorldSnapshot`)."""
        st, n = self.state, self.agents
        body = np.clip(st.kind[arena], 0, AGENT_KIND)
        heading = self.vehicle_headings()[arena, :n]
        return WorldSnapshot(
            sim_time_s=float(st.frame[arena] * self.dt),
            lane_count=self.road.lane_count,
            lane_width_m=float(self.road.lane_width_m),
            agent_active=st.active[arena, :n].copy(),
            x_m=st.x_m[arena].astype(np.float64),
            y_m=st.y_m[arena].astype(np.float64),
            speed_mps=st.speed_mps[arena].astype(np.float32),
            kind=st.kind[arena].astype(np.int8),
            active=st.active[arena].copy(),
            half_length_m=self.kinds.half_length[body].astype(np.float32),
            half_width_m=self.kinds.half_width[body].astype(np.float32),
            agent_heading_rad=heading.astype(np.float32),
        )

    def vehicle_headings(self) -> np.ndarray:
        """(A, V) every car's heading now, radians from the road's direction, left positive."""
        if self.config.highway_scene.enabled:
            return self.state.heading_rad
        return headings(self.state, self.kinds, self.road.lane_width_m, self.vehicles)

    def action_mask(self) -> np.ndarray:
        """(A, N, actions) int8: 1 where the action can be taken now."""
        return self.actions.mask(self.state)

    def metrics(self) -> dict[str, np.ndarray]:
        """Each agent's episode so far: the papers' metrics, (A, N) per name."""
        table = self.metrics_table()
        return {name: table[..., i] for i, name in enumerate(self.metric_fields)}

    @property
    def metric_fields(self) -> tuple[str, ...]:
        """The metrics' names, in the columns of :meth:`metrics_table`: the papers'
        (METRIC_FIELDS), and the lane-change watch's where it runs (WATCH_METRICS)."""
        return self.episodes.fields

    def metrics_table(self) -> np.ndarray:
        """(A, N, metric fields) float64: :meth:`metrics` as one table (what travels)."""
        return self.episodes.metrics_table(self.state)
