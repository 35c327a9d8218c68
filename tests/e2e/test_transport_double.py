"""A transport is one offer type in the contract and one module on each side (protocol 1.10).

A test double shows it: the ``hand-over`` transport hands rounds and Actions between the
server's thread and the trainer in this process. Registered on both sides (the server's
``OFFERED``, the trainer's ``ATTACH``), it is negotiated like shared memory: the trainer lists
it, the server offers it, the group's rounds travel through it (no Steps frame over Zenoh) and
step the road exactly as Zenoh frames do; errors still come over Zenoh; leaving closes both
ends. Nothing else in the server, the connection or the environments changes.
"""

from __future__ import annotations

import contextlib
import copy
import threading
from collections import deque
from dataclasses import dataclass, fields
from typing import ClassVar

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
import overtake.server.channels as server_channels
from overtake.client.wire import steps_channel
from overtake.envs import REMOTE_HIGHWAY_ENV_ID
from overtake.ipc.doorbell import AVAILABLE as DOORBELL_AVAILABLE
from overtake.protocol import errors
from overtake.protocol.channel_offers import ChannelOffer
from overtake.protocol.messages import Actions, Message, Steps
from overtake.server.channels import ChannelTerms
from overtake.server.service.server import SimulatorServer
from overtake.server.service.server_config import ServerConfig

from tests.support.remote import endpoint, free_port, remote_config, wait_until

TRANSPORT = "hand-over"


@dataclass(frozen=True, eq=False)
class HandOverOffer(ChannelOffer):
    """The double's offer: which mailbox of this process the rounds go through."""

    TRANSPORT: ClassVar[str] = TRANSPORT
    mailbox: int


class Mailbox:
    """Where the two ends meet: Steps one way, Actions the other."""

    opened: ClassVar[dict[int, Mailbox]] = {}

    def __init__(self, terms: ChannelTerms, group: int) -> None:
        self.terms, self.group = terms, group
        self.steps: deque[Steps] = deque()
        self.actions: deque[Actions] = deque()
        self.posted = threading.Condition()
        self.server_closed = self.trainer_closed = False
        self.key = len(Mailbox.opened)
        Mailbox.opened[self.key] = self

    def post_steps(self, steps: Steps) -> None:
        # A copy, as any transport delivers: the server writes its next round into these arrays.
        copied = Steps.trusted(
            **{f.name: copy.deepcopy(getattr(steps, f.name)) for f in fields(steps)}
        )
        with self.posted:
            self.steps.append(copied)
            self.posted.notify_all()


class ServerEnd:
    """The server's side: an :class:`~overtake.server.channels.OfferedChannel`."""

    def __init__(self, terms: ChannelTerms) -> None:
        self.trainer, self.group = terms.trainer, terms.current.group
        self.box = Mailbox(terms, self.group)

    def offer(self) -> HandOverOffer:
        return HandOverOffer(mailbox=self.box.key)

    def send_steps(self, steps: Steps) -> None:
        self.box.post_steps(steps)

    def send(self, message: Message) -> None:
        self.box.terms.fallback.send(message)  # what is not a round: over Zenoh
        with self.box.posted:
            self.box.posted.notify_all()

    def rung(self) -> bool:
        return bool(self.box.actions)

    def hear_rings(self, on: bool) -> None:
        """Nothing to switch: the trainer's end calls on_ring at every post, asleep or not."""

    def actions(self) -> Actions:
        return self.box.actions.popleft()

    def close(self) -> None:
        self.box.server_closed = True


class TrainerEnd:
    """The trainer's side: a :class:`~overtake.client.wire.steps_channel.StepsChannel`."""

    name = TRANSPORT

    def __init__(self, box: Mailbox) -> None:
        self.box, self.rounds, self.heard = box, 0, 0

    def send_actions(self, actions: Actions) -> None:
        self.box.actions.append(actions)
        self.box.terms.on_ring(self.box.terms.trainer, self.box.group)

    def take(self, round_: int) -> Steps | None:
        while self.box.steps and self.box.steps[0].round < round_:
            self.box.steps.popleft()  # a round the trainer no longer waits for
        if self.box.steps and self.box.steps[0].round == round_:
            self.rounds += 1
            return self.box.steps.popleft()
        return None

    def wait(self, timeout_s: float, spin_s: float) -> bool:
        with self.box.posted:
            if not self.box.steps:
                self.box.posted.wait(min(timeout_s, 0.05))
        return True

    def heard_over_zenoh(self) -> None:
        self.heard += 1

    def wake(self) -> None:
        with self.box.posted:
            self.box.posted.notify_all()

    def close(self, unlink: bool) -> None:
        self.box.trainer_closed = True


