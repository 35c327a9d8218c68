"""Episodes as data: what an evaluation (or a drive) did, small enough to keep, enough to play
again bit for bit.

The simulator is deterministic (an arena's episode depends only on its seed and actions), so an
episode is its seed and the actions taken; beside them a record keeps the episode's metrics and
the decisions where something happened (collisions, emergency brakes, the safety shield's
overrides), which a replay checks itself against and a table points at.

One JSON-lines file per evaluation: the first line a header (:class:`RecordHeader`: the preset,
its overrides, the simulator configuration they resolved to, the policy, the code's commit),
then one line per episode (:class:`EpisodeRecord`). Actions are a string of digits (one per
decision, :data:`~overtake.protocol.vocabulary.ACTION_NAMES` order): 1.3 KB per 1,000
decisions of episodes that run their length, metrics and events included, and 3.3 KB of header
per file (``python -m bench.speed.bench_episode_records``, bench/RESULTS.md). Decisions are numbered
from 0 in the order taken: decision ``d`` is the ``d``-th action and the step it made.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from overtake.cli import UsageError
from overtake.client.episodes.runner import VectorStep
from overtake.client.policies.shield import SHIELD_OVERRIDES
from overtake.protocol.vocabulary import (
    ACTION_COUNT,
    EPISODE_COUNTS,
    METRIC_FIELDS,
)

RECORD_FORMAT = "overtake-episodes"
RECORD_VERSION = 1
# The events a record marks, by decision: the simulator's counts, and the shield's overrides.
EVENTS: tuple[str, ...] = (*EPISODE_COUNTS, SHIELD_OVERRIDES)


class RecordError(UsageError):
    """An episode record that cannot be read or played: the message says what was expected
    and what the file holds."""


@dataclass(frozen=True)
class PolicySource:
    """What drove: a checkpoint (its path and step), an exported ONNX model, or a reference
    policy by name; and whether the safety shield stood in front of it."""

    kind: Literal["checkpoint", "onnx", "reference"]
    name: str
    """the checkpoint's or model's path, or the reference policy's name (rule, random, ...)"""
    step: int | None = None
    """the checkpoint's training step"""
    shield: bool = False


@dataclass(frozen=True)
class RecordHeader:
    """What every episode of a record shares."""

    preset: str
    overrides: dict[str, Any]
    """the simulator overrides the evaluation ran with (dotted.name: value)"""
    config: dict[str, Any]
    """the simulator configuration they resolved to (the environment's ``sim_config``): a
    replay refuses a record whose preset and overrides resolve otherwise now"""
    policy: PolicySource
    commit: str
    """the code's git commit (``+uncommitted`` where the checkout had changes)"""
    name: str = ""
    """the evaluation's row name"""
    format: str = RECORD_FORMAT
    version: int = RECORD_VERSION


@dataclass(frozen=True)
class EpisodeRecord:
    """One episode: its seed, every action taken, its metrics and where its events were."""

    episode: int
    """the episode's index in its evaluation (seed = the evaluation's seed + episode)"""
    seed: int
    actions: str
    """one digit per decision: the action index sent"""
    metrics: dict[str, float]
    events: dict[str, tuple[int, ...]] = field(default_factory=dict)
    """per event (:data:`EVENTS`), the decisions it happened at"""

    def action_array(self) -> np.ndarray:
        return np.frombuffer(self.actions.encode("ascii"), dtype=np.uint8).astype(np.int64) - 48

    @property
    def collisions(self) -> int:
        return int(self.metrics.get("collisions", 0))


def record_name(name: str) -> str:
    """A file name for an evaluation's row name (``dqn/lidar@200000`` -> ``dqn_lidar_200000``)."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_.") or "episodes"


def write_records(path: Path, header: RecordHeader, episodes: list[EpisodeRecord]) -> Path:
    """Write a record file whole, atomically (a kill leaves the old file or none, never half
    of one); returns ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = [json.dumps(asdict(header), separators=(",", ":"))]
    for episode in sorted(episodes, key=lambda e: e.episode):
        row = asdict(episode)
        row["events"] = {name: list(decisions) for name, decisions in episode.events.items()}
        lines.append(json.dumps(row, separators=(",", ":")))
    handle, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write("\n".join(lines) + "\n")
        os.chmod(tmp, 0o644)  # mkstemp's 0600 is for the temporary name only
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _header(values: Any, path: Path) -> RecordHeader:
    if not isinstance(values, dict) or values.get("format") != RECORD_FORMAT:
        raise RecordError(
            f"{path} is not an episode record: its first line should be a header with "
            f"format {RECORD_FORMAT!r}, got {str(values)[:120]!r}"
        )
    if values.get("version") != RECORD_VERSION:
        raise RecordError(
            f"{path} is an episode record of version {values.get('version')}, this code reads "
            f"version {RECORD_VERSION}"
        )
    try:
        policy = PolicySource(**values["policy"])
        header = RecordHeader(**{**values, "policy": policy})
    except (KeyError, TypeError) as error:
        raise RecordError(f"{path}: the header is not a record header ({error})") from None
    if policy.kind not in ("checkpoint", "onnx", "reference"):
        raise RecordError(f"{path}: unknown policy kind {policy.kind!r}")
    return header


