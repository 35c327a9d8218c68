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
from overtake.envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID
from overtake.ipc.doorbell import AVAILABLE as DOORBELL_AVAILABLE
from overtake.ipc.shared_memory import (
    ACTION_ARRAYS,
    ACTIONS_BELL_OFFSET,
    ACTIONS_COUNT_OFFSET,
    GENERATION_OFFSET,
    HEADER_BYTES,
    NAME_PREFIX,
    STEPS_BELL_OFFSET,
    STEPS_ROUND_OFFSET,
    Segment,
    channel_plan,
    shm_dir,
    sweep_orphans,
)
from overtake.protocol import codec, errors
from overtake.protocol.errors import DecodeError
from overtake.protocol.messages import ShmArray, ShmOffer, Steps
from overtake.protocol.shm_messages import ACTION_ARRAY_NAMES, STEPS_ARRAYS

from tests.support.remote import remote_config, trainer_args, wait_until

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
    places, size = channel_plan(3, arrays)
    assert [p[0] for p in places[:3]] == [name for name, _ in ACTION_ARRAYS]
    writer = Segment.create(size)
    try:
        mode = stat.S_IMODE(os.stat(writer.path).st_mode)
        assert mode == 0o600, oct(mode)
        pid, random_part = writer.name.removeprefix(NAME_PREFIX).split("-")
        assert int(pid) == os.getpid() and len(random_part) == 32
        reader = Segment.attach(writer.name, writer.nonce, writer.size)
        writer.lay_out(places)
        reader.lay_out(places)
        assert all(offset % 64 == 0 for _, offset, _, _ in places)
        assert writer.write_steps(7, arrays)
        assert writer.generation == 2
        round_, got = reader.read_steps(arrays)
        assert round_ == 7
        for name, value in arrays.items():
            assert got[name].dtype == value.dtype and np.array_equal(got[name], value), name
        # Copies: the next write does not change what was read.
        arrays["reward"][:] = 9.0
        assert writer.write_steps(8, arrays)
        assert got["reward"][0] == 0.5
        # The Actions the other way, as many as written (fewer than the cars, here).
        reader.write_actions(
            8,
            1234,
            np.array([2, 0], dtype=np.int32),
            np.array([4, 1], dtype=np.int64),
            np.array([1], dtype=np.int32),
        )
        round_, trainer_step, agents, actions, retire = writer.read_actions()
        assert (round_, trainer_step) == (8, 1234)
        assert agents.tolist() == [2, 0] and actions.tolist() == [4, 1] and retire.tolist() == [1]
        with pytest.raises(ValueError, match="at most 3 cars"):
            reader.write_actions(9, -1, np.zeros(4, np.int32), np.zeros(4, np.int64), _NONE)
        reader.close()
    finally:
        writer.unlink()
        writer.close()
    assert not writer.path.exists()


_NONE = np.zeros(0, dtype=np.int32)


