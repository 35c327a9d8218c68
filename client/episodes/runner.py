"""Episode stepping and metric tables: what the commands that drive episodes share.

A policy stepping one episode per environment of a vector environment to its end (on the wall
clock if asked), the reference policies, and the papers' metrics of those episodes (the columns
of :data:`overtake.protocol.vocabulary.METRIC_FIELDS`) with their mean and spread. Which
simulator and where is :mod:`.scenario`; a command's whole run of episodes (open, drive,
record, close) is :mod:`.session`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from overtake.cli import UsageError
from overtake.client.policies.drivers import (
    GridRuleDriver,
    GridRuleDriverConfig,
    MapRuleDriver,
    MapRuleDriverConfig,
    RandomDriver,
    RuleDriver,
    RuleDriverConfig,
)
from overtake.client.policies.shield import SHIELD_OVERRIDES
from overtake.envs.faces import VectorFace
from overtake.protocol.messages import BehaviourSpec
from overtake.protocol.vocabulary import (
    EGO_DRIVER_IDM,
    EGO_DRIVER_SETTING,
    HIGHWAY_SCENE_PRESETS,
    HIGHWAY_SCENE_SETTING,
    KEEP,
    METRIC_FIELDS,
    WATCH_METRICS,
)

Policy = Callable[[dict[str, np.ndarray], dict[str, Any], np.ndarray], np.ndarray]
"""``act(obs, info, starting)`` -> actions, for :func:`run_episodes`."""


def metric_table(rows: list[dict[str, float]]) -> np.ndarray:
    """The episodes' metrics as an (episodes, metrics) array, columns in METRIC_FIELDS order."""
    return np.array([[row[name] for name in METRIC_FIELDS] for row in rows])