def _episode(values: Any, path: Path, line: int) -> EpisodeRecord:
    where = f"{path}, line {line}"
    try:
        record = EpisodeRecord(
            episode=int(values["episode"]),
            seed=int(values["seed"]),
            actions=str(values["actions"]),
            metrics={name: float(value) for name, value in values["metrics"].items()},
            events={
                name: tuple(int(d) for d in decisions)
                for name, decisions in values.get("events", {}).items()
            },
        )
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        raise RecordError(f"{where}: not an episode ({type(error).__name__}: {error})") from None
    digits = set(record.actions)
    if not digits <= {str(a) for a in range(ACTION_COUNT)}:
        raise RecordError(
            f"{where}: actions must be digits 0-{ACTION_COUNT - 1}, got {sorted(digits)}"
        )
    missing = [name for name in METRIC_FIELDS if name not in record.metrics]
    if missing:
        raise RecordError(f"{where}: the metrics lack {', '.join(missing)}")
    if record.metrics["decisions"] != len(record.actions):
        raise RecordError(
            f"{where}: {len(record.actions)} actions for an episode of "
            f"{record.metrics['decisions']:.0f} decisions"
        )
    return record


def read_header(path: Path) -> RecordHeader:
    """A record file's header alone (its first line: what every episode shares), without
    reading its episodes; :class:`RecordError` as :func:`read_records`."""
    try:
        with Path(path).open(encoding="utf-8") as file:
            first = next((line for line in file if line.strip()), None)
    except OSError as error:
        raise _unreadable(path, error) from None
    if first is None:
        raise _empty(path)
    return _header(_row(first, path, 1), path)


def read_records(path: Path) -> tuple[RecordHeader, list[EpisodeRecord]]:
    """A record file's header and episodes; :class:`RecordError` says what is wrong with a
    file that is not one."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as error:
        raise _unreadable(path, error) from None
    lines = [line for line in text.splitlines() if line.strip()]
    if not lines:
        raise _empty(path)
    rows = [_row(line, path, number) for number, line in enumerate(lines, start=1)]
    header = _header(rows[0], path)
    episodes = [_episode(row, path, n) for n, row in enumerate(rows[1:], start=2)]
    return header, episodes


# What the two readers say of a file that is not a record (blank lines are not counted).
def _unreadable(path: Path, error: OSError) -> RecordError:
    return RecordError(f"cannot read the episode record {path}: {error}")


def _empty(path: Path) -> RecordError:
    return RecordError(f"{path} is empty: an episode record starts with its header")


def _row(line: str, path: Path, number: int) -> Any:
    try:
        return json.loads(line)
    except json.JSONDecodeError as error:
        raise RecordError(f"{path}, line {number}: not JSON ({error})") from None


class EventCounts:
    """Which of ``info["episode_counts"]`` rose at a step, per environment: the decisions
    where a collision or an emergency brake happened (both episode watchers read it), or
    where driver assistance turned a lane change back (a training run's safety layer reads
    ``names=WATCH_METRICS``). A count that falls has started a new episode."""

    def __init__(self, num_envs: int, names: tuple[str, ...] = EPISODE_COUNTS) -> None:
        self.counts = {name: np.zeros(num_envs, dtype=np.int64) for name in names}

    def reset(self) -> None:
        for value in self.counts.values():
            value[:] = 0

    def rose(
        self, info: dict[str, Any], envs: np.ndarray | slice = slice(None)
    ) -> dict[str, np.ndarray]:
        """Per count in ``info`` (whose rows are the environments ``envs``, all by default),
        the rows whose count rose since the last call (then kept)."""
        counts = info.get("episode_counts", {})
        rose = {}
        for name, before in self.counts.items():
            if name in counts:
                now = np.asarray(counts[name])
                rose[name] = now > before[envs]
                before[envs] = now
        return rose


class EpisodeRecorder:
    """Builds the records of the episodes :func:`~overtake.client.episodes.runner.run_episodes`
    drives (one per environment: the first episode of each), as it steps them.

    ``policy`` may say, after each call, which environments' choices the safety shield
    overrode (``last_overridden``, (N,) bool): those decisions are marked too.
    """

    def __init__(self, seeds: list[int], policy: Any = None) -> None:
        self.seeds = seeds
        self.policy = policy
        n = len(seeds)
        self.actions: list[list[int]] = [[] for _ in range(n)]
        self.events: list[dict[str, list[int]]] = [{name: [] for name in EVENTS} for _ in range(n)]
        self.counts = EventCounts(n)
        self.metrics: list[dict[str, float] | None] = [None] * n
        self.running = np.ones(n, dtype=bool)

    def started(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.counts.reset()

    def stepped(self, step: VectorStep) -> None:
        actions, info = step.actions, step.info
        running = np.flatnonzero(self.running)
        overridden = getattr(self.policy, "last_overridden", None)
        rose = self.counts.rose(info)
        for i in running:
            decision = len(self.actions[i])
            self.actions[i].append(int(actions[i]))
            for name, happened in rose.items():
                if happened[i]:
                    self.events[i][name].append(decision)
            if overridden is not None and overridden[i]:
                self.events[i][SHIELD_OVERRIDES].append(decision)
        ended = step.ended & self.running
        for i in np.flatnonzero(ended & info.get("_metrics", False)):
            self.metrics[i] = {name: float(v[i]) for name, v in info["metrics"].items()}
        self.running &= ~ended

    def records(self) -> list[EpisodeRecord]:
        """The episodes that ended, in order."""
        return [
            EpisodeRecord(
                episode=i,
                seed=self.seeds[i],
                actions="".join(str(a) for a in self.actions[i]),
                metrics=metrics,
                events={name: tuple(d) for name, d in self.events[i].items() if d},
            )
            for i, metrics in enumerate(self.metrics)
            if metrics is not None
        ]
