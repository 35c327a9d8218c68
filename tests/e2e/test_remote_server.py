"""End to end, the server's side: several trainers, shared arenas, trainers that die or stall,
hostile input, several servers on one Zenoh network, and clean shutdown.

Servers and trainers are real processes on 127.0.0.1 with free ports (``tests/support/remote.py``);
trainer subprocesses run ``tests/support/trainer_script.py`` and report one event per line.
"""

from __future__ import annotations

import math
import queue
import secrets
import signal
import subprocess
import sys
import threading
import time

import gymnasium as gym
import msgpack
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.client import RemoteEnvironment
from overtake.client.wire.remote import Connection
from overtake.envs import REMOTE_HIGHWAY_ENV_ID
from overtake.protocol import codec, errors, keys
from overtake.protocol.codec import version_text
from overtake.protocol.errors import ServerLost
from overtake.protocol.messages import (
    Ack,
    Actions,
    ErrorReply,
    JoinRequest,
    Message,
    OpenRequest,
    StatusReply,
    StatusRequest,
    WorldFrame,
)
from overtake.server.cli import main
from overtake.server.errors import StartError
from overtake.server.service.server import ServerConfig

from tests.support.remote import (
    RawClient,
    child_env,
    next_message,
    remote_config,
    trainer_args,
    wait_until,
)


def group_of(status: StatusReply, trainer: str):
    return next((g for g in status.groups if trainer in g.trainers), None)


# --- 3. two trainers, independent arenas, at the same time -----------------------------------


@pytest.mark.timeout(60)
def test_two_trainers_step_their_own_arenas_concurrently(start_server, start_trainer):
    server = start_server("e2e-two")
    steps = 300
    a = start_trainer(
        trainer_args(server, server.name, seed=1, policy="random", print_every=steps), "a"
    )
    b = start_trainer(
        trainer_args(server, server.name, seed=2, policy="random", print_every=steps), "b"
    )
    ready_a, ready_b = a.expect("READY"), b.expect("READY")
    assert ready_a["trainer"] != ready_b["trainer"]
    assert ready_a["group"] != ready_b["group"]
    assert set(ready_a["arena_ids"]).isdisjoint(ready_b["arena_ids"])

    a.send(f"step {steps}")
    b.send(f"step {steps}")

    # While they run, the server holds two groups, one trainer each.
    def both_stepping() -> StatusReply | None:
        s = server.status()
        return s if len(s.groups) == 2 and all(g.rounds > 0 for g in s.groups) else None

    status = wait_until(both_stepping, 20, "two groups stepping")
    assert status.arenas_used == 2
    assert {g.trainers for g in status.groups} == {(ready_a["trainer"],), (ready_b["trainer"],)}

    done_a, done_b = a.expect("STEPPED", 60), b.expect("STEPPED", 60)
    for done in (done_a, done_b):
        assert done["steps"] == steps and done["round"] == steps
        assert done["late_seen"] == 0
    # Concurrently: each started before the other finished.
    assert max(done_a["t0"], done_b["t0"]) < min(done_a["t1"], done_b["t1"])
    status = server.status()
    assert sorted(g.rounds for g in status.groups) == [steps, steps]
    assert all(g.late_agents == 0 for g in status.groups)
    # Both are idle now: nothing waits in the server's queues, and nothing was dropped.
    assert (status.queued_actions, status.queued_requests, status.dropped_frames) == (0, 0, 0)
    from overtake.client.wire.status import format_status

    text = format_status([status])
    assert f"{server.name}: 2/" in text and "0 frames dropped at the queues' bounds" in text
    for ready in (ready_a, ready_b):
        assert f"trainers [{ready['trainer']!r}], {steps} rounds" in text

    a.send("exit")
    b.send("exit")
    a.expect("EXIT")
    b.expect("EXIT")
    wait_until(lambda: server.status().groups == (), 5, "the groups closed")
    assert server.status().arenas_used == 0


# --- 4. three trainers on one road ------------------------------------------------------------


