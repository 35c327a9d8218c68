"""The trainer's side of a transport is one module: a :class:`StepsChannel`. A test double (a
transport whose rounds are handed over in this process) steps a connection's group with no
change to the connection: its Actions go through the double, its rounds come out of it, the
connection waits on it, and the Zenoh inbox stays the way errors arrive, whatever the transport.
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np
import pytest
import zenoh

from overtake.client.wire.connection import Connection
from overtake.client.wire.steps_channel import StepsChannel
from overtake.client.wire.zenoh_channel import ZenohChannel
from overtake.ipc.transport import TransportConfig
from overtake.protocol import codec, errors, keys
from overtake.protocol.messages import Actions, ErrorReply, Steps

from tests.support.remote import endpoint, free_port, remote_config, wait_until

SERVER, GROUP = "double-server", 3


class HandOverChannel:
    """A transport of the test's own: Actions kept, Steps handed over by the test."""

    name = "hand-over"

    def __init__(self) -> None:
        self.sent: list[Actions] = []
        self.ready: deque[Steps] = deque()
        self.waits = 0
        self.heard = 0
        self.closed_with: bool | None = None
        self.rounds = 0
        self._woken = threading.Event()

    def send_actions(self, actions: Actions) -> None:
        self.sent.append(actions)

    def take(self, round_: int) -> Steps | None:
        if self.ready and self.ready[0].round == round_:
            self.rounds += 1
            return self.ready.popleft()
        return None

    def wait(self, timeout_s: float, spin_s: float) -> bool:
        self.waits += 1
        self._woken.wait(min(timeout_s, 0.01))  # as a doorbell would: asleep until rung
        self._woken.clear()
        return True

    def heard_over_zenoh(self) -> None:
        self.heard += 1

    def wake(self) -> None:
        self._woken.set()

    def close(self, unlink: bool) -> None:
        self.closed_with = unlink


def steps(round_: int) -> Steps:
    n = 1
    return Steps(
        server=SERVER,
        group=GROUP,
        round=round_,
        agents=np.arange(n, dtype=np.int32),
        observations={"ego": np.zeros((n, 2), np.float32)},
        reward=np.zeros(n),
        terminated=np.zeros(n, bool),
        truncated=np.zeros(n, bool),
        action_applied=np.zeros(n, np.int64),
        late=np.zeros(n, bool),
        action_mask=np.ones((n, 5), np.int8),
        reward_terms=np.zeros((n, 1)),
        metrics=np.zeros((n, 1)),
    )


def actions(conn: Connection, round_: int) -> Actions:
    return Actions(
        trainer=conn.trainer,
        ticket=b"t",
        group=GROUP,
        round=round_,
        agents=np.zeros(1, np.int32),
        actions=np.ones(1, np.int64),
    )


@pytest.fixture
def network():
    """A Zenoh peer listening on a free loopback port, for the connection to reach."""
    ep = endpoint(free_port())
    session = zenoh.open(TransportConfig(mode="peer", listen=(ep,)).zenoh_config())
    yield session, ep
    session.close()


def test_a_transport_double_steps_a_group_through_the_connection(network):
    session, ep = network
    conn = Connection(remote_config(ep, step_timeout_s=0.3))
    try:
        double = HandOverChannel()
        assert isinstance(double, StepsChannel)  # every member of the interface, no more
        conn.track(SERVER, GROUP)
        conn.attach(SERVER, GROUP, double)
        # Actions go through the double, not over Zenoh.
        sent = actions(conn, 1)
        conn.send_actions(SERVER, sent)
        assert double.sent == [sent]
        # A round the double holds is what the connection returns, without waiting.
        double.ready.append(steps(1))
        assert conn.arrived(SERVER, GROUP, 1).round == 1
        double.ready.append(steps(2))
        assert conn.next_steps(SERVER, GROUP, 2, conn.epoch(SERVER)).round == 2
        assert conn.rounds_through("hand-over") == 2 and conn.rounds_through("shm") == 0
        # Nothing held: the connection waits on the double until its step timeout.
        with pytest.raises(errors.StepTimeout):
            conn.next_steps(SERVER, GROUP, 3, conn.epoch(SERVER))
        assert double.waits > 0
        # An error still comes over Zenoh, whatever the transport, and the double hears of it.
        reply = ErrorReply(code="bad_action", message="no such action", group=GROUP)
        session.put(keys.trainer_steps(conn.trainer, SERVER), codec.encode(reply))
        with pytest.raises(errors.BadAction, match="no such action"):
            conn.next_steps(SERVER, GROUP, 3, conn.epoch(SERVER))
        assert double.heard == 1
        # Forgetting the group closes its channel; its rounds stay counted.
        conn.forget(SERVER, GROUP)
        assert double.closed_with is False  # the server is not lost: nothing to remove
        assert conn.rounds_through("hand-over") == 2
    finally:
        conn.close()


def test_a_group_without_an_opened_channel_steps_over_zenoh(network):
    """A joined group (no segment offered) sends its Actions on the server's Zenoh key."""
    session, ep = network
    got: list[Actions] = []
    sub = session.declare_subscriber(
        keys.server_actions_all(SERVER),
        lambda sample: got.append(codec.decode(sample.payload.to_bytes(), Actions)),
    )
    conn = Connection(remote_config(ep))
    try:
        conn.track(SERVER, GROUP)
        assert conn.open_channel(SERVER, GROUP, offer=None) == "zenoh"
        conn.send_actions(SERVER, actions(conn, 1))
        wait_until(lambda: got, 10.0, "the Actions over Zenoh")
        assert got[0].group == GROUP and got[0].round == 1
        assert isinstance(conn._channels[(SERVER, GROUP)], ZenohChannel)
    finally:
        conn.close()
        sub.undeclare()
