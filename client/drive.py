"""``overtake-drive``: drive baseline policies through episodes and print the papers' metrics.

Runs the vector environment (one arena per episode, all stepped together) with the rule-based
or the random driver, in-process or (``--connect``) on a simulator server over Zenoh, and
prints one row per episode and the mean and spread of each metric.
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from overtake.protocol.transport import SecurityConfig
from overtake.protocol.vocabulary import METRIC_FIELDS

from .commands import UsageError, run_command
from .episodes import (
    baseline_policy,
    make_vector_env,
    metric_summary,
    metric_table,
    parse_overrides,
    run_episodes,
)


@dataclass(frozen=True)
class DriveConfig:
    """Drive a baseline policy through episodes of a preset and report the metrics."""

    policy: Literal["rule", "random", "idle", "planner"] = "rule"
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


def main(config: DriveConfig) -> dict[str, dict[str, float]]:
    """Drive the episodes; returns {metric: {"mean": .., "std": ..}} and prints the table."""
    if config.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {config.episodes}")
    overrides = parse_overrides(config.set)
    if config.traffic is not None:
        overrides["traffic.density"] = config.traffic
    if config.max_decisions is not None:
        overrides["episode.max_decisions"] = config.max_decisions
    envs = make_vector_env(
        config.preset, overrides, config.episodes, config.connect, config.security
    )
    try:
        act = baseline_policy(
            config.policy, envs.unwrapped.sim_config, config.seed, config.episodes, envs
        )
        rows, decisions, elapsed = run_episodes(envs, act, config.episodes, config.seed)
    finally:
        envs.close()

    table = metric_table(rows)
    summary = metric_summary(rows)
    _print_table(config, table, summary, decisions, elapsed)
    if config.json_out is not None:
        config.json_out.parent.mkdir(parents=True, exist_ok=True)
        config.json_out.write_text(
            json.dumps(
                {
                    "policy": config.policy,
                    "preset": config.preset,
                    "seed": config.seed,
                    "overrides": overrides,
                    "episodes": [dict(zip(METRIC_FIELDS, r)) for r in table.tolist()],
                    "summary": summary,
                },
                indent=2,
            )
        )
    return summary


def _print_table(
    config: DriveConfig,
    table: np.ndarray,
    summary: dict[str, dict[str, float]],
    decisions: int,
    elapsed: float,
) -> None:
    headers = (
        "episode",
        "speed km/h",
        "lane chg",
        "overtakes",
        "collisions",
        "e-brakes",
        "distance m",
        "return",
        "decisions",
    )
    widths = [max(9, len(h)) for h in headers]
    line = "  ".join(h.rjust(w) for h, w in zip(headers, widths))
    where = "in-process" if config.connect is None else f"on {config.connect}"
    print(
        f"policy={config.policy} preset={config.preset} episodes={config.episodes} "
        f"seed={config.seed} ({where})"
    )
    print(line)
    print("-" * len(line))
    for i, row in enumerate(table):
        cells = [str(config.seed + i)] + [
            f"{v:.1f}" if j in (0, 5, 6) else f"{v:.0f}" for j, v in enumerate(row)
        ]
        print("  ".join(c.rjust(w) for c, w in zip(cells, widths)))
    print("-" * len(line))
    means = ["mean"] + [f"{summary[n]['mean']:.1f}" for n in METRIC_FIELDS]
    spreads = ["std"] + [f"{summary[n]['std']:.1f}" for n in METRIC_FIELDS]
    for cells in (means, spreads):
        print("  ".join(c.rjust(w) for c, w in zip(cells, widths)))
    print(
        f"{decisions} decisions in {elapsed:.1f} s ({decisions / max(elapsed, 1e-9):.0f} "
        "decisions/s)",
        file=sys.stderr,
    )


def cli(argv: list[str] | None = None) -> None:
    import tyro

    config = tyro.cli(DriveConfig, args=argv, config=(tyro.conf.OmitArgPrefixes,))
    run_command("overtake-drive", main, config)


if __name__ == "__main__":
    cli()