@pytest.mark.timeout(60)
def test_three_trainers_share_one_arena_in_lock_step(start_server, start_trainer):
    server = start_server("e2e-share", world_rate_hz=1000)
    empty_road = {"traffic.vehicle_count": 0}
    a = start_trainer(
        trainer_args(
            server,
            server.name,
            arenas=1,
            agents_per_arena=3,
            claim=1,
            seed=3,
            overrides=empty_road,
            print_lidar=True,
        ),
        "a",
    )
    ready_a = a.expect("READY")
    arena = ready_a["arena_ids"][0]
    b = start_trainer(trainer_args(server, server.name, join=arena, print_lidar=True), "b")
    c = start_trainer(trainer_args(server, server.name, join=arena, print_lidar=True), "c")
    ready_b, ready_c = b.expect("READY"), c.expect("READY")
    trainers = [a, b, c]
    readies = [ready_a, ready_b, ready_c]

    # One group, three trainers, one agent each, all different.
    assert ready_b["group"] == ready_c["group"] == ready_a["group"]
    agents = [r["agents"] for r in readies]
    assert all(len(x) == 1 for x in agents)
    assert sorted(x[0] for x in agents) == [0, 1, 2]
    status = server.status()
    assert len(status.groups) == 1 and status.arenas_used == 1
    assert set(status.groups[0].trainers) == {r["trainer"] for r in readies}

    frames: dict[int, WorldFrame] = {}
    with RawClient(server.endpoint) as spectator:
        spectator.subscribe(
            keys.world(server.name, arena),
            lambda sample: frames.setdefault(
                (f := codec.decode(sample.payload.to_bytes(), WorldFrame)).round, f
            ),
        )

        # The round waits for every trainer: two acting is not enough.
        a.send("step 1")
        b.send("step 1")
        assert a.no_event_within(0.5) and b.no_event_within(0.0), (
            "the shared round stepped without the third trainer"
        )
        c.send("step 1")
        for t in trainers:
            assert t.expect("STEPPED")["round"] == 1

        rounds = 15
        lidar_by_round: list[dict[int, list[float]]] = [{}, {}, {}]
        for t in trainers:
            t.send(f"step {rounds}")
        for k, t in enumerate(trainers):
            while True:
                event, fields = t.next_event(30)
                assert event != "ERROR", fields
                if event == "STEP":
                    lidar_by_round[k][fields["round"]] = fields["lidar"][0]
                    assert fields["late"] == [False]
                if event == "STEPPED":
                    assert fields["round"] == rounds + 1 and fields["late_seen"] == 0
                    break
        wait_until(
            lambda: any(r in frames for r in range(2, rounds + 2)),
            10,
            "a world frame of a round the trainers saw",
        )

    status = server.status()
    assert status.groups[0].rounds == rounds + 1 and status.groups[0].late_agents == 0

    # Each trainer's LIDAR sees the other two cars: the ray towards another car's centre
    # stops short of it (on an empty road nothing else is there; without that car the ray
    # would go on to the guard rail beyond it, or to its full range).
    checked = 0
    for r in sorted(
        set(frames) & set(lidar_by_round[0]) & set(lidar_by_round[1]) & set(lidar_by_round[2])
    ):
        frame = frames[r]
        assert frame.agent_active.tolist() == [True, True, True]
        for k in range(3):
            me = agents[k][0]
            lidar = np.asarray(lidar_by_round[k][r])
            assert np.array_equal(lidar.astype(np.float32), frame.observations["lidar"][me])
            for other in {0, 1, 2} - {me}:
                dx = frame.x_m[other] - frame.x_m[me]
                dy = frame.y_m[other] - frame.y_m[me]
                distance = math.hypot(dx, dy)
                assert distance < 75.0, "the cars are further apart than the LIDAR's range"
                ray = round(math.degrees(math.atan2(dy, dx))) % 360
                window = [(ray + d) % 360 for d in range(-2, 3)]
                assert lidar[window].min() < distance, (
                    f"trainer {k} (agent {me}) does not see agent {other} at round {r}"
                )
                checked += 1
    assert checked >= 6


# --- 5. a trainer killed mid-episode ------------------------------------------------------------


