"""How large a recording of the road is: bytes and chunks per 1,000 arena-steps.

The same world frames (the ``min2018`` preset, several arenas, the agent keeping its lane,
both sensors, as a spectator records them with ``--no-rays``) are logged through the project's
:class:`~overtake.viz.world_view.WorldRecording` twice, into two ``.rrd`` files:

- with Rerun's default chunk batcher (flush every 0.2 s or 2 MiB), which is how recordings
  were written before (the 2-minute demo's ``world.rrd``: 22,573 chunks, 45 MB);
- with the project's file sink (:func:`overtake.viz.recording.open_recording`: flush every
  5 s or 8 MiB).

It prints bytes and chunks per 1,000 arena-steps for each and their ratio, and the seconds
logging took (the logging thread's cost, not the simulation's).

    .venv/bin/python -m bench.speed.bench_recording_size [--arenas 6] [--rounds 600] [--json PATH]
"""

from __future__ import annotations

import json
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np


@dataclass(frozen=True)
class SizeBenchConfig:
    arenas: int = 6
    """arenas recorded, as the demo's spectator does"""
    rounds: int = 600
    """decisions per arena"""
    json: Path | None = None
    """also write the figures here"""


def world_frames(arenas: int, rounds: int) -> list[Any]:
    """The frames a server publishes for ``arenas`` arenas over ``rounds`` rounds."""
    from overtake.server.engine.world import group_world_frame
    from overtake.server.service.groups import Group

    group = Group.open(0, "bench", list(range(arenas)), "min2018", {}, 1, seed=0)
    sim = group.sim
    for arena in range(arenas):
        sim.respawn_agents(arena, [0])
    frames = []
    keep = np.zeros((arenas, 1), dtype=np.int64)
    for round_ in range(rounds):
        sim.step(keep)
        group.rounds.round = round_ + 1
        group.trainer_step = round_ * arenas
        observations = sim.observe()
        frames += [group_world_frame(group, arena, observations) for arena in range(arenas)]
    return frames


def record(frames: list[Any], path: Path, batcher: Any | None) -> tuple[int, int, float]:
    """Log ``frames`` to ``path``: (bytes, chunks, seconds spent logging)."""
    import rerun as rr

    from overtake.viz.recording import APPLICATION_ID, RecordingConfig, open_recording
    from overtake.viz.world_view import WorldRecording

    if batcher is None:
        recording = open_recording(APPLICATION_ID, RecordingConfig(rrd=path), path)
        assert recording is not None
        stream, close = recording.stream, recording.close
    else:
        stream = rr.RecordingStream(APPLICATION_ID, batcher_config=batcher)
        stream.save(str(path))

        def close() -> None:
            stream.flush(timeout_sec=30)
            stream.disconnect()

    view = WorldRecording(stream, rays=False)
    start = time.perf_counter()
    for frame in frames:
        view.log(frame)
    close()
    seconds = time.perf_counter() - start
    chunks = len(rr.chunk.RrdReader(str(path)).stream().to_chunks())
    return path.stat().st_size, chunks, seconds


def main(config: SizeBenchConfig) -> dict[str, Any]:
    import rerun as rr

    frames = world_frames(config.arenas, config.rounds)
    steps = config.arenas * config.rounds
    with tempfile.TemporaryDirectory() as scratch:
        before = record(frames, Path(scratch) / "default.rrd", rr.ChunkBatcherConfig.DEFAULT())
        after = record(frames, Path(scratch) / "project.rrd", None)
    per_k = 1000 / steps
    result = {
        "arenas": config.arenas,
        "rounds": config.rounds,
        "arena_steps": steps,
        "default_batcher": {
            "bytes_per_1000_steps": before[0] * per_k,
            "chunks_per_1000_steps": before[1] * per_k,
            "logging_s": before[2],
        },
        "project_file_sink": {
            "bytes_per_1000_steps": after[0] * per_k,
            "chunks_per_1000_steps": after[1] * per_k,
            "logging_s": after[2],
        },
        "size_ratio": after[0] / before[0],
        "chunk_ratio": after[1] / before[1],
        "machine": platform.platform(),
        "rerun": rr.__version__,
    }
    for name in ("default_batcher", "project_file_sink"):
        figures = result[name]
        print(
            f"{name:>18}: {figures['bytes_per_1000_steps'] / 1e6:6.2f} MB and "
            f"{figures['chunks_per_1000_steps']:7.1f} chunks per 1,000 arena-steps, "
            f"logged in {figures['logging_s']:.1f} s"
        )
    print(f"project / default: size {result['size_ratio']:.3f}, chunks {result['chunk_ratio']:.4f}")
    if config.json is not None:
        config.json.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    import tyro

    main(tyro.cli(SizeBenchConfig))
