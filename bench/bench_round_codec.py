"""What one round's Steps cost to hand over, apart from Zenoh: msgpack against the segment.

For min2018's real Steps of 1 and 64 arenas (both sensors), the median of a loop of each
operation a round needs on either path:

- over Zenoh: the server encodes the Steps, the trainer decodes them (``codec``);
- through shared memory: the server writes the arrays into a segment and builds and encodes
  the notice (``Segment.write``, ``StepsInShm``), the trainer decodes the notice and reads the
  arrays back out (``steps_from_notice``).

Zenoh's own cost of moving the bytes is not in it (``bench.bench_shm``, ``bench.bench_remote``).

    .venv/bin/python -m bench.bench_round_codec [--repeats 300] [--json PATH]
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from bench.bench_sim import machine_description, pin_threads, write_report


@dataclass(frozen=True)
class RoundCodecConfig:
    arenas: tuple[int, ...] = (1, 64)
    repeats: int = 300
    """timed calls of each operation (the median is reported)"""
    json: Path | None = None


def _median_us(operation: Callable[[], Any], repeats: int) -> float:
    operation()
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        operation()
        times.append(time.perf_counter() - started)
    return statistics.median(times) * 1e6


def _steps(arenas: int) -> Any:
    import gymnasium as gym
    import numpy as np

    import overtake.client  # noqa: F401 - registers the environments
    from overtake.protocol.messages import Steps
    from overtake.protocol.vocabulary import ACTION_COUNT, METRIC_FIELDS

    envs = gym.make_vec(
        "overtake/Highway-v0", num_envs=arenas, vectorization_mode="vector_entry_point"
    )
    obs, info = envs.reset(seed=0)
    terms = len(info["reward_terms"])
    envs.close()
    return Steps(
        server="bench",
        group=1,
        round=3,
        agents=np.arange(arenas, dtype=np.int32),
        observations=obs,
        reward=np.zeros(arenas),
        terminated=np.zeros(arenas, dtype=bool),
        truncated=np.zeros(arenas, dtype=bool),
        action_applied=np.zeros(arenas, dtype=np.int64),
        late=np.zeros(arenas, dtype=bool),
        action_mask=np.ones((arenas, ACTION_COUNT), dtype=np.int8),
        reward_terms=np.zeros((arenas, terms)),
        metrics=np.zeros((arenas, len(METRIC_FIELDS))),
    )


def measure(arenas: int, repeats: int) -> dict[str, float]:
    from overtake.client.wire.shared_steps import steps_from_notice
    from overtake.protocol import codec
    from overtake.protocol.messages import ShmArray, StepsInShm
    from overtake.protocol.shared_memory import Segment, layout_bytes
    from overtake.server.outbox import steps_arrays

    steps = _steps(arenas)
    frame = codec.encode(steps)
    arrays = steps_arrays(steps)
    segment = Segment.create(layout_bytes((v.dtype, v.shape) for v in arrays.values()))
    try:

        def notice_of(generation: int, places: Any) -> StepsInShm:
            return StepsInShm.trusted(
                server="bench",
                group=1,
                round=3,
                generation=generation,
                arrays=tuple(
                    ShmArray.trusted(name=n, offset=o, dtype=d, shape=s) for n, o, d, s in places
                ),
            )

        def server_writes() -> bytes:
            written = segment.write(steps_arrays(steps))
            assert written is not None
            return codec.encode(notice_of(*written))

        server_us = _median_us(server_writes, repeats)
        notice_frame = server_writes()
        notice = codec.decode(notice_frame)
        figures = {
            "steps_bytes": float(len(frame)),
            "notice_bytes": float(len(notice_frame)),
            "zenoh_server_encode_us": _median_us(lambda: codec.encode(steps), repeats),
            "zenoh_trainer_decode_us": _median_us(lambda: codec.decode(frame), repeats),
            "shm_server_write_and_notice_us": server_us,
            "shm_trainer_decode_notice_us": _median_us(lambda: codec.decode(notice_frame), repeats),
            "shm_trainer_read_us": _median_us(lambda: steps_from_notice(segment, notice), repeats),
        }
    finally:
        segment.unlink()
        segment.close()
    figures["zenoh_total_us"] = (
        figures["zenoh_server_encode_us"] + figures["zenoh_trainer_decode_us"]
    )
    figures["shm_total_us"] = (
        figures["shm_server_write_and_notice_us"]
        + figures["shm_trainer_decode_notice_us"]
        + figures["shm_trainer_read_us"]
    )
    return figures


def main(config: RoundCodecConfig) -> dict[str, Any]:
    threads = pin_threads(1)
    results = {arenas: measure(arenas, config.repeats) for arenas in config.arenas}
    print(
        f"{'arenas':>6} {'Steps B':>8} {'Zenoh: encode + decode µs':>27} "
        f"{'shm: write+notice + notice decode + read µs':>45}"
    )
    for arenas, f in results.items():
        print(
            f"{arenas:>6} {f['steps_bytes']:>8.0f} "
            f"{f['zenoh_server_encode_us']:>8.1f} + {f['zenoh_trainer_decode_us']:.1f} = "
            f"{f['zenoh_total_us']:.1f}".ljust(46)
            + f"{f['shm_server_write_and_notice_us']:.1f} + "
            f"{f['shm_trainer_decode_notice_us']:.1f} + {f['shm_trainer_read_us']:.1f} = "
            f"{f['shm_total_us']:.1f}"
        )
    report = {"machine": machine_description(), "threads": threads, "results": results}
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    main(tyro.cli(RoundCodecConfig))
