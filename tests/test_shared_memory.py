"""Steps through shared memory for a trainer on the server's host (protocol 1.6): the segment
(its permissions, name, layout and guards), the transport choice (auto, shm, zenoh) with its
fallbacks, remote equal to in-process on both transports, and segments that outlive neither a
killed trainer nor a killed server."""

from __future__ import annotations

import dataclasses
import os
import signal
import stat
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.protocol import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, codec, errors
from overtake.protocol.errors import DecodeError
from overtake.protocol.messages import ShmArray, ShmOffer, Steps, StepsInShm
from overtake.protocol.shared_memory import (
    HEADER_BYTES,
    NAME_PREFIX,
    Segment,
    layout_bytes,
    shm_dir,
    sweep_orphans,
)
from overtake.protocol.shm_messages import STEPS_ARRAYS

from remote_support import remote_config, trainer_args, wait_until

SHORT = {"episode.max_decisions": 40}


def segments_of(pid: int) -> list[Path]:
    """The segments a process (a server) created that still have a name in shared memory:
    what would be left there if everything ended now."""
    return sorted(shm_dir().glob(f"{NAME_PREFIX}{pid}-*"))


def held_segments(holder: int, creator: int) -> list[str]:
    """The segments ``creator`` made that process ``holder`` has mapped, named or not (a name
    goes once the trainer has said whether it reads the segment; the memory stays mapped)."""
    prefix = str(shm_dir() / f"{NAME_PREFIX}{creator}-")
    try:
        maps = Path(f"/proc/{holder}/maps").read_text().splitlines()
    except OSError:
        return []
    return sorted({line.split(maxsplit=5)[-1] for line in maps if prefix in line})


# --- the segment --------------------------------------------------------------------------------


def test_a_segment_is_private_unguessable_and_round_trips_every_wire_dtype():
    arrays = {
        "agents": np.arange(3, dtype=np.int32),
        "reward": np.array([0.5, -1.0, 2.0]),
        "terminated": np.array([True, False, True]),
        "action_mask": np.ones((3, 5), dtype=np.int8),
        "obs/camera": np.arange(3 * 8 * 8, dtype=np.uint8).reshape(3, 8, 8),
        "obs/lidar": np.linspace(0, 1, 3 * 7, dtype=np.float32).reshape(3, 7),
        "metrics": np.zeros((3, 0)),
        "action_applied": np.array([-1, 2, 4], dtype=np.int64),
    }
    size = layout_bytes((v.dtype, v.shape) for v in arrays.values())
    writer = Segment.create(size)
    try:
        mode = stat.S_IMODE(os.stat(writer.path).st_mode)
        assert mode == 0o600, oct(mode)
        pid, random_part = writer.name.removeprefix(NAME_PREFIX).split("-")
        assert int(pid) == os.getpid() and len(random_part) == 32
        reader = Segment.attach(writer.name, writer.nonce, writer.size)
        written = writer.write(arrays)
        assert written is not None
        generation, places = written
        assert generation == 2 and all(offset % 64 == 0 for _, offset, _, _ in places)
        got = reader.read(generation, places)
        for name, value in arrays.items():
            assert got[name].dtype == value.dtype and np.array_equal(got[name], value), name
        # Copies: the next write does not change what was read.
        arrays["reward"][:] = 9.0
        assert writer.write(arrays) is not None
        assert got["reward"][0] == 0.5
        reader.close()
    finally:
        writer.unlink()
        writer.close()
    assert not writer.path.exists()


def test_a_segment_refuses_what_is_not_the_offer_and_torn_or_outside_reads():
    writer = Segment.create(HEADER_BYTES + 256)
    try:
        with pytest.raises(DecodeError, match="another nonce"):
            Segment.attach(writer.name, bytes(16), writer.size)
        with pytest.raises(DecodeError, match="the offer said"):
            Segment.attach(writer.name, writer.nonce, writer.size + 64)
        with pytest.raises(FileNotFoundError):
            Segment.attach(writer.name + "x", writer.nonce, writer.size)
        with pytest.raises(DecodeError, match="plain file name"):
            Segment.attach("../etc", writer.nonce, writer.size)
        # Too big for the segment: the caller is told (None) and sends the frame instead.
        assert writer.write({"obs/x": np.zeros(1000)}) is None
        written = writer.write({"reward": np.ones(4)})
        assert written is not None
        generation, places = written
        reader = Segment.attach(writer.name, writer.nonce, writer.size)
        with pytest.raises(DecodeError, match="holds write 2, the notice names 4"):
            reader.read(4, places)
        with pytest.raises(DecodeError, match="outside segment"):
            reader.read(generation, [("reward", HEADER_BYTES, "float64", (1000,))])
        with pytest.raises(DecodeError, match="not a wire dtype"):
            reader.read(generation, [("reward", HEADER_BYTES, "float16", (4,))])
        reader.close()
    finally:
        writer.unlink()
        writer.close()


