"""``overtake-spectate``: watch a running server's arenas in Rerun, read-only.

It subscribes to the servers' world topics (the server publishes them at its world rate, with
dropping congestion control, and only while somebody watches), so watching never slows or
touches the simulation. Frames go to an ``.rrd`` file by default, stream to a viewer, or to a
web viewer this command serves; ``--record-every N`` logs one frame in N.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from overtake.cli import Command, Output, UsageError
from overtake.client.wire.remote_config import RemoteConfig
from overtake.client.wire.world_feed import Spectator
from overtake.ipc.transport import DEFAULT_ENDPOINT, SecurityConfig
from overtake.viz.recording import APPLICATION_ID, RecordingConfig, close_recording, open_recording
from overtake.viz.world_view import WorldRecording

DEFAULT_RRD = Path("runs/spectate/world.rrd")


@dataclass(frozen=True)
class SpectateConfig:
    """Log what a simulator server's arenas look like to Rerun."""

    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """the server's (or a router's) Zenoh endpoints"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates for --connect"""
    server: str | None = None
    """only this server's arenas (default: every server's)"""
    arena: int | None = None
    """only this arena (needs --server)"""
    seconds: float | None = None
    """stop after this long (default: until SIGINT or SIGTERM)"""
    frames: int | None = None
    """stop after this many logged frames"""
    rays: bool = True
    """draw every LIDAR ray, not only the hits"""
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    """where the frames go (default: runs/spectate/world.rrd)"""
    overwrite: bool = False
    """replace an existing .rrd (sink=file); without it an existing one is refused"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before it connects)."""
        return (self.recording.output(DEFAULT_RRD),)


def main(config: SpectateConfig, stop: threading.Event | None = None) -> int:
    """Log frames until ``stop`` is set, or the time or frame limit; returns frames logged."""
    rrd = config.recording.rrd or DEFAULT_RRD
    if config.recording.sink == "file" and rrd.exists() and not config.overwrite:
        # The last spectator's recording is somebody's evidence: never lost without a word.
        raise UsageError(
            f"{rrd} exists (an earlier recording): give --rrd NEW.rrd, or --overwrite to replace it"
        )
    stop = stop or threading.Event()
    remote = RemoteConfig(connect=config.connect, security=config.security)
    with Spectator(remote, server=config.server, arena=config.arena) as spectator:
        # The layout follows the arenas as they appear (WorldRecording sends it).
        # No footer: a spectator may record for days (see overtake.viz.recording on footers).
        recording = open_recording(APPLICATION_ID, config.recording, DEFAULT_RRD, footer=False)
        # Shared with trainers (--recording-id): the layout shows their plots too.
        view = (
            WorldRecording(
                recording.stream,
                rays=config.rays,
                with_training=config.recording.recording_id is not None,
            )
            if recording is not None
            else None
        )
        logged = received = 0
        deadline = None if config.seconds is None else time.monotonic() + config.seconds
        try:
            while not stop.is_set():
                if config.frames is not None and logged >= config.frames:
                    break
                wait = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
                if wait <= 0:
                    break
                frame = spectator.next_frame(wait)
                if frame is None:
                    continue
                received += 1
                if (received - 1) % config.recording.record_every:
                    continue
                if view is not None:
                    view.log(frame)
                logged += 1
        finally:
            close_recording(recording)
            if logged == 0 and config.recording.sink == "file" and rrd.exists():
                # No frame came (no arena open): an empty recording would only block the next
                # run's --rrd; nothing is kept.
                rrd.unlink()
    return logged


def _report(config: SpectateConfig, logged: int) -> None:
    if logged == 0 and config.recording.sink == "file":
        print("logged no world frame (no arena was open): no recording kept", file=sys.stderr)
        return
    print(
        f"logged {logged} world frame(s) to {config.recording.describe(DEFAULT_RRD)}",
        file=sys.stderr,
    )


COMMAND = Command("overtake-spectate", SpectateConfig, main, report=_report, stopping="event")


if __name__ == "__main__":
    COMMAND.run()