@pytest.mark.timeout(60)
def test_killed_trainer_frees_its_arena_and_never_stalls_another(start_server, start_trainer):
    server = start_server("e2e-kill")
    victim = start_trainer(trainer_args(server, server.name, print_every=20), "victim")
    other = start_trainer(trainer_args(server, server.name, print_every=20), "other")
    ready_v, ready_o = victim.expect("READY"), other.expect("READY")
    victim.send("run")
    other.send("run")
    victim.expect("STEP")  # mid-episode: stepping
    other.expect("STEP")
    status = server.status()
    assert status.arenas_used == 2 and len(status.groups) == 2

    killed_at = time.monotonic()
    assert victim.kill() == -signal.SIGKILL
    wait_until(
        lambda: group_of(server.status(), ready_v["trainer"]) is None,
        2.0,
        "the killed trainer's group to be freed",
    )
    freed_after = time.monotonic() - killed_at
    status = server.status()
    assert status.arenas_used == 1
    assert [g.trainers for g in status.groups] == [(ready_o["trainer"],)]
    assert "gone (liveliness token lost)" in server.wait_log("liveliness token lost", 5)

    # The other trainer went on stepping all along, and still does.
    while other.expect("STEP")["t"] <= killed_at + freed_after:
        pass
    other.send("stop")
    summary = other.expect("STOPPED")
    assert summary["max_gap_s"] < 1.0, f"the other trainer stalled {summary['max_gap_s']:.2f} s"
    assert summary["late_seen"] == 0
    assert group_of(server.status(), ready_o["trainer"]).rounds == summary["total_steps"]


@pytest.mark.timeout(60)
def test_frozen_trainer_host_is_dropped_within_its_lease_and_comes_back(
    start_server, start_trainer
):
    # SIGSTOP freezes the whole process, Zenoh's threads included: no keep-alives, no FIN, as
    # when a host drops off the network. Its arenas must go within the lease it announced.
    server = start_server("e2e-frozen")
    lease_s = 1.0
    frozen = start_trainer(
        trainer_args(server, server.name, lease_s=lease_s, print_every=10, reconnect_timeout_s=10),
        "frozen",
    )
    ready = frozen.expect("READY")
    frozen.send("run")
    frozen.expect("STEP")
    assert group_of(server.status(), ready["trainer"]) is not None
    frozen_at = time.monotonic()
    frozen.proc.send_signal(signal.SIGSTOP)
    try:
        wait_until(
            lambda: group_of(server.status(), ready["trainer"]) is None,
            lease_s + 3.0,
            "the frozen trainer's group to be freed",
        )
        freed_after = time.monotonic() - frozen_at
        # Not before the lease: a trainer busy for a moment is not thrown out.
        assert freed_after >= 0.5 * lease_s, f"freed after only {freed_after:.2f} s"
        assert server.status().arenas_used == 0
    finally:
        frozen.proc.send_signal(signal.SIGCONT)
    # Woken, it finds its arenas gone: the episode under way ends truncated, it opens new
    # arenas and steps on (bench/reliability/faults.py: back within 0.1 s); nothing of the old
    # is left.
    step = frozen.expect("STEP", timeout_s=20)
    while not step["restarted"]:
        step = frozen.expect("STEP", timeout_s=20)
    assert step["truncated"] == [True] and step["reward"] == [0.0]
    frozen.expect("STEP", timeout_s=10)
    [group] = server.status().groups
    assert group.trainers == (ready["trainer"],) and group.rounds > 0
    assert server.status().arenas_used == 1
    frozen.send("stop")
    assert frozen.expect("STOPPED")["restarts"] == 1


# --- 6. a trainer that stops answering in a shared arena ---------------------------------------


