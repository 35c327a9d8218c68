"""``overtake-drive``: drive baseline policies through episodes and print the papers' metrics.

Runs the vector environment (one arena per episode, all stepped together) with the rule-based
or the random driver, in-process or (``--connect``) on a simulator server over Zenoh, and
prints one row per episode and the mean and spread of each metric.
"""

from __future__ import annotations

import functools
import json
import logging
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np

from overtake.cli import Command, CommandError, Output, UsageError
from overtake.cli.options import unset
from overtake.client.episodes.records import PolicySource
from overtake.client.episodes.runner import (
    baseline_policy,
    metric_summary,
    metric_table,
    policy_settings,
    say_stopping_episodes,
)
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.episodes.session import Driver, Episodes, Keeping, RealTime, drive_episodes
from overtake.client.policies.shield import SHIELD_OVERRIDES
from overtake.envs.faces import VectorFace
from overtake.protocol.vocabulary import METRIC_FIELDS, WATCH_SETTING

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriveConfig:
    """Drive a baseline policy through episodes of a preset and report the metrics. The
    simulator and where it runs are the scenario's and where's options (--preset unset: the
    ONNX model's own with --onnx, else min2018)."""

    scenario: Scenario = field(default_factory=Scenario)
    """the simulator: a preset, its traffic, episode length and overrides"""
    where: Where = field(default_factory=Where)
    """where the simulator runs: in this process, or on a server (--connect)"""

    policy: Literal["rule", "random", "idle", "planner", "idm"] = "rule"
    """which driver acts (unless --onnx is given): the rule-based driver, random, idle (never
    acts), the privileged planner (in process) or idm (highway-env's IDM + MOBIL car at the
    wheel; presets highway-fast and highway)"""
    onnx: Annotated[Path | None, unset("PATH")] = None
    """drive a policy exported by overtake-export (ONNX Runtime, no PyTorch) instead of
    --policy"""
    shield: Annotated[bool | None, unset("{True,False}")] = None
    """with --onnx: the safety shield in front of the model (overtake.client.policies.shield);
    unset: where the model was trained with it"""
    realtime: bool = False
    """advance the simulator on the wall clock, one decision period (0.4 s for min2018) per
    decision: an action not ready in time is late (the car keeps its lane and speed), and the
    latency of every decision is reported"""
    episodes: int = 4
    """episodes to drive, all at once (one arena each)"""
    seed: int = 0
    """episode i uses seed + i"""
    json_out: Annotated[Path | None, unset("PATH")] = None
    """also write the table as JSON here"""
    episodes_out: Annotated[Path | None, unset("PATH")] = None
    """keep every episode as a record in this folder (<policy>.jsonl), for overtake-replay"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before any episode is driven)."""
        return (
            Output("--json-out", self.json_out),
            Output("--episodes-out", self.episodes_out, folder=True),
        )


@dataclass(frozen=True)
class DriveSetup:
    """What a drive runs: the preset, the overrides a model brings, the sensors and the ego
    vector's fields it reads."""

    preset: str
    base: dict[str, Any]  # overrides beneath the scenario's
    observations: tuple[str, ...]  # the sensors to render (none named: every one)
    ego_fields: tuple[str, ...] = ()  # the ego vector's fields (none named: the preset's)


def what_to_drive(config: DriveConfig) -> DriveSetup:
    """The preset and overrides of ``config``'s drive: an ONNX model's own preset, the
    lane-change watch it was trained with behind the shield, and only the sensors it reads (on
    its own preset; on another every sensor, so that the model can say what differs)."""
    if config.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {config.episodes}")
    if config.onnx is None:
        preset = config.scenario.preset_or(None)
        settings = policy_settings(config.policy, preset, config.scenario.overrides({}))
        return DriveSetup(preset, settings, ())
    from overtake.client.policies.onnx_policy import read_metadata

    meta = read_metadata(config.onnx)
    base: dict[str, Any] = {}
    shielded = meta.get("shield", False) if config.shield is None else config.shield
    if shielded and meta.get("overrides", {}).get(WATCH_SETTING):
        # Trained with driver assistance watching lane changes through: the shield's
        # second half is the simulator's, and drives with the model.
        base[WATCH_SETTING] = True
    preset = config.scenario.preset_or(meta["preset"])
    own = preset == meta["preset"]
    reads = tuple(meta.get("input_names", ())) if own else ()
    # A model exported before issue 70 names no ego fields (its run set them by an override).
    ego_fields = tuple(meta.get("ego_fields", ())) if own else ()
    return DriveSetup(preset, base, reads, ego_fields)