def attach_double(
    server: str, group: int, offer: ChannelOffer | None, required: bool
) -> TrainerEnd | None:
    if not isinstance(offer, HandOverOffer):
        if required:
            raise errors.ConnectError(f"transport {TRANSPORT}: server {server} offered none")
        return None
    return TrainerEnd(Mailbox.opened[offer.mailbox])


@contextlib.contextmanager
def serving(monkeypatch, make_double):
    """A server in this process that can offer the double (and shared memory), and a trainer
    side that lists the double first."""
    monkeypatch.setitem(server_channels.OFFERED, TRANSPORT, make_double)
    monkeypatch.setattr(steps_channel, "ATTACH", {TRANSPORT: attach_double, **steps_channel.ATTACH})
    server = SimulatorServer(ServerConfig(name="double", listen=(endpoint(free_port()),)))
    serving = threading.Thread(target=server.serve, daemon=True)
    serving.start()
    try:
        yield server
    finally:
        server.stop()
        serving.join(10)
    assert not serving.is_alive()


def drive(server: SimulatorServer, transport: str, rounds: int) -> tuple[list, object]:
    env = gym.make_vec(
        REMOTE_HIGHWAY_ENV_ID,
        num_envs=2,
        vectorization_mode="vector_entry_point",
        remote=remote_config(server.config.listen[0], "double", transport=transport),
        preset="min2018",
        overrides={"episode.max_decisions": 30},
    )
    seen = []
    try:
        obs, _ = env.reset(seed=11)
        seen.append(copy.deepcopy(obs))
        rng = np.random.default_rng(3)
        for _ in range(rounds):
            obs, reward, terminated, truncated, _ = env.step(rng.integers(0, 5, 2))
            seen.append(copy.deepcopy((obs, reward, terminated, truncated)))
        group = env.unwrapped.group
        return seen, (group.transport, group.connection.rounds_through(TRANSPORT))
    finally:
        env.close()


def same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, tuple):
        return all(same(x, y) for x, y in zip(a, b, strict=True))
    return np.array_equal(a, b)


@pytest.mark.timeout(120)
def test_a_transport_double_is_negotiated_and_steps_as_zenoh_does(monkeypatch):
    with serving(monkeypatch, ServerEnd) as server:
        check_negotiated(server)


def check_negotiated(server: SimulatorServer) -> None:
    before = len(Mailbox.opened)
    over_double, (transport, rounds) = drive(server, "auto", 40)
    assert transport == TRANSPORT  # listed first by the trainer, offered by the server
    assert rounds == 40  # every round came through the double, none as a Zenoh frame
    box = Mailbox.opened[before]
    assert not box.steps and not box.actions
    # Leaving closed both ends (the server's when the trainer left its group).
    wait_until(lambda: box.server_closed, 10.0, "the server's end to close")
    assert box.trainer_closed

    over_zenoh, (transport, rounds) = drive(server, "zenoh", 40)
    assert transport == "zenoh" and rounds == 0
    assert len(Mailbox.opened) == before + 1  # a trainer that lists none is offered none
    assert all(same(a, b) for a, b in zip(over_double, over_zenoh, strict=True))


@pytest.mark.timeout(60)
def test_a_server_without_the_transport_offers_the_next_the_trainer_lists(monkeypatch):
    """The trainer lists the double first; a server that cannot make it (its maker raises
    OSError, as a segment the machine cannot make does) offers the next, or none."""

    def cannot(terms: ChannelTerms) -> ServerEnd:
        raise OSError("no room for a mailbox")

    with serving(monkeypatch, cannot) as server:
        _, (transport, rounds) = drive(server, "auto", 3)
        assert transport == ("shm" if DOORBELL_AVAILABLE else "zenoh") and rounds == 0
        with pytest.raises(errors.ConnectError, match=f"transport {TRANSPORT}: server double"):
            drive(server, TRANSPORT, 1)  # type: ignore[arg-type]  # a transport of its own
        assert server.arenas.groups == {}  # the arenas of a refused channel are not kept