def test_the_notices_decode_and_refuse_what_they_must():
    # Every array of a Steps has its place in a notice: a field added to Steps without one
    # would not reach a trainer reading shared memory.
    names = [
        f.name
        for f in dataclasses.fields(Steps)
        if f.name not in ("server", "group", "round", "observations")
    ]
    assert tuple(names) == STEPS_ARRAYS
    arrays = tuple(ShmArray(name=n, offset=64, dtype="int8", shape=(1,)) for n in names)
    notice = StepsInShm(server="s", group=3, round=5, generation=2, arrays=arrays)
    assert codec.decode(codec.encode(notice), StepsInShm) == notice
    with pytest.raises(DecodeError, match="missing \\['metrics'\\]"):
        StepsInShm(server="s", group=3, round=5, generation=2, arrays=arrays[:-1])
    with pytest.raises(DecodeError, match="array name must be one of"):
        ShmArray(name="secret", offset=64, dtype="int8", shape=(1,))
    with pytest.raises(DecodeError, match="offset must be from 64"):
        ShmArray(name="obs/lidar", offset=0, dtype="int8", shape=(1,))
    with pytest.raises(DecodeError, match="nonce is 16 bytes"):
        ShmOffer(name="overtake-1-ab", nonce=b"x", size_bytes=128)
    with pytest.raises(DecodeError, match="segment name"):
        ShmOffer(name="../../etc/passwd", nonce=bytes(16), size_bytes=128)


def test_the_sweep_removes_only_segments_of_processes_that_are_gone(tmp_path, monkeypatch):
    monkeypatch.setenv("OVERTAKE_SHM_DIR", str(tmp_path))
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"],
        check=True,
        capture_output=True,
        text=True,
    )
    dead_pid = int(gone.stdout)
    orphan = tmp_path / f"{NAME_PREFIX}{dead_pid}-{'0' * 32}"
    orphan.write_bytes(b"x")
    live = Segment.create(HEADER_BYTES)
    stranger = tmp_path / "other-file"
    stranger.write_bytes(b"y")
    try:
        assert sweep_orphans() == [orphan.name]
        assert not orphan.exists() and live.path.exists() and stranger.exists()
    finally:
        live.unlink()
        live.close()


# --- the transport, end to end -------------------------------------------------------------------


@pytest.mark.timeout(90)
@pytest.mark.parametrize("transport", ["shm", "zenoh"])
def test_remote_equals_in_process_on_each_transport(start_server, transport):
    server = start_server(f"shm-bits-{transport}")
    n = 3
    remote = gym.make_vec(
        REMOTE_HIGHWAY_ENV_ID,
        num_envs=n,
        vectorization_mode="vector_entry_point",
        remote=remote_config(server.endpoint, server.name, steps_transport=transport),
        preset="min2018",
        overrides=SHORT,
    )
    local = gym.make_vec(
        HIGHWAY_ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", overrides=SHORT
    )
    try:
        group = remote.unwrapped.group
        assert group.shm == (transport == "shm")
        assert len(segments_of(server.proc.pid)) == (1 if transport == "shm" else 0)
        rng = np.random.default_rng(5)
        pid = server.proc.pid
        got, want = remote.reset(seed=3), local.reset(seed=3)
        for step in range(90):  # episodes end and restart on the way
            for name in want[0]:
                assert np.array_equal(got[0][name], want[0][name]), (step, name)
            actions = rng.integers(0, 5, size=n)
            got, want = remote.step(actions), local.step(actions)
            for index in (1, 2, 3):
                assert np.array_equal(got[index], want[index]), (step, index)
            # Once the trainer has said it reads the segment, its name is gone: both sides
            # hold the memory, and nothing is left in /dev/shm however they end.
            assert not segments_of(pid)
            held = 1 if transport == "shm" else 0
            assert len(held_segments(pid, pid)) == len(held_segments(os.getpid(), pid)) == held
        rounds = group.connection.rounds_through_shm
        assert rounds == (90 if transport == "shm" else 0)
    finally:
        remote.close()
        local.close()
    # Closing the group removes its segment.
    wait_until(lambda: not segments_of(server.proc.pid), 5.0, "the group's segment to go")