@pytest.mark.timeout(60)
def test_late_trainer_gets_keep_and_is_counted_and_can_resume(start_server):
    server = start_server("e2e-late", step_deadline_s=0.5)
    config = remote_config(server.endpoint, server.name, step_timeout_s=10.0)
    a = RemoteEnvironment(arenas=1, agents_per_arena=2, claim=1, seed=1, config=config)
    b = None
    try:
        b = RemoteEnvironment(join=a.group.arena_ids[0], config=config)
        assert a.steps.agents.tolist() != b.steps.agents.tolist()

        # B stops answering: each of A's rounds goes ahead at the deadline, not later. (A's
        # actions are taken in Zenoh's thread, which must wake the server's loop to wait for
        # the deadline: otherwise the loop sleeps out its idle second first, and every round
        # takes a second or more.) Never before the deadline; the fastest round within it and
        # a little (a loaded machine may slow one round or two, not the loop's wake-up).
        took = []
        for expected_round in (1, 2, 3):
            start = time.monotonic()
            a.step()
            took.append(time.monotonic() - start)
            assert a.steps.round == expected_round and not a.steps.late.any()
        assert min(took) > 0.4, f"a round went ahead before the 0.5 s deadline: {took}"
        assert min(took) < 0.85, f"every round waited past the 0.5 s deadline: {took}"
        group = server.status().groups[0]
        assert group.rounds == 3 and group.late_agents == 3

        # B comes back: its car kept going (keep) and it is told it was late.
        b.step()
        steps = b.steps
        assert steps.late.tolist() == [True]
        assert steps.action_applied.tolist() == [0]

        # And then A and B step together again, without errors.
        failures: list[BaseException] = []

        def drive_a() -> None:
            try:
                for _ in range(4):
                    a.step()
            except BaseException as error:  # reported below
                failures.append(error)

        thread = threading.Thread(target=drive_a)
        thread.start()
        b_late = []
        try:
            for _ in range(4):
                b.step()
                b_late.append(bool(b.steps.late[0]))
                assert b.steps.round == b.group.round
        finally:
            thread.join(30)
        assert not failures, f"A failed: {failures!r}"
        assert not b_late[-1], f"B never got back in lock step: late flags {b_late}"
    finally:
        if b is not None:
            b.close()
        a.close()


# --- 9. hostile input straight over Zenoh ---------------------------------------------------


def _open(trainer: str, **changes) -> OpenRequest:
    fields = dict(
        trainer=trainer,
        preset="min2018",
        overrides={},
        arenas=1,
        agents_per_arena=1,
        claim=1,
        seed=None,
    )
    fields.update(changes)
    return OpenRequest(**fields)


def _actions_frame(trainer: str, ticket: bytes, group: int, round_: int, agents, actions) -> bytes:
    """An Actions frame built by hand, bypassing the dataclass's own checks."""

    def array(values, dtype):
        a = np.asarray(values, dtype=dtype)
        return {"dtype": np.dtype(dtype).name, "shape": list(a.shape), "data": a.tobytes()}

    body = {
        "trainer": trainer,
        "ticket": ticket,
        "group": group,
        "round": round_,
        "agents": array(agents, "<i4"),
        "actions": array(actions, "<i8"),
    }
    return msgpack.packb([1, 0, "actions", body], use_bin_type=True)


