"""``overtake-eval``: a checkpoint or a reference policy (rule, random, idle, planner, idm) over
fixed-seed episodes.

Every policy drives the same episodes: episode i uses seed ``seed + i``, at the chosen traffic,
in-process or on a server. The table has the papers' metrics (mean and spread over episodes):
average speed, lane changes, overtakes, collisions, emergency brakes and return, plus
collisions per 1,000 decisions (the issue's bar compares that one).
"""

from __future__ import annotations

import functools
import json
import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import torch

from overtake.cli import Command, CommandError, Output, UsageError
from overtake.cli.options import unset
from overtake.client.episodes.records import PolicySource
from overtake.client.episodes.runner import (
    baseline_policy,
    metric_summary,
    policy_settings,
    say_stopping_episodes,
)
from overtake.client.episodes.scenario import Scenario, Where, parse_overrides
from overtake.client.episodes.session import Driver, Episodes, Keeping, drive_episodes
from overtake.client.policies.shield import Shield, ShieldedActing
from overtake.envs.faces import VectorFace
from overtake.protocol.vocabulary import DENSITY_SETTING, WATCH_SETTING
from overtake.viz.recording import RecordingConfig

from .config.presets import PRESET_TRAINING
from .learning.network import INPUT_SENSORS, ego_fields_read, observations_read
from .learning.replay_memory import FrameStacker
from .run.checkpoint import Checkpoint, load_checkpoint
from .run.observations import describe_space, frame_shapes

log = logging.getLogger(__name__)

TABLE_METRICS = (
    "avg_speed_kmh",
    "lane_changes",
    "overtakes",
    "collisions",
    "emergency_brakes",
    "return",
)


@dataclass(frozen=True)
class EvalConfig:
    """Evaluate a trained checkpoint or a baseline driver on fixed seeds. The simulator and
    where it runs are the scenario's and where's options (--preset unset: the checkpoint's,
    else min2018; --max-decisions unset: the preset's, or its paper's evaluation's)."""

    scenario: Scenario = field(default_factory=Scenario)
    """the simulator: a preset, its traffic, episode length and overrides"""
    where: Where = field(default_factory=Where)
    """where the simulator runs: in this process, or on a server (--connect)"""

    checkpoint: Annotated[Path | None, unset("PATH")] = None
    """a checkpoint.pt written by overtake-train (evaluated greedily)"""
    policy: Annotated[
        Literal["rule", "random", "idle", "planner", "idm"] | None,
        unset("{rule,random,idle,planner,idm}"),
    ] = None
    """a reference policy instead of a checkpoint: the rule-based driver, random, idle (never
    acts), the privileged planner (reads the true state; in-process only) or idm
    (highway-env's IDM + MOBIL car at the wheel; presets highway-fast and highway)"""
    episodes: int = 10
    """episodes per policy, all at once (one arena each)"""
    seed: int = 1_000
    """episode i uses seed + i (training uses other seeds by default)"""
    shield: Annotated[bool | None, unset("{True,False}")] = None
    """the safety shield in front of the checkpoint's greedy choices; unset: where the run was
    trained with it (overtake.client.policies.shield). False also drops the lane-change watch a
    run trained with --shield-watch (the shield's second half), as overtake-drive does"""
    paper_evaluation: bool = True
    """evaluate as the preset's paper does where it evaluates otherwise than it trains
    (ho2018: a decision every frame, 4,000 frames, as Ho's code evaluates); --no-paper-
    evaluation decides as training does"""
    json_out: Annotated[Path | None, unset("PATH")] = None
    """also write the table (and every episode) as JSON here"""
    episodes_out: Annotated[Path | None, unset("PATH")] = None
    """keep every episode as a record in this folder (<name>.jsonl: seeds, actions, metrics,
    the decisions of collisions, emergency brakes and shield overrides), for overtake-replay"""
    record: Annotated[Path | None, unset("PATH")] = None
    """record the episodes to this .rrd while evaluating, each on its own timeline (the road
    too, in process), as overtake-replay does"""
    name: Annotated[str | None, unset("NAME")] = None
    """the row's name in the table (default: the algorithm and inputs, or the baseline)"""
    table: tuple[Path, ...] = ()
    """instead of evaluating: print one table of these --json-out files (rows side by side)"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before any episode is driven)."""
        return (
            Output("--json-out", self.json_out),
            Output("--episodes-out", self.episodes_out, folder=True),
            Output("--record", self.record),
        )