def test_a_segment_refuses_what_is_not_the_offer_and_torn_or_outside_reads():
    places, size = channel_plan(2, {"reward": np.ones(2)})
    writer = Segment.create(size)
    writer.lay_out(places)
    try:
        with pytest.raises(DecodeError, match="another nonce"):
            Segment.attach(writer.name, bytes(16), writer.size)
        with pytest.raises(DecodeError, match="the offer said"):
            Segment.attach(writer.name, writer.nonce, writer.size + 64)
        with pytest.raises(FileNotFoundError):
            Segment.attach(writer.name + "x", writer.nonce, writer.size)
        with pytest.raises(DecodeError, match="plain file name"):
            Segment.attach("../etc", writer.nonce, writer.size)
        reader = Segment.attach(writer.name, writer.nonce, writer.size)
        # Nothing written yet, then arrays that are not the layout's: refused, nothing written.
        with pytest.raises(DecodeError, match="no finished write"):
            reader.read_steps(["reward"])
        assert not writer.write_steps(1, {"reward": np.ones(3)})
        assert not writer.write_steps(1, {"reward": np.ones(2, np.float32)})
        assert not writer.write_steps(1, {"rewards": np.ones(2)})
        assert writer.generation == 0
        # A layout from the wire that points outside the segment, off its alignment or at no
        # wire dtype is refused before any read.
        with pytest.raises(DecodeError, match="outside segment"):
            reader.lay_out([("reward", HEADER_BYTES, "float64", (10_000,))])
        with pytest.raises(DecodeError, match="alignment"):
            reader.lay_out([("reward", HEADER_BYTES + 8, "float64", (1,))])
        with pytest.raises(DecodeError, match="not a wire dtype"):
            reader.lay_out([("reward", HEADER_BYTES, "float16", (4,))])
        reader.lay_out(places)
        # A write under way (odd generation) is not read.
        assert writer.write_steps(1, {"reward": np.ones(2)})
        writer._i64[GENERATION_OFFSET // 8] += 1
        with pytest.raises(DecodeError, match="no finished write"):
            reader.read_steps(["reward"])
        # Counts out of range (the trainer's to write) are refused by the server.
        reader._i32[ACTIONS_COUNT_OFFSET // 4] = 3
        with pytest.raises(DecodeError, match="at most 2"):
            writer.read_actions()
        reader.close()
    finally:
        writer.unlink()
        writer.close()
    # A 1.6 peer's segment (another magic) is refused as such.
    old = Segment.create(HEADER_BYTES)
    try:
        old.memory[:8] = b"OVTKSHM1"
        with pytest.raises(DecodeError, match="another protocol version"):
            Segment.attach(old.name, old.nonce, old.size)
    finally:
        old.unlink()
        old.close()


def _ring_back(name: str, nonce: bytes, size: int, rounds: int) -> None:
    """In another process: answer each ring of the Steps bell with a ring of the Actions bell,
    counting the rounds in the actions' round field."""
    segment = Segment.attach(name, nonce, size)
    steps_bell, actions_bell = segment.bell(STEPS_BELL_OFFSET), segment.bell(ACTIONS_BELL_OFFSET)
    # Counted from 0, not from its value now: the first ring may come before this one looks.
    for seen in range(rounds):
        while steps_bell.value == seen:
            steps_bell.wait(seen, 5.0)
        actions_bell.ring()
    segment.close()


def _two_cars_round() -> dict[str, np.ndarray]:
    """A round's arrays for two cars, as a segment's layout names them (rewards of 1)."""
    return {
        "agents": np.arange(2, dtype=np.int32),
        "reward": np.ones(2),
        "terminated": np.zeros(2, dtype=bool),
        "truncated": np.zeros(2, dtype=bool),
        "action_applied": np.zeros(2, dtype=np.int64),
        "late": np.zeros(2, dtype=bool),
        "action_mask": np.ones((2, 5), dtype=np.int8),
        "reward_terms": np.zeros((2, 0)),
        "metrics": np.zeros((2, 0)),
        "obs/lidar": np.zeros((2, 4), dtype=np.float32),
    }


@pytest.mark.skipif(not DOORBELL_AVAILABLE, reason="no futex doorbell on this machine")
def test_a_round_whose_write_is_not_finished_is_waited_for_not_an_error():
    """The server writes a round's number before the generation that closes the write: a
    trainer looking in between (it spins on the segment) sees its round and an odd generation.
    That is "not yet", not a broken segment (the fault matrix's no-fault case once ended a
    trainer with 'holds no finished write')."""
    from overtake.client.wire.shm_channel import ShmChannel

    arrays = _two_cars_round()
    assert set(STEPS_ARRAYS) < set(arrays)
    places, size = channel_plan(2, arrays)
    writer = Segment.create(size)
    try:
        writer.lay_out(places)
        channel = ShmChannel(Segment.attach(writer.name, writer.nonce, writer.size), places, "s", 1)
        assert writer.write_steps(1, arrays)
        # Round 2's write stopped where the race caught it: its number down, the generation
        # still odd.
        index = GENERATION_OFFSET // 8
        writer._i64[index] += 1
        writer._i64[STEPS_ROUND_OFFSET // 8] = 2
        assert channel.take(2) is None
        writer._i64[index] += 1  # the write closes
        steps = channel.take(2)
        assert steps is not None and steps.round == 2 and steps.reward.tolist() == [1.0, 1.0]
        channel.close(unlink=False)
    finally:
        writer.unlink()
        writer.close()


class _Recorded:
    """A member's Zenoh channel that keeps what it is given (the server's fallback)."""

    def __init__(self) -> None:
        self.sent: list[object] = []

    def send_steps(self, steps: Steps) -> None:
        self.sent.append(steps)

    def send(self, message: object) -> None:
        self.sent.append(message)

    def close(self) -> None:
        pass


@pytest.mark.skipif(not DOORBELL_AVAILABLE, reason="no futex doorbell on this machine")
def test_the_server_hears_a_ring_on_its_thread_only_while_its_loop_sleeps():
    """A ring's thread on the server side is off the bell while the service loop runs (the
    loop looks at rung() itself: a woken thread took the GIL from the round, which made a
    64-arena round 13-29% slower here), and turns a ring into on_ring while the loop sleeps,
    once."""
    from overtake.client.wire.shm_channel import attach
    from overtake.protocol.messages import Actions
    from overtake.protocol.rows import row_values
    from overtake.server.channels import ChannelTerms
    from overtake.server.channels.shm_channel import ShmChannel as ServerShmChannel

    arrays = _two_cars_round()
    rings: list[tuple[str, int]] = []
    terms = ChannelTerms(
        trainer="t",
        ticket=b"ticket",
        current=Steps(server="s", group=1, round=0, **row_values(arrays)),
        fallback=_Recorded(),
        on_ring=lambda trainer, group: rings.append((trainer, group)),
    )
    server = ServerShmChannel.create(terms)
    trainer = attach("s", 1, server.offer(), required=True)
    assert trainer is not None

    def ring(round_: int) -> None:
        trainer.send_actions(
            Actions(
                trainer="t",
                ticket=b"ticket",
                group=1,
                round=round_,
                agents=np.arange(2, dtype=np.int32),
                actions=np.array([1, 2]),
            )
        )

    def heard(count: int, timeout_s: float) -> bool:
        try:
            wait_until(lambda: len(rings) >= count, timeout_s, f"{count} ring(s) heard")
        except AssertionError:
            return False
        return True

    try:
        ring(0)  # the loop runs: nobody is woken, the loop finds it with rung()
        assert server.rung()
        assert not heard(1, 0.3)
        server.hear_rings(True)  # the loop goes to sleep with a ring not taken: heard at once
        assert heard(1, 5.0) and rings == [("t", 1)]
        assert server.actions().actions.tolist() == [1, 2] and not server.rung()
        ring(1)  # asleep: a new ring is heard, once
        assert heard(2, 5.0)
        assert not heard(3, 0.3)
        server.actions()
        server.hear_rings(False)
        ring(2)
        assert server.rung() and not heard(3, 0.3)
    finally:
        server.close()
        trainer.close(unlink=False)
    assert len(rings) == 2


def test_the_doorbell_wakes_another_process_and_times_out_without_a_ring():
    import multiprocessing
    import time

    segment = Segment.create(HEADER_BYTES)
    try:
        steps_bell, actions_bell = (
            segment.bell(STEPS_BELL_OFFSET),
            segment.bell(ACTIONS_BELL_OFFSET),
        )
        # Nobody rings: the wait ends at its timeout with the value it was given.
        started = time.monotonic()
        assert actions_bell.wait(actions_bell.value, 0.05) == 0
        assert time.monotonic() - started >= 0.04
        # A value that moved on returns at once.
        assert actions_bell.wait(5, 10.0) == 0
        rounds = 200
        peer = multiprocessing.get_context("spawn").Process(
            target=_ring_back, args=(segment.name, segment.nonce, segment.size, rounds)
        )
        peer.start()
        try:
            seen = actions_bell.value
            for _ in range(rounds):
                steps_bell.ring()
                while actions_bell.value == seen:
                    actions_bell.wait(seen, 5.0)
                seen = actions_bell.value
            assert seen == rounds and steps_bell.value == rounds
        finally:
            peer.join(10)
            if peer.exitcode is None:
                peer.kill()
            assert peer.exitcode == 0
        # The word wraps at 2**32 like the waiter's comparison expects, without a warning.
        bell_word = np.frombuffer(segment.memory, "<u4", count=1, offset=STEPS_BELL_OFFSET)
        bell_word[0] = 2**32 - 1
        steps_bell.ring()
        assert steps_bell.value == 0
        del bell_word
    finally:
        segment.unlink()
        segment.close()


def test_the_offer_decodes_and_refuses_what_it_must():
    # Every array of a Steps has its place in a layout: a field added to Steps without one
    # would not reach a trainer reading shared memory.
    names = [
        f.name
        for f in dataclasses.fields(Steps)
        if f.name not in ("server", "group", "round", "observations")
    ]
    assert tuple(names) == STEPS_ARRAYS
    layout = tuple(
        ShmArray(name=n, offset=128 + 64 * i, dtype="int8", shape=(1,))
        for i, n in enumerate((*ACTION_ARRAY_NAMES, *names))
    )
    ShmOffer(name="overtake-1-ab", nonce=bytes(16), size_bytes=4096, layout=layout)
    with pytest.raises(DecodeError, match="missing \\['metrics'\\]"):
        ShmOffer(name="overtake-1-ab", nonce=bytes(16), size_bytes=4096, layout=layout[:-1])
    with pytest.raises(DecodeError, match="missing \\['actions/retire'\\]"):
        ShmOffer(
            name="overtake-1-ab", nonce=bytes(16), size_bytes=4096, layout=layout[:2] + layout[3:]
        )
    with pytest.raises(DecodeError, match="array name must be one of"):
        ShmArray(name="secret", offset=128, dtype="int8", shape=(1,))
    with pytest.raises(DecodeError, match="offset must be from 128"):
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
        remote=remote_config(server.endpoint, server.name, transport=transport),
        preset="min2018",
        overrides=SHORT,
    )
    local = gym.make_vec(
        HIGHWAY_ENV_ID, num_envs=n, vectorization_mode="vector_entry_point", overrides=SHORT
    )
    try:
        group = remote.unwrapped.group
        assert group.transport == ("shm" if transport == "shm" else "zenoh")
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
        rounds = group.connection.rounds_through("shm")
        assert rounds == (90 if transport == "shm" else 0)
    finally:
        remote.close()
        local.close()
    # Closing the group removes its segment.
    wait_until(lambda: not segments_of(server.proc.pid), 5.0, "the group's segment to go")


@pytest.mark.timeout(90)
def test_auto_takes_the_shared_memory_channel_at_every_size(start_server):
    """Measured (bench/RESULTS.md, issue 47): with the doorbell the channel gains at 1, 8 and
    64 arenas, so ``auto`` takes it wherever the segment can be attached."""
    server = start_server("shm-auto")
    for arenas in (1, 40):
        env = gym.make_vec(
            REMOTE_HIGHWAY_ENV_ID,
            num_envs=arenas,
            vectorization_mode="vector_entry_point",
            remote=remote_config(server.endpoint, server.name),
            preset="min2018",
        )
        try:
            group = env.unwrapped.group
            assert group.transport == "shm"
            env.reset(seed=1)
            env.step(np.zeros(arenas, dtype=np.int64))
            assert not segments_of(server.proc.pid)  # read: its name went at the first Actions
            assert group.connection.rounds_through("shm") == 1
        finally:
            env.close()
        wait_until(lambda: not segments_of(server.proc.pid), 5.0, "the group's segment to go")


@pytest.mark.timeout(60)
def test_no_round_crosses_zenoh_and_forged_frames_on_the_trainers_key_change_nothing(start_server):
    from overtake.protocol import keys

    from tests.support.remote import RawClient

    server = start_server("shm-silent")
    remote = gym.make(
        REMOTE_HIGHWAY_ENV_ID,
        remote=remote_config(server.endpoint, server.name, transport="shm"),
        overrides=SHORT,
    )
    local = gym.make(HIGHWAY_ENV_ID, overrides=SHORT)
    raw = RawClient(server.endpoint)
    try:
        group = remote.unwrapped.group
        trainer = group.connection.trainer
        steps_key = keys.trainer_steps(trainer, server.name)
        heard = raw.collect(steps_key)
        actions_heard = raw.collect(keys.server_actions(server.name, trainer))
        remote.reset(seed=2), local.reset(seed=2)
        for step in range(20):
            # Anyone on the network may publish on the trainer's key: a Steps frame of the
            # next round with other observations is not taken for the segment's.
            if step % 5 == 0:
                forged = dataclasses.replace(
                    group.last,
                    round=group.round + 1,
                    observations={k: np.zeros_like(v) for k, v in group.last.observations.items()},
                    server="someone-else",
                )
                raw.put(steps_key, codec.encode(forged))
            got, want = remote.step(step % 5), local.step(step % 5)
            for name in want[0]:
                assert np.array_equal(got[0][name], want[0][name]), (step, name)
            assert got[1] == want[1]
        assert group.connection.rounds_through("shm") == 20
        # Nothing of a round went over Zenoh either way: only the four forged frames.
        assert heard.qsize() == 4 and actions_heard.qsize() == 0
        # The last forged frame may reach the trainer's inbox after its round came through the
        # segment: the connection files (and drops) it when it next looks there.
        conn = group.connection
        wait_until(
            lambda: (
                conn.arrived(server.name, group.group_id, group.round + 1) is None
                and conn.dropped == 4
            ),
            10.0,
            "the four forged frames dropped",
        )
    finally:
        raw.close()
        remote.close()
        local.close()


@pytest.mark.timeout(60)
def test_an_error_about_a_segment_round_reaches_the_trainer_asleep_on_the_bell(start_server):
    """What is not a round (an error reply) goes over Zenoh, counted in the segment and rung:
    a trainer waiting on the bell takes it from Zenoh at once."""
    server = start_server("shm-error")
    remote = gym.make(
        REMOTE_HIGHWAY_ENV_ID,
        remote=remote_config(server.endpoint, server.name, transport="shm"),
        overrides=SHORT,
    )
    try:
        group = remote.unwrapped.group
        remote.reset(seed=1)
        remote.step(1)
        # Actions for agents this trainer does not own, through the segment: refused.
        group.send(np.array([99], dtype=np.int32), np.array([1]))
        with pytest.raises(errors.BadAction, match="agent ids in group"):
            group.receive()
    finally:
        remote.close()


def _over_zenoh_and_shm_refused(server, refusal: str) -> None:
    """With ``auto`` a trainer steps ``server`` over Zenoh; asking for ``shm`` is refused,
    saying ``refusal``."""
    env = gym.make(
        REMOTE_HIGHWAY_ENV_ID, remote=remote_config(server.endpoint, server.name), overrides=SHORT
    )
    try:
        assert env.unwrapped.group.transport == "zenoh"  # auto: over Zenoh
        env.reset(seed=1)
        env.step(1)
    finally:
        env.close()
    with pytest.raises(errors.ConnectError, match=refusal):
        gym.make(
            REMOTE_HIGHWAY_ENV_ID,
            remote=remote_config(server.endpoint, server.name, transport="shm"),
        )


@pytest.mark.timeout(60)
def test_a_trainer_that_cannot_reach_the_segment_falls_back_or_says_why(
    start_server, tmp_path, monkeypatch
):
    # The trainer looks for segments in another directory: a server in another container.
    server = start_server("shm-elsewhere")
    monkeypatch.setenv("OVERTAKE_SHM_DIR", str(tmp_path))
    _over_zenoh_and_shm_refused(server, "is the server on this host")
    # The refused group was closed, not left open.
    wait_until(lambda: server.status().arenas_used == 0, 5.0, "the refused group to close")


@pytest.mark.timeout(60)
def test_a_server_without_shared_memory_offers_none(start_server):
    server = start_server("shm-off", extra=("--no-shared-memory",))
    _over_zenoh_and_shm_refused(server, "offered no shared memory")
    assert not segments_of(server.proc.pid)


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
