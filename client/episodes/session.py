"""One command's episodes, from opening the simulator to closing it: what ``overtake-drive``,
``overtake-eval`` and ``overtake-replay`` each do, written once.

:func:`drive_episodes` opens the vector environment (one arena per episode), asks the command
for its driver (which may read the environment: its spec, its planner), keeps each episode's
record and a Rerun recording where asked, drives the episodes, and closes what it opened,
whatever happens; the command then reads the :class:`Driven` (rows of metrics, records) and
prints its table.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from overtake.client.episodes.recording import close_recording, open_episode_recording
from overtake.client.episodes.records import (
    EpisodeRecord,
    EpisodeRecorder,
    PolicySource,
    RecordHeader,
    record_name,
    write_records,
)
from overtake.client.episodes.runner import EpisodeWatcher, Policy, RealTime, drive_until
from overtake.client.episodes.scenario import Where
from overtake.client.provenance import git_commit
from overtake.envs.faces import VectorFace
from overtake.viz.recording import RecordingConfig


@dataclass(frozen=True)
class Driver:
    """What drives: the policy, what it is (for the records) and the name of its row."""

    act: Policy
    source: PolicySource
    name: str


@dataclass(frozen=True)
class Episodes:
    """The episodes to drive, one per environment: each one's seed, and its number (its
    timeline in a recording, its number in a record)."""

    seeds: tuple[int, ...]
    labels: tuple[int, ...]

    @classmethod
    def from_seed(cls, count: int, seed: int) -> Episodes:
        """``count`` episodes numbered from 0, episode ``i`` on seed ``seed + i``."""
        return cls(tuple(seed + i for i in range(count)), tuple(range(count)))

    @property
    def count(self) -> int:
        return len(self.seeds)


@dataclass(frozen=True)
class Keeping:
    """What is kept of the episodes besides their metrics."""

    records: bool = False
    """each episode's record (seed, actions, events: :class:`EpisodeRecord`)"""
    recording: RecordingConfig | None = None
    """a Rerun recording of the episodes, each on its own timeline (the road too, in process)"""
    rrd: Path | None = None
    """the recording's file where ``recording`` names none"""
    every: int = 1
    """draw the car and the road at one decision in this many (events always)"""


@dataclass(frozen=True)
class Driven:
    """What a run of episodes did."""

    driver: Driver
    preset: str
    overrides: dict[str, Any]
    sim_config: dict[str, Any]
    """the simulator configuration the preset and overrides resolved to"""
    rows: list[dict[str, float]]
    """each finished episode's metrics, in the order of the episodes"""
    finished: tuple[int, ...]
    """the episodes (their positions in :class:`Episodes`) that ended: all of them unless the
    drive was stopped (:attr:`partial`)"""
    planned: int
    """the episodes asked for"""
    decisions: int
    elapsed_s: float
    records: list[EpisodeRecord] | None
    """each episode's record, numbered as :attr:`Episodes.labels` (with Keeping.records)"""
    clock: RealTime | None
    recorded: bool
    """a Rerun recording was written"""

    @property
    def partial(self) -> bool:
        """Whether the drive was stopped before every episode ended."""
        return len(self.finished) < self.planned

    def partial_line(self) -> str:
        """What a command says of a stopped drive (empty where it was not stopped)."""
        if not self.partial:
            return ""
        return (
            f"partial: stopped after {len(self.finished)} of {self.planned} episodes ended "
            "(the table has those only)"
        )

    def header(self) -> RecordHeader:
        return RecordHeader(
            preset=self.preset,
            overrides=self.overrides,
            config=self.sim_config,
            policy=self.driver.source,
            commit=git_commit(),
            name=self.driver.name,
        )

    def write_records(self, folder: Path) -> Path:
        """The records as ``<row name>.jsonl`` in ``folder``; says where."""
        assert self.records is not None, "drive with Keeping(records=True) to keep records"
        path = write_records(
            folder / f"{record_name(self.driver.name)}.jsonl", self.header(), self.records
        )
        print(f"episodes kept in {path} (overtake-replay {path} --rrd OUT.rrd)")
        return path


def drive_episodes(
    where: Where,
    preset: str,
    overrides: Mapping[str, Any],
    episodes: Episodes,
    driver_for: Callable[[VectorFace], Driver],
    keeping: Keeping = Keeping(),
    realtime: bool = False,
    open_envs: Callable[[], VectorFace] | None = None,
    observations: Sequence[str] = (),
    stop: threading.Event | None = None,
    ego_fields: Sequence[str] = (),
) -> Driven:
    """Drive ``episodes`` of ``preset`` with ``overrides``, ``where`` says (or in what
    ``open_envs`` opens instead: a replay's simulator), by the driver ``driver_for`` chooses
    for the environment.
    ``realtime``: on the wall clock, one decision period per decision (:class:`RealTime`).
    ``observations``: only the sensors the driver reads (none named: the configuration's);
    ``ego_fields``: the ego vector's fields it reads, in order (none named: the preset's).
    ``stop``: once set, the drive ends before the next decision, with the episodes that ended
    (:attr:`Driven.partial`)."""
    if open_envs is None:
        envs = where.open(
            preset, overrides, episodes.count, observations=observations, ego_fields=ego_fields
        )
    else:
        envs = open_envs()
    recording = None
    rrd = keeping.rrd or Path("episodes.rrd")
    try:
        driver = driver_for(envs)
        clock = RealTime(period_s=envs.decision_period_s) if realtime else None
        recorder = EpisodeRecorder(list(episodes.seeds), driver.act) if keeping.records else None
        # Kept only where asked for: a list append per environment and decision otherwise.
        watchers: list[EpisodeWatcher] = [recorder] if recorder is not None else []
        if keeping.recording is not None:
            recording, view = open_episode_recording(
                keeping.recording,
                rrd,
                episodes.labels,
                envs,
                driver.act,
                driver.name,
                every=keeping.every,
            )
            if view is not None:
                watchers.append(view)
        run = drive_until(
            envs,
            driver.act,
            episodes.count,
            list(episodes.seeds),
            realtime=clock,
            watchers=watchers,
            stop=stop,
        )
        if (
            recording is not None
            and keeping.recording is not None
            and keeping.recording.sink == "web"
        ):
            # The web viewer lives in this process: it serves until the user is done.
            print(f"episodes driven: {keeping.recording.describe(rrd)}; Ctrl-C ends it")
            with contextlib.suppress(KeyboardInterrupt):
                (stop or threading.Event()).wait()
        sim_config = envs.sim_config
    finally:
        close_recording(recording)
        envs.close()
    records = None
    if recorder is not None:
        labels = episodes.labels
        # The recorder numbers environments 0..n-1: give them the episodes' numbers.
        records = [
            EpisodeRecord(labels[r.episode], r.seed, r.actions, r.metrics, r.events)
            for r in recorder.records()
        ]
    return Driven(
        driver=driver,
        preset=preset,
        overrides=dict(overrides),
        sim_config=sim_config,
        rows=[row for row in run.rows if row is not None],
        finished=run.finished,
        planned=episodes.count,
        decisions=run.decisions,
        elapsed_s=run.elapsed_s,
        records=records,
        clock=clock,
        recorded=recording is not None,
    )


__all__ = ["Driven", "Driver", "Episodes", "Keeping", "drive_episodes"]