@pytest.mark.timeout(90)
def test_auto_reads_shared_memory_where_the_steps_are_large_enough_to_gain(start_server):
    from overtake.client.wire.shared_steps import AUTO_SHM_MIN_BYTES

    server = start_server("shm-auto")
    for arenas, through_shm in ((2, False), (40, True)):
        env = gym.make_vec(
            REMOTE_HIGHWAY_ENV_ID,
            num_envs=arenas,
            vectorization_mode="vector_entry_point",
            remote=remote_config(server.endpoint, server.name),
            preset="min2018",
        )
        try:
            group = env.unwrapped.group
            # The server offers a segment either way; auto takes it by its size.
            [segment] = segments_of(server.proc.pid)
            assert (segment.stat().st_size >= AUTO_SHM_MIN_BYTES) == through_shm
            assert group.shm is through_shm
            env.reset(seed=1)
            env.step(np.zeros(arenas, dtype=np.int64))
            assert group.connection.rounds_through_shm == (1 if through_shm else 0)
        finally:
            env.close()
        wait_until(lambda: not segments_of(server.proc.pid), 5.0, "the group's segment to go")


@pytest.mark.timeout(60)
def test_a_forged_notice_is_dropped_and_the_trainer_steps_on(start_server):
    from overtake.protocol import keys

    from remote_support import RawClient

    server = start_server("shm-forged")
    remote = gym.make(
        REMOTE_HIGHWAY_ENV_ID,
        remote=remote_config(server.endpoint, server.name, steps_transport="shm"),
        overrides=SHORT,
    )
    local = gym.make(HIGHWAY_ENV_ID, overrides=SHORT)
    raw = RawClient(server.endpoint)
    try:
        group = remote.unwrapped.group
        remote.reset(seed=2), local.reset(seed=2)
        key = keys.trainer_steps(group.connection.trainer, server.name)
        for step in range(20):
            # Anyone on the network may publish on the trainer's key: a notice naming another
            # write, and one pointing outside the segment.
            for generation, offset in ((10**6, 64), (2, 2**27)):
                forged = StepsInShm(
                    server=server.name,
                    group=group.group_id,
                    round=step + 1,
                    generation=generation,
                    arrays=tuple(
                        ShmArray(name=name, offset=offset, dtype="float64", shape=(1,))
                        for name in STEPS_ARRAYS
                    ),
                )
                raw.put(key, codec.encode(forged))
            got, want = remote.step(step % 5), local.step(step % 5)
            for name in want[0]:
                assert np.array_equal(got[0][name], want[0][name]), (step, name)
            assert got[1] == want[1]
        assert group.connection.rounds_through_shm == 20
        # Every forged notice dropped (the log says so once per 5 s; it is not read here: a
        # library earlier in the suite may have disabled the project's loggers).
        assert group.connection.dropped == 40
    finally:
        raw.close()
        remote.close()
        local.close()


@pytest.mark.timeout(60)
def test_a_trainer_that_cannot_reach_the_segment_falls_back_or_says_why(
    start_server, tmp_path, monkeypatch
):
    # The trainer looks for segments in another directory: a server in another container.
    server = start_server("shm-elsewhere")
    monkeypatch.setenv("OVERTAKE_SHM_DIR", str(tmp_path))
    env = gym.make(
        REMOTE_HIGHWAY_ENV_ID, remote=remote_config(server.endpoint, server.name), overrides=SHORT
    )
    try:
        assert env.unwrapped.group.shm is False  # auto: over Zenoh
        env.reset(seed=1)
        env.step(1)
    finally:
        env.close()
    with pytest.raises(errors.ConnectError, match="is the server on this host"):
        gym.make(
            REMOTE_HIGHWAY_ENV_ID,
            remote=remote_config(server.endpoint, server.name, steps_transport="shm"),
        )
    # The refused group was closed, not left open.
    wait_until(lambda: server.status().arenas_used == 0, 5.0, "the refused group to close")