def driver(config: DriveConfig, preset: str, envs: VectorFace) -> Driver:
    """The reference policy, or the ONNX model (behind the shield where asked), on ``envs``."""
    name = _policy_name(config)
    if config.onnx is None:
        act = baseline_policy(
            config.policy, envs.behaviour_spec, config.seed, config.episodes, envs
        )
        return Driver(act, PolicySource("reference", config.policy), name)
    from overtake.client.policies.onnx_policy import OnnxPolicy

    model = OnnxPolicy(
        config.onnx,
        config.episodes,
        envs.single_observation_space,
        preset,
        spec=envs.behaviour_spec,
        shield=config.shield,
    )
    source = PolicySource("onnx", str(config.onnx), shield=model.guard is not None)
    return Driver(model, source, name)


def main(config: DriveConfig, stop: threading.Event | None = None) -> dict[str, dict[str, float]]:
    """Drive the episodes; returns {metric: {"mean": .., "std": ..}} and prints the table.
    ``stop`` (Ctrl-C or SIGTERM on the command line): the episodes that ended by then make the
    table and the JSON, said as partial."""
    what = what_to_drive(config)
    driven = drive_episodes(
        config.where,
        what.preset,
        config.scenario.overrides(what.base),
        Episodes.from_seed(config.episodes, config.seed),
        functools.partial(driver, config, what.preset),
        Keeping(records=config.episodes_out is not None),
        realtime=config.realtime,
        observations=what.observations,
        ego_fields=what.ego_fields,
        stop=stop,
    )
    if not driven.rows:
        raise CommandError(
            f"stopped before any of the {driven.planned} episodes ended: no table, nothing written"
        )
    if config.episodes_out is not None:
        driven.write_records(config.episodes_out)
    rows = driven.rows
    summary = metric_summary(rows)
    seeds = [config.seed + i for i in driven.finished]
    _print_table(
        config, what.preset, seeds, metric_table(rows), summary, driven.decisions, driven.elapsed_s
    )
    if driven.partial:
        print(driven.partial_line())
    if SHIELD_OVERRIDES in summary:
        overrides = sum(row[SHIELD_OVERRIDES] for row in rows)
        print(
            f"the safety shield overrode the model {int(overrides)} times "
            f"in {driven.decisions} decisions"
        )
    timing = _realtime_report(driven.clock)
    if config.json_out is not None:
        config.json_out.parent.mkdir(parents=True, exist_ok=True)
        result = {
            "policy": _policy_name(config),
            "preset": what.preset,
            "seed": config.seed,
            "overrides": driven.overrides,
            "episodes": rows,
            "summary": summary,
            "realtime": timing or None,
            "partial": driven.partial,
            "episodes_planned": driven.planned,
        }
        config.json_out.write_text(json.dumps(result, indent=2))
    return summary


def _realtime_report(clock: RealTime | None) -> dict[str, float]:
    """A real-time drive's late decisions and latency, printed and returned (none: {})."""
    if clock is None:
        return {}
    timing = {
        "period_s": clock.period_s,
        "decisions": clock.decisions,
        "late": clock.late,
        "latency_p50_ms": clock.percentile_ms(50),
        "latency_p99_ms": clock.percentile_ms(99),
    }
    print(
        f"real time, one decision every {clock.period_s:g} s: {clock.late} of "
        f"{clock.decisions} decisions late; decision latency p50 "
        f"{timing['latency_p50_ms']:.2f} ms, p99 {timing['latency_p99_ms']:.2f} ms"
    )
    return timing


def _policy_name(config: DriveConfig) -> str:
    return f"onnx:{config.onnx}" if config.onnx is not None else config.policy


def _print_table(
    config: DriveConfig,
    preset: str,
    seeds: list[int],
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
    where = config.where.describe()
    print(
        f"policy={_policy_name(config)} preset={preset} episodes={config.episodes} "
        f"seed={config.seed} ({where})"
    )
    print(line)
    print("-" * len(line))
    for seed, row in zip(seeds, table, strict=True):
        cells = [str(seed)] + [
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


# Ctrl-C and SIGTERM end the drive before the next decision: the episodes that ended are
# reported and written, said as partial (a second signal ends it at once, in one line).
COMMAND = Command(
    "overtake-drive", DriveConfig, main, stopping="event", on_stop=say_stopping_episodes
)


if __name__ == "__main__":
    COMMAND.run()
