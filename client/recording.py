"""Rerun recordings: where a process's logging goes, chosen by one option.

``file`` saves an ``.rrd`` (the default; a trainer puts it in its run directory), ``grpc``
streams to a running viewer (``rerun`` on the same host, or ``--url`` on another), ``off`` logs
nothing. Processes of one run that pass the same ``recording_id`` open as one recording.
Each process keeps its own :class:`rerun.RecordingStream` (never Rerun's global one), so a
library user's own Rerun logging is left alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

DEFAULT_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"


@dataclass(frozen=True)
class RecordingConfig:
    """Where Rerun logging goes."""

    sink: Literal["file", "grpc", "off"] = "file"
    """file: an .rrd (in the run directory unless --rrd says where); grpc: stream to a viewer
    at --viewer-url; off: no recording"""
    rrd: Path | None = None
    """the .rrd to write with sink=file"""
    viewer_url: str = DEFAULT_VIEWER_URL
    """a Rerun viewer's gRPC address, for sink=grpc (start one with `rerun`)"""
    recording_id: str | None = None
    """processes that share it open as one recording (default: one per process)"""


def open_recording(application: str, config: RecordingConfig, default_rrd: Path,
                   blueprint: Any = None) -> Any:
    """A RecordingStream with the configured sink, or None for sink=off."""
    if config.sink == "off":
        return None
    import rerun as rr

    stream = rr.RecordingStream(application, recording_id=config.recording_id)
    if config.sink == "file":
        path = config.rrd or default_rrd
        path.parent.mkdir(parents=True, exist_ok=True)
        stream.save(str(path), default_blueprint=blueprint)
    else:
        stream.set_sinks(rr.GrpcSink(config.viewer_url), default_blueprint=blueprint)
    return stream


def close_recording(stream: Any) -> None:
    """Flush and close: an .rrd gets its footer (a killed process leaves a readable file
    without one)."""
    if stream is None:
        return
    stream.flush()
    stream.disconnect()