def metric_summary(rows: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Mean and spread of each metric over the episodes: the papers' metrics, and those the
    simulator or the policy added to every episode (WATCH_METRICS where lane changes are
    watched, shield_overrides behind the safety shield)."""
    added = (*WATCH_METRICS, SHIELD_OVERRIDES)
    names = [*METRIC_FIELDS, *(n for n in added if rows and all(n in r for r in rows))]
    table = np.array([[row[name] for name in names] for row in rows])
    return {
        name: {"mean": float(table[:, j].mean()), "std": float(table[:, j].std())}
        for j, name in enumerate(names)
    }


@dataclass
class RealTime:
    """The wall clock that :func:`run_episodes` drives the simulator on, and what it saw.

    The simulator advances every ``period_s`` of wall time, as a car on the road would: the
    observation of one decision arrives at a tick, and the action must be ready by the next.
    An action that is not ready then is late: the simulator has already advanced with the
    default action (keep) at every tick that passed, the late action is dropped, and the policy
    answers the newest observation next. ``late`` counts the decisions (per environment) the
    simulator took without the policy; ``latencies_s`` holds each policy call's wall time.
    """

    period_s: float
    decisions: int = 0
    late: int = 0
    latencies_s: list[float] = field(default_factory=list)

    def percentile_ms(self, q: float) -> float:
        return float(np.percentile(self.latencies_s, q) * 1e3) if self.latencies_s else 0.0


@dataclass(frozen=True)
class VectorStep:
    """One step of a vector environment: the ``actions`` sent and what the step answered."""

    actions: np.ndarray
    obs: dict[str, np.ndarray]
    reward: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    info: dict[str, Any]

    @property
    def ended(self) -> np.ndarray:
        return self.terminated | self.truncated


class EpisodeWatcher(Protocol):
    """Sees every step :func:`run_episodes` takes (an episode record, a Rerun recording)."""

    def started(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        """The environments were reset: ``obs`` and ``info`` are the episodes' first."""

    def stepped(self, step: VectorStep) -> None:
        """A step was taken (``step``: its actions and what it answered)."""


@dataclass(frozen=True)
class EpisodesRun:
    """What :func:`drive_until` did: each episode's metrics (None where it had not ended when
    asked to stop), the decisions taken and the seconds it took."""

    rows: list[dict[str, float] | None]
    decisions: int
    elapsed_s: float

    @property
    def finished(self) -> tuple[int, ...]:
        """The episodes that ended, in order."""
        return tuple(i for i, row in enumerate(self.rows) if row is not None)

    @property
    def partial(self) -> bool:
        """Whether it was stopped before every episode ended."""
        return len(self.finished) < len(self.rows)


def run_episodes(
    envs: VectorFace,
    act: Policy,
    episodes: int,
    seed: int | Sequence[int],
    realtime: RealTime | None = None,
    watchers: Sequence[EpisodeWatcher] = (),
) -> tuple[list[dict[str, float]], int, float]:
    """One episode per environment of ``envs`` (seeds seed, seed + 1, ..., or each its own
    of a sequence), all stepped together; returns each episode's metrics, the decisions taken
    and the seconds it took (:func:`drive_until`, never stopped)."""
    run = drive_until(envs, act, episodes, seed, realtime, watchers)
    return [row for row in run.rows if row is not None], run.decisions, run.elapsed_s


def drive_until(
    envs: VectorFace,
    act: Policy,
    episodes: int,
    seed: int | Sequence[int],
    realtime: RealTime | None = None,
    watchers: Sequence[EpisodeWatcher] = (),
    stop: threading.Event | None = None,
) -> EpisodesRun:
    """:func:`run_episodes`, until every episode ended or ``stop`` is set (checked before each
    decision: the episodes that ended by then are the run's, the others are left out).

    ``act(obs, info, starting)`` returns the actions; ``starting`` marks the environments whose
    observation is the first of an episode (a policy that stacks frames restarts there).
    ``realtime``: advance on the wall clock instead of waiting for the policy (see
    :class:`RealTime`). ``watchers`` see the reset and every step (the episodes' first are
    the ones that count; each environment steps on, into episodes of its own, until all end).
    """
    # A policy may add columns of its own to each episode's row (the shield's overrides).
    extras = getattr(act, "episode_extras", None)
    obs, info = envs.reset(seed=seed if isinstance(seed, int) else list(seed))
    for watcher in watchers:
        watcher.started(obs, info)
    starting = np.ones(episodes, dtype=bool)
    resetting = np.zeros(episodes, dtype=bool)  # ended: the next step is their autoreset
    rows: list[dict[str, float] | None] = [None] * episodes
    started = time.perf_counter()
    decisions = 0
    keep = np.zeros(episodes, dtype=np.int64)
    next_tick = started + (realtime.period_s if realtime else 0.0)

    def step(actions: np.ndarray) -> None:
        nonlocal obs, info, starting, resetting, decisions
        obs, reward, terminated, truncated, info = envs.step(actions)
        if watchers:
            taken = VectorStep(actions, obs, reward, terminated, truncated, info)
            for watcher in watchers:
                watcher.stepped(taken)
        decisions += episodes
        ended = terminated | truncated
        for i in np.flatnonzero(ended & info.get("_metrics", False)):
            if rows[i] is None:
                # The papers' metrics, and any the simulator adds (WATCH_METRICS).
                row = {name: float(value[i]) for name, value in info["metrics"].items()}
                rows[i] = row if extras is None else {**row, **extras(int(i))}
        # Gymnasium's next-step autoreset: an env that ended is reset by the following step,
        # whose observation is then the first of the new episode.
        starting, resetting = resetting, ended

    while any(row is None for row in rows) and not (stop is not None and stop.is_set()):
        asked = time.perf_counter()
        actions = act(obs, info, starting)
        if realtime is None:
            step(actions)
            continue
        answered = time.perf_counter()
        realtime.latencies_s.append(answered - asked)
        if answered <= next_tick:
            time.sleep(next_tick - answered)  # pacing to the wall clock, not synchronisation
            step(actions)
            realtime.decisions += episodes
        else:
            # Every tick that passed while the policy thought went by with keep.
            missed = int((answered - next_tick) // realtime.period_s) + 1
            for _ in range(missed):
                if all(row is not None for row in rows):
                    break
                step(keep)
                realtime.decisions += episodes
                realtime.late += episodes
            next_tick += (missed - 1) * realtime.period_s
        next_tick += realtime.period_s
    return EpisodesRun(rows, decisions, time.perf_counter() - started)


# The reference policies ``baseline_policy`` builds.
BASELINE_POLICIES = ("rule", "random", "idle", "planner", "idm")


def policy_settings(
    policy: str | None, preset: str, overrides: Mapping[str, Any]
) -> dict[str, Any]:
    """The simulator settings ``policy`` drives under on ``preset`` (with ``overrides``), to
    add to the scenario's: ``idm`` is the scene's own IDM + MOBIL car (highway-env's scenes
    only: anywhere else a :class:`UsageError` in one line); the others need none."""
    if policy != "idm":
        return {}
    if preset not in HIGHWAY_SCENE_PRESETS and overrides.get(HIGHWAY_SCENE_SETTING) is not True:
        raise UsageError(
            f"--policy idm is highway-env's IDM + MOBIL car, which drives the highway scenes "
            f"only (presets {', '.join(HIGHWAY_SCENE_PRESETS)}), not preset {preset}: drive "
            f"{preset} with --policy rule, random, idle or planner"
        )
    return {EGO_DRIVER_SETTING: EGO_DRIVER_IDM}


def baseline_policy(
    policy: str, spec: BehaviourSpec, seed: int, num_envs: int, envs: VectorFace | None = None
) -> Policy:
    """A reference policy for :func:`run_episodes`:

    - ``rule``: the rule-based driver that reads what the preset observes (the LIDAR and ego
      vector, Ho's grid or Fayjie et al.'s LIDAR map: :mod:`overtake.client.policies.drivers`),
      tuned to the environment's behaviour spec (its road, car and the observations' reach);
    - ``random``: uniformly random among the allowed actions;
    - ``idle``: never acts (action 0 throughout): the floor any policy should beat;
    - ``planner``: the simulator's privileged planner, which reads the true state of every
      car: an upper reference, not a policy anyone trains; it needs ``envs``, the in-process
      vector environment being driven (a remote simulator keeps its state to itself);
    - ``idm``: highway-env's scenes' own IDM + MOBIL car at the wheel, in the simulator (the
      setting :func:`policy_settings` adds, in process or remote): what is sent is unread
      (keep), and ``info["action_applied"]`` says the meta-action each decision stands for.
      Its simulator is opened with that setting by the caller (the spec does not say it).
    """
    if policy == "idle":
        return lambda _obs, _info, _starting: np.zeros(num_envs, dtype=np.int64)
    if policy == "idm":
        return lambda _obs, _info, _starting: np.full(num_envs, KEEP, dtype=np.int64)
    if policy == "planner":
        road = envs.simulator.road if envs is not None else None
        if road is None:
            raise UsageError(
                "the planner reads the simulator's true state: run it in-process (without "
                "--connect)"
            )
        plan = road.planner_actions
        return lambda _obs, _info, _starting: np.asarray(plan(), dtype=np.int64)
    if policy == "random":
        randomly = RandomDriver(seed)
        return lambda _obs, info, _starting: randomly.act(None, None, info["action_mask"])
    if policy != "rule":
        raise UsageError(
            f"unknown baseline policy {policy!r}: one of {', '.join(BASELINE_POLICIES)}"
        )
    return _rule_driver(spec)


def _rule_driver(spec: BehaviourSpec) -> Policy:
    """The rule-based driver for what ``spec``'s agents observe."""
    road, car = spec.road, spec.car
    assert road is not None and car is not None  # a 1.5 spec (remote_gym refuses older ones)
    if spec.has("lidar") and spec.has("ego"):
        lidar, ego = spec.observation("lidar"), spec.observation("ego")
        assert lidar.reach is not None
        driver = RuleDriver(
            RuleDriverConfig(cruise_max_kmh=car.max_speed_kmh, lane_width_m=road.lane_width_m),
            ray_count=lidar.shape[0],
            max_range_m=lidar.reach.range_m,
            ego_fields=ego.columns,
        )
        return lambda obs, info, _starting: driver.act(
            obs["lidar"], obs["ego"], info["action_mask"]
        )
    if spec.has("grid"):
        grid = spec.observation("grid")
        assert grid.reach is not None
        if grid.shape[1] != 3:
            raise UsageError(
                "the rule-based driver on the occupancy grid reads the lanes either side of its "
                f"own (grid.side_lanes = 1), got grid.side_lanes = {(grid.shape[1] - 1) // 2}"
            )
        on_grid = GridRuleDriver(
            GridRuleDriverConfig(half_length_m=car.length_m / 2),
            ahead_m=grid.reach.ahead_m,
            behind_m=grid.reach.behind_m,
            cells=grid.shape[0],
        )
        return lambda obs, info, _starting: on_grid.act(obs["grid"], info["action_mask"])
    if spec.has("lidar_map"):
        lidar_map = spec.observation("lidar_map")
        assert lidar_map.reach is not None
        on_map = MapRuleDriver(
            MapRuleDriverConfig(lane_width_m=road.lane_width_m, half_length_m=car.length_m / 2),
            cells=lidar_map.shape[0],
            ahead_m=lidar_map.reach.ahead_m,
            behind_m=lidar_map.reach.behind_m,
            half_width_m=lidar_map.reach.side_m,
        )
        return lambda obs, info, _starting: on_map.act(obs["lidar_map"], info["action_mask"])
    if spec.preset in HIGHWAY_SCENE_PRESETS:
        raise UsageError(
            f"the rule-based driver reads the LIDAR and the ego vector, the occupancy grid or "
            f"the LIDAR map, and preset {spec.preset} observes highway-env's Kinematics table: "
            f"drive it with --policy idm (highway-env's IDM + MOBIL car), random or idle instead"
        )
    raise UsageError(
        "the rule-based driver reads the LIDAR and the ego vector (lidar.enabled, "
        "ego_vector.enabled), the occupancy grid (grid.enabled) or the LIDAR map "
        "(lidar_map.enabled): this configuration has none of them; drive it with --policy "
        "idle, random or planner (in process) instead, or idm on highway-env's scenes "
        f"(presets {', '.join(HIGHWAY_SCENE_PRESETS)})"
    )


def say_stopping_episodes(name: str) -> None:
    """What overtake-drive and overtake-eval say at the first Ctrl-C or SIGTERM."""
    logging.getLogger("overtake").warning(
        "%s: stopping after the decision under way; the table and --json-out hold the "
        "episodes that ended (send it again to stop at once)",
        name,
    )
