"""A server logging its arenas to Rerun directly (``overtake-server --sink file|grpc|web``).

The simulation loop only builds each arena's :class:`WorldFrame` (copies of a few arrays) every
``--record-every`` rounds and hands it to a bounded queue; a thread of its own turns frames into
Rerun calls. When that thread falls behind, frames are dropped and counted, never waited for:
like the spectators' world topic, recording must not hold the simulation back.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
from pathlib import Path

from overtake.protocol.messages import WorldFrame
from overtake.viz.recording import APPLICATION_ID, Recording, RecordingConfig, open_recording
from overtake.viz.world_view import WorldRecording

log = logging.getLogger("overtake.server.service.recorder")

# Frames waiting for the logging thread; beyond this they are dropped (about a second of a
# 64-arena server at 16 rounds/s).
QUEUE_FRAMES = 1024


def default_rrd(server: str) -> Path:
    return Path("runs") / "server" / f"{server}.rrd"


class ServerRecorder:
    """Logs world frames to a recording from a background thread; :meth:`offer` never blocks."""

    def __init__(self, config: RecordingConfig, server: str) -> None:
        self.config = config
        self.where = config.describe(default_rrd(server))
        # No footer: the server may record for days (see overtake.viz.recording on footers).
        recording = open_recording(APPLICATION_ID, config, default_rrd(server), footer=False)
        if recording is None:
            raise ValueError("a ServerRecorder needs a sink other than off")
        self.recording: Recording = recording
        # Shared with trainers (--recording-id): the layout shows their plots too.
        self.view = WorldRecording(recording.stream, with_training=config.recording_id is not None)
        self.logged = 0
        self.dropped = 0
        self._queue: queue.Queue[WorldFrame | None] = queue.Queue(maxsize=QUEUE_FRAMES)
        self._thread = threading.Thread(target=self._run, name="overtake-recorder", daemon=True)
        self._thread.start()

    def wants(self, round_: int) -> bool:
        """Whether a group that has just played round ``round_`` should be recorded."""
        return round_ % self.config.record_every == 0

    def has_room(self) -> bool:
        """Whether a frame offered now would be kept (so none is built only to be dropped)."""
        return not self._queue.full()

    def offer(self, frame: WorldFrame) -> bool:
        """Queue a frame for logging; False (and counted) if the queue is full."""
        try:
            self._queue.put_nowait(frame)
            return True
        except queue.Full:
            self.count_dropped(1)
            return False

    def count_dropped(self, frames: int) -> None:
        before, self.dropped = self.dropped, self.dropped + frames
        # A warning at the first drop and at every power of ten after it: visible, not a flood.
        if before == 0 or len(str(before)) != len(str(self.dropped)):
            log.warning(
                "recording falls behind: %d world frame(s) dropped so far (raise "
                "--record-every to record fewer)",
                self.dropped,
            )

    def _run(self) -> None:
        while True:
            frame = self._queue.get()
            if frame is None:
                return
            try:
                self.view.log(frame)
                self.logged += 1
            except Exception:
                # A frame Rerun refuses is that frame's loss, not the recording's.
                log.exception("could not log a world frame of arena %d", frame.arena)

    def close(self, timeout_s: float = 30.0) -> None:
        """Log what is queued (for at most ``timeout_s``), then close the recording (an .rrd
        gets its footer)."""
        with contextlib.suppress(queue.Full):  # the logging thread is stuck
            self._queue.put(None, timeout=timeout_s)
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():  # pragma: no cover
            log.warning(
                "the recording thread did not finish within %.0f s; closing anyway", timeout_s
            )
        self.recording.close()
        log.info(
            "recorded %d world frame(s) to %s (%d dropped)", self.logged, self.where, self.dropped
        )