@pytest.mark.timeout(90)
def test_hostile_input_is_refused_and_harms_nobody(start_server):
    server = start_server("e2e-hostile", max_arenas=4)
    name = server.name
    victim = RemoteEnvironment(config=remote_config(server.endpoint, name, step_timeout_s=10.0))
    rounds = [victim.group.round]

    def victim_steps() -> None:
        """The well-behaved trainer still gets its steps."""
        victim.step()
        assert victim.steps.round == rounds[-1] + 1
        rounds.append(victim.steps.round)

    try:
        with RawClient(server.endpoint) as raw:

            def refused(payload, code: str) -> str:
                reply = raw.request(name, payload)
                assert isinstance(reply, ErrorReply), reply
                assert reply.code == code, reply
                victim_steps()
                return reply.message

            rng = np.random.default_rng(0)
            refused(rng.bytes(64), "bad_message")
            refused(b"", "bad_message")
            refused(msgpack.packb([1, 0, "no_such_message", {}]), "bad_message")
            refused(codec.encode(Ack(message="not a request")), "bad_message")
            refused(codec.encode(ErrorReply(code="x", message="not a request")), "bad_message")
            message = refused(msgpack.packb([2, 0, "status_request", {}]), "version_mismatch")
            assert "2.0" in message and version_text() in message
            # Opening needs a liveliness token, as overtake.client declares.
            refused(codec.encode(_open("ghost")), "not_owner")
            raw.token(keys.trainer_alive("hostile"))
            assert "no-such-preset" in refused(
                codec.encode(_open("hostile", preset="no-such-preset")), "unknown_preset"
            )
            assert "no.such.field" in refused(
                codec.encode(_open("hostile", overrides={"no.such.field": 1})), "bad_config"
            )
            refused(
                codec.encode(_open("hostile", overrides={"episode.max_decisions": "many"})),
                "bad_config",
            )
            refused(codec.encode(_open("hostile", arenas=5)), "server_full")
            refused(
                codec.encode(JoinRequest(trainer="hostile", arena=999, agents=1)), "unknown_arena"
            )
            refused(
                codec.encode(
                    JoinRequest(trainer="hostile", arena=victim.group.arena_ids[0], agents=1)
                ),
                "server_full",
            )  # its one slot is taken

            # Bad actions are answered where the trainer's Steps would go.
            inbox = raw.collect(keys.trainer_steps("hostile", name))
            actions_key = keys.server_actions(name, "hostile")
            made_up = secrets.token_bytes(16)

            def refused_actions(payload: bytes, code: str) -> str:
                raw.put(actions_key, payload)
                key, reply = next_message(inbox, 5, "an error reply on the steps key")
                assert key == keys.trainer_steps("hostile", name)
                assert isinstance(reply, ErrorReply) and reply.code == code, reply
                victim_steps()
                return reply.message

            refused_actions(
                codec.encode(
                    Actions(
                        trainer="hostile",
                        ticket=made_up,
                        group=77,
                        round=0,
                        agents=np.array([0], np.int32),
                        actions=np.array([1]),
                    )
                ),
                "unknown_arena",
            )
            refused_actions(rng.bytes(32), "bad_message")
            assert "[7]" in refused_actions(
                _actions_frame(
                    "hostile", made_up, victim.group.group_id, victim.group.round, [0], [7]
                ),
                "bad_message",
            )
            refused_actions(
                _actions_frame(
                    "hostile", made_up, victim.group.group_id, victim.group.round, [0, 0], [1, 1]
                ),
                "bad_message",
            )
            # Actions for another trainer's group, on our own key with a made-up ticket.
            refused_actions(
                codec.encode(
                    Actions(
                        trainer="hostile",
                        ticket=made_up,
                        group=victim.group.group_id,
                        round=victim.group.round,
                        agents=np.array([0], np.int32),
                        actions=np.array([3]),
                    )
                ),
                "not_owner",
            )
            # Actions that claim to be the victim's, on our key: dropped, logged.
            raw.put(
                actions_key,
                codec.encode(
                    Actions(
                        trainer=victim.group.connection.trainer,
                        ticket=made_up,
                        group=victim.group.group_id,
                        round=victim.group.round,
                        agents=np.array([0], np.int32),
                        actions=np.array([3]),
                    )
                ),
            )
            server.wait_log("claim to come from", 5)
            victim_steps()
            assert victim.steps.action_applied.tolist() == [0]  # the victim's keep, not 3
            assert inbox.empty()
    finally:
        victim.close()
    assert server.alive()
    assert server.status().groups == ()
    assert len(rounds) > 15
    log = server.log_text()
    assert "unexpected error" not in log and "Traceback" not in log, log[-3000:]


@pytest.mark.timeout(60)
def test_spoofed_actions_on_a_trainers_key_do_not_break_its_steps(start_server):
    """The actions key of a trainer is public (its id is in status and liveliness): a
    stranger putting garbage there, with the trainer's name and a made-up ticket, must not
    make the trainer's own next step fail."""
    server = start_server("e2e-spoof")
    victim = RemoteEnvironment(
        config=remote_config(server.endpoint, server.name, step_timeout_s=10.0)
    )
    try:
        trainer = victim.group.connection.trainer
        assert trainer in server.status().groups[0].trainers  # anybody can read it
        victim.step()
        with RawClient(server.endpoint) as raw:
            raw.put(
                keys.server_actions(server.name, trainer),
                codec.encode(
                    Actions(
                        trainer=trainer,
                        ticket=secrets.token_bytes(16),
                        group=victim.group.group_id,
                        round=victim.group.round,
                        agents=np.array([0], np.int32),
                        actions=np.array([3]),
                    )
                ),
            )
            server.wait_log("wrong ticket", 5)
            for _ in range(3):
                victim.step()  # must not raise NotOwner
            assert victim.steps.round == 4
    finally:
        victim.close()


# --- 10. two servers on one Zenoh network ------------------------------------------------------