class GreedyPolicy:
    """A trained learner acting greedily on stacked frames (restarted at episode starts)."""

    def __init__(
        self,
        checkpoint: Any,
        num_envs: int,
        space: Any,
        preset: str,
        shield: Shield | None = None,
    ) -> None:
        trained_on = f"(the checkpoint was trained on preset {checkpoint.preset})"
        shapes = frame_shapes(space, checkpoint.inputs, f"preset {preset} {trained_on}")
        here = describe_space(space)
        for name in shapes.shapes:
            if here[name] != checkpoint.space.get(name):
                raise UsageError(
                    f"observation {name!r} of preset {preset} is {here[name]}, the checkpoint's "
                    f"network was built for {checkpoint.space.get(name)} {trained_on}"
                )
        self.learner = checkpoint.make_learner()
        self.stacker = FrameStacker(
            num_envs, shapes, checkpoint.dqn.stack, INPUT_SENSORS[checkpoint.inputs]
        )
        self.rng = np.random.default_rng(0)  # unused by a greedy policy, which act() needs
        self.guard = ShieldedActing(shield, num_envs) if shield is not None else None
        # The last decision's Q-values (N, actions) and where the shield overrode them: what
        # an episode record and a recording show beside the action.
        self.last_q: np.ndarray | None = None
        self.last_overridden: np.ndarray | None = None
        if self.guard is not None:
            # run_episodes adds each episode's overrides to its row.
            self.episode_extras = self.guard.episode_extras

    @torch.no_grad()
    def __call__(
        self, obs: dict[str, np.ndarray], info: dict[str, Any], starting: np.ndarray
    ) -> np.ndarray:
        stacked = self.stacker.take(obs, starting)
        mask = info["action_mask"]
        if self.guard is None:
            actions, self.last_q = self.learner.act(stacked, mask, 0.0, self.rng)
            return actions
        shielded = self.guard.mask(stacked, mask, starting)
        actions, self.last_q = self.learner.act(stacked, shielded, 0.0, self.rng)
        self.guard.count(self.last_q, mask, shielded)
        self.last_overridden = self.guard.last_overridden
        return actions


def paper_evaluation(preset: str) -> tuple[str, ...]:
    """The overrides (dotted.name=value) under which ``preset``'s paper evaluates."""
    training = PRESET_TRAINING.get(preset)
    return training.evaluation if training is not None else ()


def summarise(rows: list[dict[str, float]]) -> dict[str, Any]:
    """Mean and spread of each metric, collisions per 1,000 decisions and the episode count."""
    summary: dict[str, Any] = dict(metric_summary(rows))
    decisions = sum(row["decisions"] for row in rows)
    collisions = sum(row["collisions"] for row in rows)
    summary["collisions_per_1000_decisions"] = float(1000.0 * collisions / max(decisions, 1.0))
    summary["episodes"] = len(rows)
    return summary


def format_rows(named: list[tuple[str, dict[str, Any]]]) -> str:
    headers: tuple[str, ...] = (
        "policy",
        "speed km/h",
        "lane changes",
        "overtakes",
        "collisions",
        "e-brakes",
        "return",
        "coll./1k dec.",
    )
    shielded = any("shield_overrides" in s for _, s in named)
    if shielded:
        headers = (*headers, "shield overrides")
    lines: list[tuple[str, ...]] = [headers]
    for name, s in named:
        cells = [name] + [f"{s[m]['mean']:.1f} ± {s[m]['std']:.1f}" for m in TABLE_METRICS]
        cells.append(f"{s['collisions_per_1000_decisions']:.2f}")
        if shielded:
            overrides = s.get("shield_overrides")
            cells.append(f"{overrides['mean']:.1f}" if overrides else "-")
        lines.append(tuple(cells))
    widths = [max(len(row[i]) for row in lines) for i in range(len(headers))]
    out = ["  ".join(c.rjust(w) for c, w in zip(row, widths)) for row in lines]
    out.insert(1, "-" * len(out[0]))
    return "\n".join(out)


def print_table(paths: tuple[Path, ...]) -> str:
    """One table of earlier evaluations (their --json-out files)."""
    named = []
    for path in paths:
        try:
            result = json.loads(Path(path).read_text())
            named.append((result["name"], result["summary"]))
        except (OSError, ValueError, KeyError) as error:
            raise UsageError(f"{path} is not an overtake-eval result ({error})") from None
    text = format_rows(named)
    print(text)
    return text


@dataclass(frozen=True)
class Evaluated:
    """What an evaluation drives, and on which simulator."""

    checkpoint: Checkpoint | None  # None: a reference policy (--policy)
    preset: str
    overrides: dict[str, Any]

    @property
    def observations(self) -> tuple[str, ...]:
        """The sensors to render: the network's, on its own preset; on another, every sensor,
        so that the network's check can say what differs (:class:`GreedyPolicy`)."""
        checkpoint = self.checkpoint
        if checkpoint is None or checkpoint.preset != self.preset:
            return ()
        return observations_read(checkpoint.inputs)

    @property
    def ego_fields(self) -> tuple[str, ...]:
        """The ego vector's fields the network reads, on its own preset (none: the preset's)."""
        checkpoint = self.checkpoint
        if checkpoint is None or checkpoint.preset != self.preset:
            return ()
        return ego_fields_read(checkpoint.inputs)


