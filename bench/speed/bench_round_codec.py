"""What one round's Steps cost to hand over, apart from Zenoh: msgpack against the segment.

For min2018's real Steps of 1 and 64 arenas (both sensors), the median of a loop of each
operation a round needs on either path:

- over Zenoh: the server encodes the Steps, the trainer decodes them (``codec``);
- through the shared-memory channel (protocol 1.7): the server writes the arrays into the
  segment at the layout's places (``Segment.write_steps``), the trainer copies them back out
  into a Steps (``ShmChannel.take``); the doorbell's rings are not in it
  (``tests/ipc/test_shared_memory.py`` exercises them, ``bench.speed.bench_remote`` times
  whole rounds).

Zenoh's own cost of moving the bytes is not in it (``bench.speed.bench_shm``,
``bench.speed.bench_remote``).

    .venv/bin/python -m bench.speed.bench_round_codec [--repeats 300] [--json PATH]
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from bench.harness import write_report
from bench.speed.bench_sim import machine_description, pin_threads


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
    from overtake.client.wire.shm_channel import ShmChannel
    from overtake.ipc.shared_memory import Segment, channel_plan
    from overtake.protocol import codec
    from overtake.server.channels.shm_channel import steps_arrays

    steps = _steps(arenas)
    frame = codec.encode(steps)
    arrays = steps_arrays(steps)
    places, size = channel_plan(steps.agents.size, arrays)
    segment = Segment.create(size)
    segment.lay_out(places)
    reader = ShmChannel(Segment.attach(segment.name, segment.nonce, size), places, "bench", 1)
    try:
        rounds = iter(range(1, 10**9))

        def server_writes() -> None:
            assert segment.write_steps(next(rounds), steps_arrays(steps))

        def trainer_reads() -> None:
            server_writes()  # a new round each time (take returns each round once)
            assert reader.take(segment.steps_round()) is not None

        write_us = _median_us(server_writes, repeats)
        figures = {
            "steps_bytes": float(len(frame)),
            "zenoh_server_encode_us": _median_us(lambda: codec.encode(steps), repeats),
            "zenoh_trainer_decode_us": _median_us(lambda: codec.decode(frame), repeats),
            "shm_server_write_us": write_us,
            "shm_trainer_read_us": _median_us(trainer_reads, repeats) - write_us,
        }
    finally:
        reader.close(unlink=False)
        segment.unlink()
        segment.close()
    figures["zenoh_total_us"] = (
        figures["zenoh_server_encode_us"] + figures["zenoh_trainer_decode_us"]
    )
    figures["shm_total_us"] = figures["shm_server_write_us"] + figures["shm_trainer_read_us"]
    return figures


def main(config: RoundCodecConfig) -> dict[str, Any]:
    threads = pin_threads(1)
    results = {arenas: measure(arenas, config.repeats) for arenas in config.arenas}
    print(
        f"{'arenas':>6} {'Steps B':>8} {'Zenoh: encode + decode µs':>27} "
        f"{'shm channel: write + read µs':>30}"
    )
    for arenas, f in results.items():
        print(
            f"{arenas:>6} {f['steps_bytes']:>8.0f} "
            f"{f['zenoh_server_encode_us']:>8.1f} + {f['zenoh_trainer_decode_us']:.1f} = "
            f"{f['zenoh_total_us']:.1f}".ljust(46)
            + f"{f['shm_server_write_us']:.1f} + {f['shm_trainer_read_us']:.1f} = "
            f"{f['shm_total_us']:.1f}"
        )
    report = {"machine": machine_description(), "threads": threads, "results": results}
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    main(tyro.cli(RoundCodecConfig))