@pytest.mark.timeout(60)
def test_two_servers_on_one_network_share_the_load(start_server):
    first = start_server("e2e-srv-a", max_arenas=4)
    second = start_server("e2e-srv-b", max_arenas=4, connect=(first.endpoint,))
    probe = Connection(remote_config(first.endpoint))
    envs: list[RemoteEnvironment] = []
    try:
        wait_until(
            lambda: {s.server for s in probe.discover()} == {first.name, second.name},
            10,
            "both servers visible through the first one's endpoint",
        )
        config = remote_config(first.endpoint)  # no server named: the client picks
        for _ in range(3):
            envs.append(RemoteEnvironment(config=config))
        landed = [env.group.server for env in envs]
        # Most free arenas first (ties: fewest groups, then at random): the second goes where
        # the first did not, the third to either.
        assert landed[1] != landed[0] and landed[2] in (first.name, second.name)
        busier, quieter = (first, second) if landed.count(first.name) == 2 else (second, first)
        for env in envs:
            for _ in range(3):
                env.step()
            assert env.steps.round == 3
        for server, count in ((busier, 2), (quieter, 1)):
            status = server.status()
            assert status.arenas_used == count and len(status.groups) == count
            mine = {e.group.connection.trainer for e in envs if e.group.server == server.name}
            assert {g.trainers[0] for g in status.groups} == mine
            assert all(g.rounds == 3 for g in status.groups)
        # A request that fits only one server goes there.
        big = RemoteEnvironment(arenas=3, config=config)
        envs.append(big)
        assert big.group.server == quieter.name
    finally:
        for env in envs:
            env.close()
        probe.close()


# --- 11. clean shutdown -------------------------------------------------------------------------


@pytest.mark.timeout(60)
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_server_shuts_down_cleanly_on_signal(start_server, sig):
    server = start_server(f"e2e-stop-{sig.name.lower()}")
    env = gym.make(
        REMOTE_HIGHWAY_ENV_ID,
        remote=remote_config(
            server.endpoint, server.name, reconnect_timeout_s=0.0, step_timeout_s=10.0
        ),
    )
    try:
        env.reset(seed=0)
        for _ in range(3):
            env.step(0)
        start = time.monotonic()
        server.signal(sig)
        assert server.wait_exit(5.0) == 0
        assert time.monotonic() - start < 5.0
        log = server.log_text()
        assert f"received {sig.name}, shutting down" in log
        assert f"server {server.name} stopped" in log
        start = time.monotonic()
        with pytest.raises(ServerLost, match=server.name):
            env.step(0)
        assert time.monotonic() - start < 3.0
    finally:
        env.close()


@pytest.mark.timeout(90)
def test_a_server_that_cannot_listen_says_why_and_exits(start_server):
    """A taken port: main(config) raises a typed error, the command exits with its message."""
    owner = start_server("port-owner")
    with pytest.raises(StartError, match="could not open the Zenoh session"):
        main(ServerConfig(name="second", listen=(owner.endpoint,), log_level="error"))
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "overtake.server",
            "--listen",
            owner.endpoint,
            "--name",
            "third",
            "--log-level",
            "error",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env=child_env(),
    )
    assert done.returncode == 1
    assert "overtake-server: could not open the Zenoh session" in done.stderr
    assert "Traceback" not in done.stderr


def test_equally_loaded_servers_are_picked_at_random_so_trainers_spread_out(monkeypatch):
    # Trainers started together see the same statuses; a tie broken by name sent them all to
    # the same server. Over 40 picks between two equal servers both must come first.
    from overtake.protocol.messages import StatusReply

    def status(name: str, used: int) -> StatusReply:
        return StatusReply(
            server=name,
            package_version="test",
            max_arenas=8,
            arenas_used=used,
            step_deadline_s=30.0,
            uptime_s=1.0,
            groups=(),
        )

    connection = Connection.__new__(Connection)  # no session: only the choice is exercised
    connection.config = remote_config("tcp/127.0.0.1:1")
    statuses = [status("sim-a", 2), status("sim-b", 2), status("sim-c", 5)]
    monkeypatch.setattr(connection, "discover", lambda: statuses)
    picks = [tuple(connection.candidates(arenas=1)) for _ in range(40)]
    assert {p[0] for p in picks} == {"sim-a", "sim-b"}
    assert all(p[2] == "sim-c" for p in picks)  # the busiest stays last


