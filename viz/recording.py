"""Rerun recordings: where a process's logging goes, chosen by one option.

``file`` saves an ``.rrd`` (a trainer puts it in its run directory), ``grpc`` streams to a
running viewer (``rerun`` on this host, or ``--viewer-url`` on another), ``web`` starts Rerun's
web viewer from this process (bound to 127.0.0.1 unless ``--web-bind`` says otherwise; it lives
as long as the process), ``off`` logs nothing. Processes of one run that pass the same
``recording_id`` open as one recording. Each process keeps its own
:class:`rerun.RecordingStream` (never Rerun's global one), so a library user's own Rerun logging
is left alone.

The server (logging directly), the client's spectators and the trainers all record through
this module; it depends on nothing of the project.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from overtake.cli import CommandError, Output, check_viewer
from overtake.cli.options import unset

# Every process of the project records under this application id: processes that share a
# recording id (``--recording-id``) then open as one recording in the viewer.
APPLICATION_ID = "overtake"
DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"
WEB_VIEWER_START_TIMEOUT_S = 20.0
# Rerun's batcher gathers the rows logged to an entity into one chunk until this much time has
# passed or this many bytes are waiting. Its defaults (0.2 s, 2 MiB) suit a live viewer; an
# .rrd written with them is stored as many tiny chunks (a 2-minute demo: 22,573 chunks, 45 MB),
# each repeating its schema. Files batch longer; a viewer still sees data within a second.
FILE_FLUSH_TICK_S = 5.0
STREAM_FLUSH_TICK_S = 1.0
FLUSH_BYTES = 8 * 2**20
# Footers: an .rrd's footer holds a manifest of every chunk in the file, and the SDK builds it
# in memory until the file is closed, a row per chunk padded to every timeline and component of
# the recording (a server's world recording of 4 arenas: about 4 KiB a chunk, 800 chunks and
# 3.5 MiB a minute, without end; a trainer's, 0.33 MiB a minute). Processes that write for days
# (a server's and a spectator's world recording, a trainer's) write without one
# (``footer=False``): the file holds the same data
# (RrdReader.stream, overtake-layout, whose joined copy has a footer, `rerun rrd verify
# --check-footers false`); what it lacks is the index for random access into a large file.
# Closing waits this long for logged data to reach its sink; a viewer that has gone away must
# not hold up the end of a training run.
FLUSH_TIMEOUT_S = 10.0

log = logging.getLogger("overtake.recording")


class RecordingError(CommandError, RuntimeError):
    """A recording sink could not be opened (the web viewer's port taken, the viewer not
    starting); the message says what to change."""


@dataclass(frozen=True)
class RecordingConfig:
    """Where Rerun logging goes, and how often."""

    sink: Literal["file", "grpc", "web", "off"] = "file"
    """file: an .rrd (--rrd, or the command's default); grpc: stream to a viewer at
    --viewer-url; web: serve Rerun's web viewer from this process; off: no recording"""
    rrd: Annotated[Path | None, unset("PATH")] = None
    """the .rrd to write with sink=file; unset: the command's default"""
    viewer_url: str = DEFAULT_VIEWER_URL
    """a Rerun viewer's gRPC address, for sink=grpc (start one with `rerun`)"""
    recording_id: Annotated[str | None, unset("ID")] = None
    """processes that share it open as one recording; unset: one per process"""
    record_every: int = 1
    """decimation: log what the cars see every this many steps (episode and learning
    summaries are always logged)"""
    web_bind: str = "127.0.0.1"
    """sink=web: the address the web viewer and its gRPC server listen on (0.0.0.0: every
    host may watch)"""
    web_port: int = 9090
    """sink=web: the web viewer's HTTP port"""
    web_grpc_port: int = 9876
    """sink=web: the port of the gRPC server the web viewer reads from"""

    @property
    def web_host(self) -> str:
        """Where this host reaches the web sink (its bind address; loopback for 0.0.0.0)."""
        return _reachable(self.web_bind)

    def __post_init__(self) -> None:
        if self.record_every < 1:
            raise ValueError(f"record_every must be >= 1, got {self.record_every}")

    def output(self, default_rrd: Path | None) -> Output:
        """Where the recording goes, as an output the commands' door checks before the work
        starts: the file a file sink writes (``default_rrd`` where --rrd is not given), the
        viewer a gRPC sink streams to."""
        if self.sink == "grpc":
            return Output("--viewer-url", None, viewer_url=self.viewer_url)
        return Output("--rrd", (self.rrd or default_rrd) if self.sink == "file" else None)

    def describe(self, default_rrd: Path) -> str:
        """Where the recording goes, in words, for a closing log line."""
        if self.sink == "off":
            return "nowhere (--sink off)"
        if self.sink == "grpc":
            return f"the viewer at {self.viewer_url}"
        if self.sink == "web":
            host = self.web_host
            return (
                f"the web viewer at http://{host}:{self.web_port}/?url=rerun%2Bhttp://"
                f"{host}:{self.web_grpc_port}/proxy (while this process runs)"
            )
        return str(self.rrd or default_rrd)


def _reachable(bind: str) -> str:
    """The address that reaches a server bound to ``bind`` from this host."""
    return "127.0.0.1" if bind in ("0.0.0.0", "") else bind


@contextlib.contextmanager
def _quiet_stderr(quiet: bool) -> Iterator[None]:
    """Rerun warns, at every file opened without a footer, that random access will be slow: a
    choice made here for processes that write for days (see the note on footers above), and a
    warning a user can do nothing about. It is written to stderr while the sink opens, so
    stderr points at /dev/null for that call only (an environment setting would reach Zenoh's
    logger too, which reads the same RUST_LOG)."""
    if not quiet:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(devnull)
        os.close(saved)


def viewer_binary() -> str:
    """The Rerun viewer executable shipped in the rerun-sdk wheel.

    Not the ``rerun`` script of the environment's bin: that is a Python wrapper, and stopping
    its PID would leave the real viewer running."""
    import rerun_cli

    binary = Path(rerun_cli.__file__).parent / "rerun"
    if not binary.exists():
        raise RecordingError(
            f"the Rerun viewer is not installed here ({binary} is missing: the trainer image "
            "leaves it out); record to a file (--sink file) or stream to a running viewer "
            "(--sink grpc --viewer-url ...)"
        )
    return str(binary)


def _port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((_reachable(host), port), timeout=0.2):
            return True
    except OSError:
        return False


class Recording:
    """An open recording: ``stream`` is the :class:`rerun.RecordingStream` to log to."""

    def __init__(
        self, stream: Any, viewer: subprocess.Popen | None = None, viewer_log: Any = None
    ) -> None:
        self.stream = stream
        self.viewer = viewer
        self._viewer_log = viewer_log

    def close(self) -> None:
        """Flush and close: an .rrd gets its footer (a killed process leaves a readable file
        without one); a web viewer this process started is stopped. A sink that has gone away
        (a viewer closed or restarted) costs a warning, never the caller's run."""
        try:
            self.stream.flush(timeout_sec=FLUSH_TIMEOUT_S)
        except Exception as error:
            log.warning(
                "the Rerun recording could not be flushed (%s): the last logged data "
                "may be missing from it",
                error,
            )
        try:
            self.stream.disconnect()
        except Exception as error:  # pragma: no cover - disconnecting a dead gRPC sink
            log.warning("closing the Rerun recording failed: %s", error)
        if self.viewer is not None:
            if self.viewer.poll() is None:
                self.viewer.terminate()
                try:
                    self.viewer.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    self.viewer.kill()
                    self.viewer.wait()
            self._viewer_log.close()


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the viewer gets SIGTERM when the process that started it dies, even by SIGKILL,
    instead of holding its ports as an orphan."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG


def _start_web_viewer(config: RecordingConfig) -> tuple[subprocess.Popen, Any]:
    if _port_open(config.web_bind, config.web_grpc_port):
        raise RecordingError(
            f"cannot serve the web viewer: port {config.web_grpc_port} on "
            f"{config.web_bind} is already taken (another viewer?); choose "
            "--web-grpc-port, or stream to that viewer with --sink grpc"
        )
    # Its messages go to a file, not a pipe nobody reads (a full pipe would block it), and it
    # runs in a session of its own: Ctrl-C in a terminal reaches this process, which flushes
    # the recording and then stops the viewer, rather than the viewer first.
    # It lives as long as the viewer, which outlives this function.
    viewer_log = tempfile.TemporaryFile()  # noqa: SIM115
    viewer = subprocess.Popen(
        [
            viewer_binary(),
            "--serve-web",
            "--bind",
            config.web_bind,
            "--port",
            str(config.web_grpc_port),
            "--web-viewer-port",
            str(config.web_port),
        ],
        stdin=subprocess.DEVNULL,
        stdout=viewer_log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None,
    )

    def failed(why: str) -> RecordingError:
        viewer_log.seek(0)
        said = viewer_log.read().decode(errors="replace").strip()[-500:]
        viewer_log.close()
        return RecordingError(f"the Rerun web viewer {why}: {said}")

    deadline = time.monotonic() + WEB_VIEWER_START_TIMEOUT_S
    while not _port_open(config.web_bind, config.web_grpc_port):
        if viewer.poll() is not None:
            raise failed(f"exited with code {viewer.returncode} at start")
        if time.monotonic() > deadline:
            viewer.kill()
            viewer.wait()
            raise failed(
                f"did not open port {config.web_grpc_port} within {WEB_VIEWER_START_TIMEOUT_S} s"
            )
        time.sleep(0.05)  # polling a port: there is nothing to wait on
    return viewer, viewer_log


def open_recording(
    application: str,
    config: RecordingConfig,
    default_rrd: Path,
    blueprint: Any = None,
    footer: bool = True,
) -> Recording | None:
    """A recording with the configured sink, or None for sink=off.

    ``footer=False``: an .rrd without Rerun's footer, for a process that may write for days
    (see the note on footers above)."""
    if config.sink == "off":
        return None
    import rerun as rr

    tick_s = FILE_FLUSH_TICK_S if config.sink == "file" else STREAM_FLUSH_TICK_S
    stream = rr.RecordingStream(
        application,
        recording_id=config.recording_id,
        batcher_config=rr.ChunkBatcherConfig(
            flush_tick=datetime.timedelta(seconds=tick_s), flush_num_bytes=FLUSH_BYTES
        ),
    )
    viewer = viewer_log = None
    if config.sink == "file":
        path = config.rrd or default_rrd
        path.parent.mkdir(parents=True, exist_ok=True)
        with _quiet_stderr(not footer):
            stream.save(str(path), default_blueprint=blueprint, write_footer=footer)
    elif config.sink == "grpc":
        try:
            check_viewer(config.viewer_url)
        except CommandError as error:
            raise RecordingError(str(error)) from None
        stream.set_sinks(rr.GrpcSink(config.viewer_url), default_blueprint=blueprint)
    else:
        viewer, viewer_log = _start_web_viewer(config)
        stream.set_sinks(
            rr.GrpcSink(f"rerun+http://{config.web_host}:{config.web_grpc_port}/proxy"),
            default_blueprint=blueprint,
        )
        log.info("Rerun: %s", config.describe(default_rrd))
    return Recording(stream, viewer, viewer_log)


def close_recording(recording: Recording | None) -> None:
    if recording is not None:
        recording.close()