@pytest.mark.timeout(60)
def test_a_server_without_shared_memory_offers_none(start_server):
    server = start_server("shm-off", extra=("--no-shared-memory",))
    env = gym.make(REMOTE_HIGHWAY_ENV_ID, remote=remote_config(server.endpoint, server.name))
    try:
        assert env.unwrapped.group.shm is False
        assert not segments_of(server.proc.pid)
    finally:
        env.close()
    with pytest.raises(errors.ConnectError, match="offered no shared memory"):
        gym.make(
            REMOTE_HIGHWAY_ENV_ID,
            remote=remote_config(server.endpoint, server.name, steps_transport="shm"),
        )


@pytest.mark.timeout(60)
def test_a_killed_trainer_leaves_no_segment_once_the_server_notices(start_server, start_trainer):
    server = start_server("shm-kill")
    victim = start_trainer(trainer_args(server, server.name, print_every=10), "victim")
    victim.expect("READY")
    victim.send("run")
    victim.expect("STEP")
    pid = server.proc.pid
    assert not segments_of(pid) and len(held_segments(pid, pid)) == 1
    assert victim.kill() == -signal.SIGKILL
    assert not segments_of(pid)  # nothing left behind, whatever happens next
    wait_until(lambda: not held_segments(pid, pid), 10.0, "the server to let the memory go")
    assert server.status().arenas_used == 0


@pytest.mark.timeout(60)
def test_a_killed_server_leaves_no_segment_once_the_trainer_notices(start_server):
    server = start_server("shm-server-kill")
    env = gym.make(REMOTE_HIGHWAY_ENV_ID, remote=remote_config(server.endpoint, server.name))
    pid = server.proc.pid
    try:
        env.reset(seed=0)
        env.step(1)
        assert not segments_of(pid) and len(held_segments(os.getpid(), pid)) == 1
        server.proc.send_signal(signal.SIGKILL)
        server.proc.wait(10)
        with pytest.raises(errors.ServerLost):
            for _ in range(1000):  # until the trainer notices the server's token went
                env.step(1)
    finally:
        env.close()
    assert not segments_of(pid) and not held_segments(os.getpid(), pid)


def _zenoh_segments() -> set[str]:
    """Zenoh's own shared-memory segments (``<number>.zenoh``), whoever made them."""
    return {p.name for p in shm_dir().glob("*.zenoh")}


@pytest.mark.timeout(90)
@pytest.mark.parametrize("ending", ["clean", "SIGTERM", "SIGKILL"])
def test_nothing_is_left_in_dev_shm_however_a_trainer_and_its_server_end(
    start_server, start_trainer, ending
):
    """A trainer on the server's host (its Steps through shared memory) and the server end
    cleanly, on SIGTERM or on SIGKILL: neither leaves a segment of any kind, overtake's or
    Zenoh's (whose shared memory is off: TransportConfig.zenoh_shared_memory)."""
    zenoh_before = _zenoh_segments()
    server = start_server(f"shm-ends-{ending}")
    pid = server.proc.pid
    trainer = start_trainer(trainer_args(server, server.name, print_every=10), "trainer")
    trainer.expect("READY")
    trainer.send("run")
    trainer.expect("STEP")
    assert len(held_segments(pid, pid)) == 1  # the Steps do go through a segment
    signals = {"SIGTERM": signal.SIGTERM, "SIGKILL": signal.SIGKILL}
    if ending == "clean":
        trainer.send("exit")
        assert trainer.proc.wait(30) == 0
    else:
        trainer.proc.send_signal(signals[ending])
        trainer.proc.wait(30)
    assert not segments_of(pid)
    wait_until(lambda: not held_segments(pid, pid), 10.0, "the server to let the memory go")
    if ending == "SIGKILL":
        server.kill()
    else:
        server.proc.send_signal(signals.get(ending, signal.SIGTERM))
        server.proc.wait(30)
    assert not segments_of(pid)
    assert _zenoh_segments() <= zenoh_before