@pytest.mark.timeout(60)
def test_one_trainer_holds_at_most_its_share_of_arenas(start_server):
    from overtake.client.wire.remote import ArenaGroup
    from overtake.protocol.errors import ServerFull

    server = start_server("e2e-share", max_arenas=8, extra=("--max-arenas-per-trainer", "3"))
    config = remote_config(server.endpoint, server.name)
    greedy, other = Connection(config), Connection(config)

    def open_request(connection: Connection, arenas: int) -> OpenRequest:
        return OpenRequest(
            trainer=connection.trainer,
            preset="min2018",
            overrides={},
            arenas=arenas,
            agents_per_arena=2,
            claim=1,
            seed=1,
        )

    try:
        ArenaGroup.open(greedy, open_request(greedy, 2))
        # 2 held, 2 more asked: refused as full, naming the limit, what it holds and asks.
        with pytest.raises(ServerFull, match=r"at most 3 arena.*holds 2, asked for 2"):
            ArenaGroup.open(greedy, open_request(greedy, 2))
        # Another trainer is not held back by the first one's share.
        theirs = ArenaGroup.open(other, open_request(other, 3))
        # Joining an arena it has no car in counts as one more: room for one, not for two.
        join = JoinRequest(trainer=greedy.trainer, arena=theirs.arena_ids[0], agents=1)
        ArenaGroup.open(greedy, join)
        with pytest.raises(ServerFull, match=r"holds 3, asked for 1"):
            ArenaGroup.open(
                greedy, JoinRequest(trainer=greedy.trainer, arena=theirs.arena_ids[1], agents=1)
            )
        assert server.status().arenas_used == 5
    finally:
        greedy.close()
        other.close()


@pytest.mark.timeout(60)
def test_refused_actions_are_answered_only_to_a_connected_trainer(start_server):
    # A reply to a name nobody holds reaches nobody, and each new key costs Zenoh memory for
    # good: a stranger inventing names must not make the server write to them.
    server = start_server("e2e-no-reflect")
    with RawClient(server.endpoint) as raw:
        raw.token(keys.trainer_alive("present"))
        wait_until(
            lambda: _refusal_reaches(raw, server.name, "present"), 10.0, "the server sees us"
        )
        ghost = raw.collect(keys.trainer_steps("ghost", server.name))
        present = raw.collect(keys.trainer_steps("present", server.name))
        wrong_version = msgpack.packb([9, 0, "actions", {}])
        raw.put(keys.server_actions(server.name, "ghost"), wrong_version)
        raw.put(keys.server_actions(server.name, "present"), wrong_version)
        # Both replies would leave the server in this order on one queue: once ours is here,
        # a reply to the ghost would be too. (Replies to the readiness probes may come first.)
        while True:
            _, payload = present.get(timeout=10.0)
            reply = codec.decode(payload)
            assert isinstance(reply, ErrorReply)
            if reply.code == "version_mismatch":
                break
        assert ghost.empty()


def _refusal_reaches(raw: RawClient, server: str, trainer: str) -> bool:
    inbox = raw.collect(keys.trainer_steps(trainer, server))
    raw.put(keys.server_actions(server, trainer), b"\x00garbage")
    try:
        inbox.get(timeout=1.0)
        return True
    except queue.Empty:
        return False