def evaluated(config: EvalConfig) -> Evaluated:
    """The checkpoint (or none) and the simulator ``config`` asks to evaluate on: the
    checkpoint's overrides less its traffic, the paper's evaluation, then the scenario's."""
    if (config.checkpoint is None) == (config.policy is None):
        raise UsageError(
            "give exactly one of --checkpoint PATH or --policy rule|random|idle|planner|idm"
        )
    if config.episodes < 1:
        raise UsageError(f"--episodes must be >= 1, got {config.episodes}")
    checkpoint = load_checkpoint(config.checkpoint) if config.checkpoint is not None else None
    preset = config.scenario.preset_or(checkpoint.preset if checkpoint else None)
    base: dict[str, Any] = dict(checkpoint.overrides) if checkpoint else {}
    base.pop(DENSITY_SETTING, None)  # evaluation sets its own traffic
    if config.shield is False:
        # The lane-change watch is the shield's second half (--shield-watch): without the
        # shield it goes too, as in overtake-drive; --set ego.lane_change_watch=true keeps it.
        base.pop(WATCH_SETTING, None)
    if config.paper_evaluation:
        base.update(parse_overrides(paper_evaluation(preset)))
    overrides = config.scenario.overrides(base)
    overrides.update(policy_settings(config.policy, preset, overrides))
    return Evaluated(checkpoint, preset, overrides)


def evaluation_driver(config: EvalConfig, what: Evaluated, envs: VectorFace) -> Driver:
    """The checkpoint acting greedily (behind the shield where it was trained with one, or
    as --shield says), or the reference policy, on ``envs``."""
    checkpoint = what.checkpoint
    if checkpoint is None:
        act = baseline_policy(
            str(config.policy), envs.behaviour_spec, config.seed, config.episodes, envs
        )
        source = PolicySource("reference", str(config.policy))
        return Driver(act, source, config.name or str(config.policy))
    shielded = checkpoint.config.get("shield", False) if config.shield is None else config.shield
    policy = GreedyPolicy(
        checkpoint,
        config.episodes,
        envs.single_observation_space,
        what.preset,
        Shield(envs.behaviour_spec) if shielded else None,
    )
    name = config.name or f"{checkpoint.algo}/{checkpoint.inputs}@{checkpoint.step}"
    source = PolicySource(
        "checkpoint", str(config.checkpoint), checkpoint.step, policy.guard is not None
    )
    return Driver(policy, source, name)


def main(config: EvalConfig, stop: threading.Event | None = None) -> dict[str, Any]:
    """Run the episodes; prints the table row and returns the summary. ``stop`` (Ctrl-C or
    SIGTERM on the command line): the episodes that ended by then make the table and the
    JSON, said as partial."""
    if config.table:
        return {"table": print_table(config.table)}
    what = evaluated(config)
    recording = None if config.record is None else RecordingConfig(sink="file", rrd=config.record)
    driven = drive_episodes(
        config.where,
        what.preset,
        what.overrides,
        Episodes.from_seed(config.episodes, config.seed),
        functools.partial(evaluation_driver, config, what),
        Keeping(config.episodes_out is not None, recording=recording, rrd=config.record),
        observations=what.observations,
        ego_fields=what.ego_fields,
        stop=stop,
    )
    if not driven.rows:
        raise CommandError(
            f"stopped before any of the {driven.planned} episodes ended: no table, nothing written"
        )
    record_path = (
        driven.write_records(config.episodes_out) if config.episodes_out is not None else None
    )
    name, summary = driven.driver.name, summarise(driven.rows)
    result = {
        "name": name,
        "preset": what.preset,
        "overrides": what.overrides,
        "seed": config.seed,
        "checkpoint": str(config.checkpoint) if config.checkpoint else None,
        "policy": config.policy,
        "summary": summary,
        "episodes": driven.rows,
        "decisions_per_s": driven.decisions / max(driven.elapsed_s, 1e-9),
        "episodes_record": str(record_path) if record_path is not None else None,
        "partial": driven.partial,
        "episodes_planned": driven.planned,
    }
    print(format_rows([(name, summary)]))
    if driven.partial:
        print(driven.partial_line())
    if config.json_out is not None:
        config.json_out.parent.mkdir(parents=True, exist_ok=True)
        config.json_out.write_text(json.dumps(result, indent=2))
    return result


# Ctrl-C and SIGTERM end the drive before the next decision: the episodes that ended are
# reported and written, said as partial (a second signal ends it at once, in one line).
COMMAND = Command(
    "overtake-eval", EvalConfig, main, stopping="event", on_stop=say_stopping_episodes
)


if __name__ == "__main__":
    COMMAND.run()
