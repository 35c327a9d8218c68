"""overtake-spectate: a running server's arenas logged to Rerun, read back from the .rrd."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
import rerun as rr

import overtake.client  # noqa: F401  (registers the environments)
from overtake.client.wire.spectate import SpectateConfig
from overtake.client.wire.spectate import main as spectate
from overtake.envs import REMOTE_HIGHWAY_ENV_ID
from overtake.viz.recording import RecordingConfig
from overtake.viz.world_view import to_drawing

from tests.support.remote import logged_by_round, remote_config, wait_until

STEP_OFFSET = 5000  # the trainer's step count, far from the round numbers


@pytest.mark.timeout(90)
def test_spectate_logs_the_arena_and_the_lidar_the_trainer_received(start_server, tmp_path):
    server = start_server("spectate", world_rate_hz=50)
    rrd = tmp_path / "world.rrd"
    env = gym.make(
        REMOTE_HIGHWAY_ENV_ID,
        overrides={"episode.max_decisions": 500},
        remote=remote_config(server.endpoint, server.name),
    )
    logged: list[int] = []
    watcher = threading.Thread(
        target=lambda: logged.append(
            spectate(
                SpectateConfig(
                    connect=(server.endpoint,),
                    server=server.name,
                    frames=8,
                    seconds=60,
                    recording=RecordingConfig(rrd=rrd),
                )
            )
        )
    )
    try:
        group = env.unwrapped.group
        env.reset(seed=3)
        seen: dict[int, tuple[np.ndarray, float]] = {}
        watcher.start()
        deadline = time.monotonic() + 60
        while watcher.is_alive() and time.monotonic() < deadline:
            # As a trainer does: its step count goes with the actions (protocol 1.2).
            env.unwrapped.label_step(STEP_OFFSET + group.round)
            obs, reward, *_ = env.step(1)
            seen[group.round] = (obs["lidar"], reward)
        watcher.join(timeout=30)
    finally:
        env.close()
    assert logged == [8]
    wait_until(rrd.exists, 5, "the .rrd")
    reader = rr.chunk.RrdReader(str(rrd))
    root = f"/world/{server.name}/arena{group.arena_ids[0]}"
    entities = {chunk.entity_path for chunk in reader.stream().to_chunks()}
    for name in (
        "road/cars",
        "road/lanes/marks",
        "road/agent0/lidar/hits",
        "road/agent0/lidar/rays",
        "agent0/camera",
        "agent0/speed_kmh",
        "agent0/reward/total",
        "agent0/action/cruise_up",
    ):
        assert f"{root}/{name}" in entities, name
    hits = logged_by_round(reader, f"{root}/road/agent0/lidar/hits", "Points2D:positions")
    rewards = logged_by_round(reader, f"{root}/agent0/reward/total", "Scalars:scalars")
    cars = logged_by_round(reader, f"{root}/road/cars", "Boxes2D:centers")
    steps = logged_by_round(reader, f"{root}/road/cars", "step")
    angles = np.arange(360) * (2 * np.pi / 360)
    matched = 0
    for round_, points in hits.items():
        if round_ not in seen:
            continue
        lidar, reward = seen[round_]
        points = np.asarray(points, dtype=np.float64)
        # The hits are the car's position plus the LIDAR distances the trainer received along
        # each ray, drawn as a map (y negated: left is up): what is left after taking the
        # distances away is one point, the car, at x = 0 (the view follows it).
        origin = points - to_drawing(np.stack([lidar * np.cos(angles), lidar * np.sin(angles)], 1))
        assert np.allclose(origin, origin[0], atol=1e-3)
        assert np.allclose(origin[0], cars[round_][0], atol=1e-3)  # the agent's box
        assert cars[round_][0][0] == pytest.approx(0.0)
        assert rewards[round_][0] == pytest.approx(reward)
        # The frame of round r came from the actions sent at round r - 1, with that step.
        assert steps[round_] == STEP_OFFSET + round_ - 1
        matched += 1
    assert matched >= 3, f"only {matched} logged rounds matched what the trainer saw"


def test_spectate_command_prints_what_is_wrong_and_exits_non_zero():
    """A process, as a user runs it (cli() installs signal handlers, not for a test process)."""
    done = subprocess.run(
        [sys.executable, "-m", "overtake.client.wire.spectate", "--arena", "1"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1, done
    assert done.stderr == "overtake-spectate: watching one arena needs its server's name\n"


def test_a_spectator_that_saw_no_arena_keeps_no_recording(start_server, tmp_path):
    server = start_server("spectate-empty", world_rate_hz=50)
    rrd = tmp_path / "world.rrd"
    config = SpectateConfig(
        connect=(server.endpoint,), server=server.name, seconds=1.0,
        recording=RecordingConfig(rrd=rrd),
    )  # fmt: skip
    assert spectate(config) == 0
    assert not rrd.exists()  # the next run's --rrd is free