def test_a_flood_queues_at_most_its_bound():
    # What Zenoh's threads queue for the loop: at most MAX_QUEUED_ACTIONS_PER_KEY actions per
    # key and MAX_QUEUED_REQUESTS requests; the rest is dropped and counted. Exercised on the
    # inbox alone (no session): a flood cannot be timed against the loop reliably.
    from types import SimpleNamespace

    from overtake.server.service import inbox as server_inbox

    inbox = server_inbox.Inbox("s")
    replies: list[bytes] = []

    class FakeQuery:
        payload = None

        def __enter__(self) -> FakeQuery:
            return self

        def __exit__(self, *_: object) -> None:
            pass

        def reply(self, key: str, payload: bytes) -> None:
            assert key == keys.server_request("s")
            replies.append(payload)

    def sample(key: str) -> SimpleNamespace:
        return SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: b"x"))

    bound = server_inbox.MAX_QUEUED_ACTIONS_PER_KEY
    for _ in range(bound + 100):
        inbox.on_actions(sample("overtake/server/s/actions/flooder"))
    inbox.on_actions(sample("overtake/server/s/actions/honest"))  # another key: let in
    backlog = inbox.backlog()
    assert backlog.queued_actions == bound + 1 and backlog.dropped_frames == 100
    # The loop taking one makes room for one more on that key.
    assert isinstance(inbox.take(), server_inbox.ActionsArrived)
    inbox.on_actions(sample("overtake/server/s/actions/flooder"))
    backlog = inbox.backlog()
    assert backlog.queued_actions == bound + 1 and backlog.dropped_frames == 100
    for _ in range(server_inbox.MAX_QUEUED_REQUESTS + 5):
        inbox.on_query(FakeQuery())
    backlog = inbox.backlog()
    assert backlog.queued_requests == server_inbox.MAX_QUEUED_REQUESTS
    assert backlog.dropped_frames == 105
    # Those beyond the bound were answered at once, busy, with the bound named (protocol 1.4);
    # those queued were not answered yet.
    assert len(replies) == 5
    busy = codec.decode(replies[0])
    assert isinstance(busy, ErrorReply) and busy.code == errors.ServerBusy.code
    assert f"{server_inbox.MAX_QUEUED_REQUESTS} requests are waiting" in busy.message
    with pytest.raises(errors.ServerBusy, match="server s is busy"):
        raise errors.error_from_code(busy.code, busy.message)


def test_a_flood_of_garbage_in_a_trainers_name_is_logged_once_per_interval(caplog):
    # One line per dropped frame would fill a trainer's log under a flood (48,000 lines in
    # bench/fuzz/fuzz_wire's run): the first is logged, the rest counted into the next line.
    import logging

    from overtake.client.wire import connection as wire

    connection = Connection.__new__(Connection)  # no session: only the filing is exercised
    connection._stepping = set()
    connection._drop_logged_t, connection._drops_unlogged = -math.inf, 0
    connection.dropped = 0
    key = keys.trainer_steps("me", "sim-a")
    with caplog.at_level(logging.WARNING, logger="overtake.client"):
        for _ in range(100):
            connection._file(key, b"\x00garbage")
        assert len(caplog.records) == 1
        assert "unreadable message from server sim-a" in caplog.records[0].getMessage()
        connection._drop_logged_t -= wire.DROPPED_LOG_INTERVAL_S  # the interval has passed
        connection._file(key, b"\x00garbage")
    assert len(caplog.records) == 2
    assert "and 99 more dropped unlogged" in caplog.records[1].getMessage()
    assert connection.dropped == 101  # every one counted, logged or not


def test_a_request_a_busy_server_did_not_queue_is_asked_again_until_the_timeout(monkeypatch):
    # Protocol 1.4: beyond its bound of waiting requests a server answers server_busy at
    # once; the client asks again with growing pauses, and names the cause when time is up.
    from overtake.client.wire import connection as wire

    connection = Connection.__new__(Connection)  # no session: only the asking is exercised
    connection.config = remote_config("tcp/127.0.0.1:1", request_timeout_s=5.0)
    ok = Ack(message="ok")
    answers: list[object] = [errors.ServerBusy("server s is busy")] * 2 + [ok]
    asked: list[Message] = []

    def once(server: str, message: Message, expect: type) -> object:
        asked.append(message)
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer

    pauses: list[float] = []
    monkeypatch.setattr(connection, "_request_once", once)
    monkeypatch.setattr(wire.time, "sleep", pauses.append)
    assert connection.request("s", StatusRequest(), Ack) is ok
    assert len(asked) == 3 and pauses == [wire.BUSY_FIRST_PAUSE_S, 2 * wire.BUSY_FIRST_PAUSE_S]

    # Always busy: it gives up before the request timeout would pass, with the server's words.
    clock = [0.0]
    monkeypatch.setattr(wire.time, "monotonic", lambda: clock[0])
    pauses.clear()

    def sleep(seconds: float) -> None:
        pauses.append(seconds)
        clock[0] += seconds

    monkeypatch.setattr(wire.time, "sleep", sleep)
    answers[:] = [errors.ServerBusy("server s is busy")] * 100
    with pytest.raises(errors.ServerBusy, match="server s is busy"):
        connection.request("s", StatusRequest(), Ack)
    assert 4.0 < clock[0] <= 5.0 and max(pauses) == wire.BUSY_MAX_PAUSE_S
