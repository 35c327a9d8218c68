"""``overtake-drive``: drive baseline policies through episodes and print the papers' metrics.

Runs the vector environment (one arena per episode, all stepped together) with the rule-based
or the random driver, in-process or (``--connect``) on a simulator server over Zenoh, and
prints one row per episode and the mean and spread of each metric.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import gymnasium as gym
import numpy as np

from overtake.protocol import (HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, ProtocolError,
                               register_environments)

from overtake.protocol.transport import SecurityConfig
from overtake.protocol.vocabulary import METRIC_FIELDS

from .drivers import RandomDriver, RuleDriver, RuleDriverConfig
from .remote import RemoteConfig

METRIC_COLUMNS = METRIC_FIELDS


@dataclass(frozen=True)
class DriveConfig:
    """Drive a baseline policy through episodes of a preset and report the metrics."""

    policy: Literal["rule", "random"] = "rule"
    """which driver acts"""
    preset: str = "min2018"
    episodes: int = 4
    """episodes to drive, all at once (one arena each)"""
    seed: int = 0
    """episode i uses seed + i"""
    traffic: Literal["light", "medium", "heavy"] | None = None
    """traffic density (Ho's Table 4: up to 20 / 40 / 60 cars); None keeps the preset's"""
    max_decisions: int | None = None
    """episode length in decisions (0.4 s each by default); None keeps the preset's"""
    set: tuple[str, ...] = field(default_factory=tuple)
    """more overrides as dotted.name=value (value read as JSON, else as a string)"""
    json_out: Path | None = None
    """also write the table as JSON here"""
    connect: str | None = None
    """a simulator server's (or router's) Zenoh endpoint, e.g. tcp/127.0.0.1:7447; None runs
    the simulator in this process"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates for --connect"""


def parse_overrides(items: tuple[str, ...]) -> dict[str, object]:
    overrides: dict[str, object] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"--set expects dotted.name=value, got {item!r}")
        try:
            overrides[name] = json.loads(text)
        except json.JSONDecodeError:
            overrides[name] = text
    return overrides


def make_vector_env(preset: str, overrides: dict[str, Any], num_envs: int,
                    connect: str | None, security: SecurityConfig | None = None) -> Any:
    """``num_envs`` arenas of ``preset`` as one vector environment: in this process, or on a
    simulator server reached at ``connect`` (with ``security``'s credentials and
    certificates)."""
    register_environments()
    if connect is None:
        return gym.make_vec(HIGHWAY_ENV_ID, num_envs=num_envs,
                            vectorization_mode="vector_entry_point", preset=preset,
                            overrides=overrides)
    remote = RemoteConfig(connect=(connect,), security=security or SecurityConfig())
    return gym.make_vec(REMOTE_HIGHWAY_ENV_ID, num_envs=num_envs,
                        vectorization_mode="vector_entry_point", preset=preset,
                        overrides=overrides, remote=remote)


