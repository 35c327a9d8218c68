"""Rerun recording sinks, and a server logging its arenas directly, read back from the .rrd."""

from __future__ import annotations

import logging
import signal
import urllib.request
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import rerun as rr

import overtake.client  # noqa: F401  (registers the environments)
from overtake.envs import REMOTE_HIGHWAY_ENV_ID
from overtake.protocol.messages import WorldFrame
from overtake.viz.recording import (
    Recording,
    RecordingConfig,
    RecordingError,
    open_recording,
    viewer_binary,
)

from tests.support.remote import (
    blueprint_texts,
    free_port,
    logged_by_round,
    remote_config,
    stop_process,
    wait_until,
)


@pytest.mark.timeout(120)
def test_server_records_its_arenas_with_reward_terms_decimated(start_server, tmp_path):
    rrd = tmp_path / "server.rrd"
    server = start_server(
        "recorder", extra=("--sink", "file", "--rrd", str(rrd), "--record-every", "3")
    )
    env = gym.make(REMOTE_HIGHWAY_ENV_ID, remote=remote_config(server.endpoint, server.name))
    seen: dict[int, tuple[np.ndarray, float, dict[str, float]]] = {}
    try:
        group = env.unwrapped.group
        _, info = env.reset(seed=1)
        for _ in range(30):
            # Lane changes in recorded rounds where allowed, so that term is not always zero.
            mask = info["action_mask"]
            lateral = [a for a in (3, 4) if mask[a]]
            action = lateral[0] if lateral and (group.round + 1) % 3 == 0 else 1
            obs, reward, terminated, truncated, info = env.step(action)
            seen[group.round] = (obs["lidar"], reward, dict(info["reward_terms"]))
            assert not (terminated or truncated)
        arena = group.arena_ids[0]
    finally:
        env.close()
    server.stop()  # SIGTERM: the server closes the recording (written without a footer)
    assert server.proc.returncode == 0, server.log_text()[-2000:]
    assert "recorded" in server.log_text() and "0 dropped" in server.log_text()

    reader = rr.chunk.RrdReader(str(rrd))
    root = f"/world/recorder/arena{arena}"
    hits = logged_by_round(reader, f"{root}/road/agent0/lidar/hits", "Points2D:positions")
    cars = logged_by_round(reader, f"{root}/road/cars", "Boxes2D:centers")
    sizes = logged_by_round(reader, f"{root}/road/cars", "Boxes2D:half_sizes")
    rewards = logged_by_round(reader, f"{root}/agent0/reward/total", "Scalars:scalars")
    terms = {
        name: logged_by_round(reader, f"{root}/agent0/reward/{name}", "Scalars:scalars")
        for name in seen[max(seen)][2]
    }
    # Every third round, and only those.
    assert sorted(hits) == [r for r in sorted(seen) if r % 3 == 0]
    for round_, points in hits.items():
        lidar, reward, reward_terms = seen[round_]
        points, agent = np.asarray(points), np.asarray(cars[round_][0])
        # The road is drawn around agent 0 (x = 0), and every car gets a box of its own: one
        # half-size for N centres would draw one box, the traffic invisible.
        assert agent[0] == pytest.approx(0.0)
        assert len(sizes[round_]) == len(cars[round_]) > 1
        assert np.allclose(sizes[round_][0], [2.25, 0.9])
        # Each hit lies its reading away from the agent's box (whatever the car's heading),
        # and the ray to the left (a quarter of the scan) is drawn upward: -y, as on a map.
        assert np.allclose(np.linalg.norm(points - agent, axis=1), lidar, atol=1e-3)
        assert points[len(lidar) // 4][1] < agent[1]
        assert rewards[round_][0] == pytest.approx(reward)
        for name, value in reward_terms.items():
            assert terms[name][round_][0] == pytest.approx(value), (round_, name)
    assert any(terms["lane_change"][r][0] != 0 for r in hits)  # the lane change was logged
    assert sum(v[0] for v in terms["speed"].values()) > 0
    # The recording lays its arena out (the road, agent 0's camera, LIDAR and plots).
    assert any(
        {f"{root}/road", f"{root}/agent0/camera", f"{root}/agent0/speed_kmh"}
        <= blueprint_texts(reader, store)
        for store in reader.blueprints()
    )


def listening_addresses(port: int) -> set[str]:
    """IPv4 addresses with a socket listening on ``port`` (from /proc/net/tcp)."""
    out = set()
    for line in Path("/proc/net/tcp").read_text().splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        address, port_hex = local.split(":")
        if state == "0A" and int(port_hex, 16) == port:  # 0A: LISTEN
            out.add(".".join(str(b) for b in reversed(bytes.fromhex(address))))
    return out


@pytest.mark.timeout(60)
def test_web_sink_serves_the_viewer_on_loopback_and_stops_it(tmp_path):
    web_port, grpc_port = free_port(), free_port()
    config = RecordingConfig(sink="web", web_port=web_port, web_grpc_port=grpc_port)
    recording = open_recording("overtake-test", config, tmp_path / "unused.rrd")
    assert isinstance(recording, Recording) and recording.viewer is not None
    viewer = recording.viewer
    try:
        assert viewer.args[0] == viewer_binary()  # the binary, not the Python wrapper
        recording.stream.log("probe", rr.Scalars(1.0))
        wait_until(lambda: listening_addresses(web_port), 20, "the web viewer's port")
        assert listening_addresses(grpc_port) == {"127.0.0.1"}
        assert listening_addresses(web_port) == {"127.0.0.1"}
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
    finally:
        recording.close()
        if viewer.poll() is None:  # close() failed to stop it: do it here and fail below
            stop_process(viewer)
    assert viewer.returncode is not None
    assert not listening_addresses(grpc_port)
    assert not (tmp_path / "unused.rrd").exists()


@pytest.mark.timeout(60)
def test_closing_a_recording_whose_viewer_died_does_not_raise(tmp_path, caplog):
    config = RecordingConfig(sink="web", web_port=free_port(), web_grpc_port=free_port())
    recording = open_recording("overtake-test", config, tmp_path / "unused.rrd")
    stop_process(recording.viewer, sig=signal.SIGKILL)  # as a viewer closed under a trainer
    for step in range(50):
        recording.stream.set_time("step", sequence=step)
        recording.stream.log("probe", rr.Scalars(float(step)))
    with caplog.at_level(logging.WARNING, logger="overtake.recording"):
        recording.close()  # a warning, not an exception that would end a training run
    # The warning says what was lost: the data logged after the viewer went.
    [warning] = [r for r in caplog.records if r.name == "overtake.recording"]
    assert warning.levelno == logging.WARNING
    assert "could not be flushed" in warning.getMessage()
    assert "the last logged data may be missing" in warning.getMessage()


def test_web_sink_refuses_a_taken_port(tmp_path):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(RecordingError, match=f"port {port} on 127.0.0.1 is already taken"):
            open_recording(
                "overtake-test",
                RecordingConfig(sink="web", web_grpc_port=port),
                tmp_path / "unused.rrd",
            )


def test_recording_config_refuses_no_decimation():
    with pytest.raises(ValueError, match="record_every must be >= 1, got 0"):
        RecordingConfig(record_every=0)


def small_frame(round_: int, arena: int = 0) -> WorldFrame:
    return WorldFrame(
        server="s",
        group=0,
        arena=arena,
        round=round_,
        sim_time_s=0.4 * round_,
        lane_count=5,
        lane_width_m=3.5,
        agent_kind=3,
        agent_active=np.ones(1, bool),
        x_m=np.zeros(2),
        y_m=np.ones(2),
        speed_mps=np.zeros(2, np.float32),
        kind=np.array([3, 0], np.int8),
        active=np.ones(2, bool),
        observations={},
        reward=np.ones(1),
        action_applied=np.zeros(1, np.int64),
    )


def test_server_recorder_drops_and_counts_what_it_cannot_keep_up_with(tmp_path, caplog):
    import threading

    from overtake.server.service import recorder as recorder_module

    recorder = recorder_module.ServerRecorder(
        RecordingConfig(sink="file", rrd=tmp_path / "s.rrd"), "s"
    )
    release = threading.Event()
    logged_rounds: list[int] = []
    real_log = recorder.view.log

    def slow_log(frame):  # a logging thread that has fallen behind
        release.wait(30)
        real_log(frame)
        logged_rounds.append(frame.round)

    recorder.view.log = slow_log
    offered = recorder_module.QUEUE_FRAMES + 20
    with caplog.at_level(logging.WARNING, logger="overtake.server.service.recorder"):
        kept = [recorder.offer(small_frame(r)) for r in range(offered)]
    assert not recorder.has_room()
    # The thread holds one frame, the queue the next QUEUE_FRAMES; the rest are dropped.
    assert recorder.dropped == offered - sum(kept) >= 19
    assert any("dropped" in r.message for r in caplog.records)
    release.set()
    recorder.close()
    assert recorder.logged == sum(kept) == len(logged_rounds)
    assert logged_rounds == sorted(logged_rounds)  # in order, none twice
    reader = rr.chunk.RrdReader(str(tmp_path / "s.rrd"))
    assert {c.entity_path for c in reader.stream().to_chunks()} >= {"/world/s/arena0/road/cars"}


def test_server_recording_lays_out_each_arena_as_it_appears(tmp_path, monkeypatch):
    from overtake.server.service import recorder as recorder_module
    from overtake.viz import world_view

    monkeypatch.setattr(world_view, "BLUEPRINT_ARENAS", 2)
    recorder = recorder_module.ServerRecorder(
        RecordingConfig(sink="file", rrd=tmp_path / "s.rrd"), "s"
    )
    for round_ in range(3):
        for arena in (7, 3, 9):  # 9 appears last: 7, the oldest, leaves the layout
            recorder.offer(small_frame(round_, arena))
    recorder.close()
    reader = rr.chunk.RrdReader(str(tmp_path / "s.rrd"))
    # One layout each time an arena appeared (the .rrd lists them in no particular order):
    # 7; 7 and 3; then 3 and 9, the oldest (7) dropped. Arenas seen before send none again.
    layouts = [blueprint_texts(reader, store) for store in reader.blueprints()]
    laid_out = sorted(
        sorted(a for a in (3, 7, 9) if f"/world/s/arena{a}/road" in texts) for texts in layouts
    )
    assert laid_out == [[3, 7], [3, 9], [7]]
    both = next(
        texts
        for texts in layouts
        if "/world/s/arena7/road" in texts and "/world/s/arena3/road" in texts
    )
    assert {"s arena 3", "s arena 7", "all roads", "/world/s/arena3/agent0/speed_kmh"} <= both
    assert "/world/s/arena3/agent0/camera" not in both  # the frames carry no camera
    # Arena 7 is recorded all the same.
    assert "/world/s/arena7/road/cars" in {c.entity_path for c in reader.stream().to_chunks()}
