"""``overtake-replay``: play recorded episodes again and watch them in Rerun.

An episode record (``overtake-eval --episodes-out``, ``overtake-drive --episodes-out``, the
experiments' evaluations) holds each episode's seed and actions; the simulator is
deterministic, so sending the same actions from the same seed re-simulates the episode bit for
bit. The replay records it as :mod:`overtake.viz.episode_view` lays out (the road with the cars
of each collision coloured, the car's camera and LIDAR, its speed, the Q-values where a
checkpoint or model drove, the action, the reward and its terms, the event log), each episode on
its own timeline.

The replay checks itself against the record and stops with a message naming what differs:
before it starts, the configuration the record's preset and overrides resolve to now against
the record's; while it runs, the policy's choice against the recorded action (a checkpoint, an
exported model, and the deterministic reference drivers: rule, idle, planner); at the end, each
episode's metrics and events against the record's.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tyro.conf import Positional

from overtake.cli import Command
from overtake.client.episodes.records import (
    EpisodeRecord,
    RecordError,
    RecordHeader,
    read_records,
)
from overtake.client.episodes.runner import baseline_policy
from overtake.client.episodes.scenario import Where
from overtake.client.episodes.session import Driver, Episodes, Keeping, drive_episodes
from overtake.client.policies.shield import Shield
from overtake.client.provenance import git_commit
from overtake.envs.faces import VectorFace
from overtake.protocol import errors
from overtake.protocol.vocabulary import ACTION_NAMES
from overtake.viz.recording import RecordingConfig

from .evaluate import GreedyPolicy
from .run.checkpoint import load_checkpoint

# Reference policies whose choices depend on nothing but what their arena shows: a replay
# checks each of their decisions against the record (random draws for the whole batch).
DETERMINISTIC_REFERENCES = ("rule", "idle", "planner")


class ReplayDiverged(RecordError):
    """The replayed episode is not the recorded one; the message says where it parted."""


@dataclass(frozen=True)
class ReplayConfig:
    """Play recorded episodes again, into Rerun (on the simulator --connect names, or in this
    process, which also draws the road)."""

    record: Positional[Path]
    """an episode record (<name>.jsonl of overtake-eval --episodes-out)"""
    where: Where = field(default_factory=Where)
    """where the simulator runs: in this process (which also draws the road), or on a server
    (--connect)"""
    episode: tuple[int, ...] = ()
    """the episodes to replay, by their number in the record (default: all)"""
    collisions: bool = False
    """only the episodes with a collision"""
    checkpoint: Path | None = None
    """the checkpoint that drove, where it is not at the path the record names (its Q-values
    are recorded, and its choices checked against the record)"""
    actions_only: bool = False
    """play the recorded actions without asking the checkpoint or model that drove (where it
    is not at hand, as in an experiment's copy kept in bench/results): no Q-values, and its
    choices are not checked; each episode's metrics and events still are"""
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    """where the replay is recorded (default: <record's name>-replay.rrd here)"""


def select(episodes: list[EpisodeRecord], config: ReplayConfig) -> list[EpisodeRecord]:
    """The episodes ``config`` asks for, in the record's order."""
    numbers = {record.episode for record in episodes}
    unknown = sorted(set(config.episode) - numbers)
    if unknown:
        raise RecordError(
            f"{config.record} has no episode {', '.join(map(str, unknown))}: it holds "
            f"episodes {min(numbers)}-{max(numbers)}"
            if numbers
            else f"{config.record} holds no episodes"
        )
    chosen = [r for r in episodes if not config.episode or r.episode in config.episode]
    if config.collisions:
        chosen = [r for r in chosen if r.collisions > 0]
        if not chosen:
            raise RecordError(f"no episode asked for in {config.record} has a collision")
    if not chosen:
        raise RecordError(f"{config.record} holds no episodes")
    return chosen


class RecordedActions:
    """Sends each environment its episode's recorded actions (keep after the episode ended);
    with ``policy`` (the one that drove, where it can be asked again) it also asks it, for its
    Q-values and the shield's overrides, and stops at the first decision where it would now
    choose otherwise than the record. It has ``last_q`` (what a recording's Q-values plot
    shows) only where ``policy`` has."""

    def __init__(
        self, episodes: list[EpisodeRecord], policy: Any, check: bool, header: RecordHeader
    ) -> None:
        self.episodes, self.policy, self.check, self.header = episodes, policy, check, header
        self.actions = [record.action_array() for record in episodes]
        self.lengths = np.array([len(a) for a in self.actions], dtype=np.int64)
        self.decision = np.zeros(len(episodes), dtype=np.int64)
        if policy is not None and hasattr(policy, "last_q"):
            self.last_q: np.ndarray | None = None
        self.last_overridden: np.ndarray | None = None
        if policy is not None and hasattr(policy, "episode_extras"):
            self.episode_extras = policy.episode_extras

    def __call__(
        self, obs: dict[str, np.ndarray], info: dict[str, Any], starting: np.ndarray
    ) -> np.ndarray:
        actions = np.zeros(len(self.episodes), dtype=np.int64)
        playing = self.decision < self.lengths
        for i in np.flatnonzero(playing):
            actions[i] = self.actions[i][self.decision[i]]
        if self.policy is not None:
            chosen = np.asarray(self.policy(obs, info, starting))
            if hasattr(self.policy, "last_q"):
                self.last_q = self.policy.last_q
            self.last_overridden = getattr(self.policy, "last_overridden", None)
            if self.check:
                parted = np.flatnonzero(playing & (chosen != actions))
                if parted.size:
                    first = int(parted[0])
                    episode = self.episodes[first]
                    raise ReplayDiverged(
                        f"episode {episode.episode} (seed {episode.seed}) "
                        f"parts from its record at decision {self.decision[first]}: the record "
                        f"took {ACTION_NAMES[actions[first]]}, the policy now chooses "
                        f"{ACTION_NAMES[chosen[first]]}, so what it observed differs"
                        f"{_commits(self.header)}"
                    )
        self.decision += playing
        return actions


def _commits(header: RecordHeader) -> str:
    now = git_commit()
    if now == header.commit:
        return ""
    return f" (the record was made by commit {header.commit}, this is {now})"


def _experiment_root(record: Path) -> Path | None:
    """The experiment directory a record lies in (the nearest folder above it holding an
    experiment's plan or table), where its relative checkpoint names are rooted."""
    for folder in Path(record).resolve().parents:
        if (folder / "experiment.json").exists() or (folder / "table.json").exists():
            return folder
    return None


def _driver_file(header: RecordHeader, config: ReplayConfig) -> Path:
    """The checkpoint or model that drove: ``--checkpoint``, or where the record says (a
    relative name from the working directory, else from the record's experiment)."""
    path = config.checkpoint or Path(header.policy.name)
    root = _experiment_root(config.record)
    if not path.exists() and not path.is_absolute() and root is not None:
        path = root / path
    if not path.exists():
        what = "checkpoint" if header.policy.kind == "checkpoint" else "model"
        raise RecordError(
            f"the record was driven by the {what} {header.policy.name}, which is not there: "
            "give its place with --checkpoint, or play the recorded actions alone with "
            "--actions-only"
        )
    return path


def _policy(header: RecordHeader, config: ReplayConfig, envs: VectorFace) -> tuple[Any, bool]:
    """The policy that drove, asked again during the replay (None: it cannot be, or need not
    be), and whether its choices are checked against the record."""
    source, n = header.policy, envs.num_envs
    if config.actions_only:
        return None, False
    space, spec = envs.single_observation_space, envs.behaviour_spec
    if source.kind == "checkpoint":
        path = _driver_file(header, config)
        checkpoint = load_checkpoint(path)
        if source.step is not None and checkpoint.step != source.step:
            raise RecordError(
                f"{path} is at step {checkpoint.step}, the record was driven at step "
                f"{source.step}: its Q-values would not be the ones that drove"
            )
        shield = Shield(spec) if source.shield else None
        return GreedyPolicy(checkpoint, n, space, header.preset, shield), True
    if source.kind == "onnx":
        from overtake.client.policies.onnx_policy import OnnxPolicy

        path = _driver_file(header, config)
        return OnnxPolicy(path, n, space, header.preset, spec=spec, shield=source.shield), True
    if source.name in DETERMINISTIC_REFERENCES:
        return baseline_policy(source.name, spec, 0, n, envs), True
    return None, False


def compare(recorded: list[EpisodeRecord], replayed: list[EpisodeRecord], header: Any) -> None:
    """Each replayed episode's length, metrics and events against the record's."""
    by_number = {record.episode: record for record in replayed}
    for record in recorded:
        again = by_number.get(record.episode)
        if again is None:
            raise ReplayDiverged(
                f"episode {record.episode} did not end within its {len(record.actions)} "
                f"recorded decisions{_commits(header)}"
            )
        # The papers' metrics, and any other the record kept (WATCH_METRICS).
        for name, value in record.metrics.items():
            if again.metrics.get(name) != value:
                raise ReplayDiverged(
                    f"episode {record.episode} (seed {record.seed}) replayed with {name} = "
                    f"{again.metrics.get(name)!r}, the record says {value!r}"
                    f"{_commits(header)}"
                )
        events = {k: v for k, v in record.events.items() if k != "shield_overrides"}
        events_again = {k: v for k, v in again.events.items() if k != "shield_overrides"}
        if events != events_again:
            raise ReplayDiverged(
                f"episode {record.episode}: events at {events_again} replayed, the record "
                f"has {events}{_commits(header)}"
            )


def replay_envs(
    header: RecordHeader,
    count: int,
    where: Where | None = None,
    changes: Mapping[str, Any] | None = None,
) -> VectorFace:
    """``count`` environments of the simulator a record was made on (``where`` says where:
    default in this process), built again by that simulator from its own settings' history
    (overtake.server.sim.settings_history: the record's preset and overrides, and what undoes
    the changes since); :class:`RecordError` where it cannot be, naming what differs.
    ``changes``: overrides put on top, for a replay that asks "what if"
    (``overtake-collision-causes``)."""
    where = where or Where()
    overrides = {**header.overrides, **(changes or {})}
    recorded = _with_changes(header.config, changes or {})
    try:
        return where.open(header.preset, overrides, count, as_recorded=recorded)
    except (errors.BadConfig, ValueError) as error:
        raise RecordError(f"{error}{_commits(header)}") from None


def _with_changes(config: dict[str, Any], changes: Mapping[str, Any]) -> dict[str, Any]:
    """A record's configuration with "what if" changes (dotted names) put in, as the
    simulator built with them must hold them."""
    changed = copy.deepcopy(config)
    for name, value in changes.items():
        *sections, last = name.split(".")
        place = changed
        for section in sections:
            place = place.setdefault(section, {})
        place[last] = list(value) if isinstance(value, tuple) else value
    return changed


def main(config: ReplayConfig) -> dict[str, Any]:
    """Replay the chosen episodes; returns what was replayed and where it was recorded."""
    header, episodes = read_records(config.record)
    chosen = select(episodes, config)
    rrd = config.recording.rrd or Path(f"{config.record.stem}-replay.rrd")
    where = config.where

    def driver_for(envs: VectorFace) -> Driver:
        policy, check = _policy(header, config, envs)
        actions = RecordedActions(chosen, policy, check, header)
        return Driver(actions, header.policy, header.name or header.policy.name)

    driven = drive_episodes(
        where,
        header.preset,
        header.overrides,
        Episodes(tuple(r.seed for r in chosen), tuple(r.episode for r in chosen)),
        driver_for,
        Keeping(
            records=True,
            recording=config.recording,
            rrd=rrd,
            every=config.recording.record_every,
        ),
        open_envs=lambda: replay_envs(header, len(chosen), where),
    )
    assert driven.records is not None
    compare(chosen, driven.records, header)
    where_recorded = config.recording.describe(rrd) if driven.recorded else "not recorded"
    for record in chosen:
        collisions = record.events.get("collisions", ())
        print(
            f"episode {record.episode} (seed {record.seed}): {len(record.actions)} decisions, "
            f"as recorded"
            + (f"; collision at decision {', '.join(map(str, collisions))}" if collisions else "")
        )
    print(f"replay: {where_recorded}")
    return {
        "episodes": [r.episode for r in chosen],
        "rrd": str(rrd) if driven.recorded else None,
    }


COMMAND = Command("overtake-replay", ReplayConfig, main)


if __name__ == "__main__":
    COMMAND.run()