def metric_summary(rows: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Mean and spread of each metric over the episodes."""
    table = np.array([[row[name] for name in METRIC_COLUMNS] for row in rows])
    return {name: {"mean": float(table[:, j].mean()), "std": float(table[:, j].std())}
            for j, name in enumerate(METRIC_COLUMNS)}


Policy = Callable[[dict[str, np.ndarray], dict[str, Any], np.ndarray], np.ndarray]


def run_episodes(envs: Any, act: Policy, episodes: int, seed: int
                 ) -> tuple[list[dict[str, float]], int, float]:
    """One episode per environment of ``envs`` (seeds seed, seed + 1, ...), all stepped
    together; returns each episode's metrics, the decisions taken and the seconds it took.

    ``act(obs, info, starting)`` returns the actions; ``starting`` marks the environments whose
    observation is the first of an episode (a policy that stacks frames restarts there).
    """
    obs, info = envs.reset(seed=seed)
    starting = np.ones(episodes, dtype=bool)
    resetting = np.zeros(episodes, dtype=bool)  # ended: the next step is their autoreset
    rows: list[dict[str, float] | None] = [None] * episodes
    started = time.perf_counter()
    decisions = 0
    while any(row is None for row in rows):
        actions = act(obs, info, starting)
        obs, _, terminated, truncated, info = envs.step(actions)
        decisions += episodes
        ended = terminated | truncated
        for i in np.flatnonzero(ended & info.get("_metrics", False)):
            if rows[i] is None:
                rows[i] = {name: float(info["metrics"][name][i]) for name in METRIC_COLUMNS}
        # Gymnasium's next-step autoreset: an env that ended is reset by the following step,
        # whose observation is then the first of the new episode.
        starting, resetting = resetting, ended
    return [row for row in rows if row is not None], decisions, time.perf_counter() - started


def baseline_policy(policy: str, sim_config: dict[str, Any], seed: int, num_envs: int
                    ) -> Policy:
    """The rule-based driver (tuned to the simulator's configuration) or random, as a policy
    for :func:`run_episodes`."""
    if policy == "rule":
        if not sim_config["lidar"]["enabled"]:
            raise SystemExit("the rule-based driver reads the LIDAR: keep lidar.enabled true")
        driver: RuleDriver | RandomDriver = RuleDriver(
            RuleDriverConfig(cruise_max_kmh=sim_config["ego"]["cruise_max_kmh"],
                             lane_width_m=sim_config["road"]["lane_width_m"]),
            ray_count=sim_config["lidar"]["ray_count"],
            max_range_m=sim_config["lidar"]["max_range_m"])
    elif policy == "random":
        driver = RandomDriver(seed)
    else:
        raise SystemExit(f"unknown baseline policy {policy!r}: rule or random")

    def act(obs: dict[str, np.ndarray], info: dict[str, Any], _starting: np.ndarray
            ) -> np.ndarray:
        lidar = obs.get("lidar", np.zeros((num_envs, 1), dtype=np.float32))
        return driver.act(lidar, obs["ego"], info["action_mask"])
    return act


def main(config: DriveConfig) -> dict[str, dict[str, float]]:
    """Drive the episodes; returns {metric: {"mean": .., "std": ..}} and prints the table."""
    if config.episodes < 1:
        raise SystemExit(f"--episodes must be >= 1, got {config.episodes}")
    overrides = parse_overrides(config.set)
    if config.traffic is not None:
        overrides["traffic.density"] = config.traffic
    if config.max_decisions is not None:
        overrides["episode.max_decisions"] = config.max_decisions
    envs = make_vector_env(config.preset, overrides, config.episodes, config.connect,
                           config.security)
    act = baseline_policy(config.policy, envs.unwrapped.sim_config, config.seed,
                          config.episodes)
    rows, decisions, elapsed = run_episodes(envs, act, config.episodes, config.seed)
    envs.close()

    table = np.array([[row[name] for name in METRIC_COLUMNS] for row in rows])
    summary = metric_summary(rows)
    _print_table(config, table, summary, decisions, elapsed)
    if config.json_out is not None:
        config.json_out.parent.mkdir(parents=True, exist_ok=True)
        config.json_out.write_text(json.dumps(
            {"policy": config.policy, "preset": config.preset, "seed": config.seed,
             "overrides": overrides,
             "episodes": [dict(zip(METRIC_COLUMNS, r)) for r in table.tolist()],
             "summary": summary}, indent=2))
    return summary


def _print_table(config: DriveConfig, table: np.ndarray, summary: dict[str, dict[str, float]],
                 decisions: int, elapsed: float) -> None:
    headers = ("episode", "speed km/h", "lane chg", "overtakes", "collisions", "e-brakes",
               "distance m", "return", "decisions")
    widths = [max(9, len(h)) for h in headers]
    line = "  ".join(h.rjust(w) for h, w in zip(headers, widths))
    where = "in-process" if config.connect is None else f"on {config.connect}"
    print(f"policy={config.policy} preset={config.preset} episodes={config.episodes} "
          f"seed={config.seed} ({where})")
    print(line)
    print("-" * len(line))
    for i, row in enumerate(table):
        cells = [str(config.seed + i)] + [f"{v:.1f}" if j in (0, 5, 6) else f"{v:.0f}"
                                           for j, v in enumerate(row)]
        print("  ".join(c.rjust(w) for c, w in zip(cells, widths)))
    print("-" * len(line))
    means = ["mean"] + [f"{summary[n]['mean']:.1f}" for n in METRIC_COLUMNS]
    spreads = ["std"] + [f"{summary[n]['std']:.1f}" for n in METRIC_COLUMNS]
    for cells in (means, spreads):
        print("  ".join(c.rjust(w) for c, w in zip(cells, widths)))
    print(f"{decisions} decisions in {elapsed:.1f} s ({decisions / max(elapsed, 1e-9):.0f} "
          "decisions/s)", file=sys.stderr)


def cli() -> None:
    import tyro

    try:
        main(tyro.cli(DriveConfig, config=(tyro.conf.OmitArgPrefixes,)))
    except ProtocolError as error:
        sys.exit(f"overtake-drive: {error}")


if __name__ == "__main__":
    cli()
