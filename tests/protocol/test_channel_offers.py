"""Protocol 1.10: the negotiation names a transport. An open request lists the channels the
trainer can take, the reply offers one tagged with its transport, and a transport's offer type
is one class; the 1.6 fields stay for older peers."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import msgpack
import numpy as np
import pytest

from overtake.protocol import codec
from overtake.protocol.channel_offers import (
    MAX_TRANSPORTS,
    ChannelOffer,
    offer_type,
    offered_transports,
)
from overtake.protocol.errors import DecodeError
from overtake.protocol.messages import (
    ACTION_COUNT,
    ACTION_NAMES,
    PROTOCOL_VERSION,
    BehaviourSpec,
    ObservationSpec,
    Opened,
    OpenRequest,
    ShmArray,
    ShmOffer,
    Steps,
)


@dataclass(frozen=True, eq=False)
class PigeonOffer(ChannelOffer):
    """A transport of this test's own: defining it is all the codec needs."""

    TRANSPORT: ClassVar[str] = "pigeon"
    loft: str


def open_request(**changes) -> OpenRequest:
    values = dict(
        trainer="t", preset="min2018", overrides={}, arenas=1, agents_per_arena=1, claim=1, seed=0
    )
    values.update(changes)
    return OpenRequest(**values)


def opened(**changes) -> Opened:
    steps = Steps(
        server="s",
        group=1,
        round=0,
        agents=np.zeros(1, np.int32),
        observations={"ego": np.zeros((1, 2), np.float32)},
        reward=np.zeros(1),
        terminated=np.zeros(1, bool),
        truncated=np.zeros(1, bool),
        action_applied=np.full(1, -1, np.int64),
        late=np.zeros(1, bool),
        action_mask=np.ones((1, 5), np.int8),
        reward_terms=np.zeros((1, 0)),
        metrics=np.zeros((1, 0)),
    )
    values = dict(
        server="s",
        group=1,
        arenas=(0,),
        ticket=bytes(16),
        spec=BehaviourSpec(
            name="Highway",
            preset="min2018",
            observations=(
                ObservationSpec(
                    name="ego",
                    shape=(2,),
                    dtype="float32",
                    low=np.zeros(2, np.float32),
                    high=np.ones(2, np.float32),
                ),
            ),
            action_branches=(ACTION_COUNT,),
            action_names=ACTION_NAMES,
            reward_terms=(),
            metric_fields=(),
            decision_period_s=0.4,
            max_episode_steps=100,
            agents_per_arena=1,
            config_json="{}",
        ),
        steps=steps,
        server_minor=PROTOCOL_VERSION[1],
    )
    values.update(changes)
    return Opened(**values)


def shm_offer() -> ShmOffer:
    return ShmOffer(name="overtake-1-ab", nonce=bytes(range(16)), size_bytes=4096)


def body(frame: bytes) -> dict:
    return msgpack.unpackb(frame, raw=False)[3]


def test_an_offer_travels_tagged_with_its_transport_and_decodes_as_its_type():
    offer = shm_offer()
    frame = codec.encode(opened(offer=offer, shm=offer))
    assert body(frame)["offer"][0] == "shm"
    back = codec.decode(frame, Opened)
    assert isinstance(back.offer, ShmOffer) and back.offer == offer
    assert back.shm == offer  # the 1.6 field, untagged, for a 1.9 trainer
    assert isinstance(body(frame)["shm"], dict)


def test_a_transport_is_one_offer_type():
    assert offer_type("pigeon") is PigeonOffer
    assert offered_transports()[0] == "shm"  # the house's own first, then this test's
    back = codec.decode(codec.encode(opened(offer=PigeonOffer(loft="roof"))), Opened)
    assert back.offer == PigeonOffer(loft="roof")


@pytest.mark.parametrize(
    ("offer", "expected"),
    [
        (["smoke", {"puffs": 3}], "expected a channel offer of .*shm.*, got 'smoke'"),
        ("shm", "expected a \\[transport, offer\\] pair, got str"),
        (["shm"], "expected a \\[transport, offer\\] pair"),
        ([7, {}], "expected a transport's name, got int"),
        (["shm", {"name": "x"}], "ShmOffer lacks field"),
        (["pigeon", {"loft": 5}], "offer.loft"),
    ],
)
def test_a_malformed_offer_is_refused_saying_what_came(offer, expected):
    major, minor, tag, fields = msgpack.unpackb(codec.encode(opened()), raw=False)
    fields["offer"] = offer
    frame = msgpack.packb([major, minor, tag, fields], use_bin_type=True)
    with pytest.raises(DecodeError, match=expected):
        codec.decode(frame, Opened)


def test_a_transport_name_is_taken_once_and_zenoh_is_no_offer():
    with pytest.raises(TypeError, match="PigeonOffer's"):

        @dataclass(frozen=True, eq=False)
        class OtherPigeon(ChannelOffer):
            TRANSPORT: ClassVar[str] = "pigeon"

    with pytest.raises(TypeError, match="every peer's transport"):

        @dataclass(frozen=True, eq=False)
        class ZenohOffer(ChannelOffer):
            TRANSPORT: ClassVar[str] = "zenoh"

    with pytest.raises(DecodeError, match="transport must be"):

        @dataclass(frozen=True, eq=False)
        class Spaced(ChannelOffer):
            TRANSPORT: ClassVar[str] = "two words"


def test_an_open_request_lists_transports_and_unknown_ones_are_no_error():
    request = open_request(transports=("pigeon", "teleport", "shm"))
    back = codec.decode(codec.encode(request), OpenRequest)
    assert back.transports == ("pigeon", "teleport", "shm")
    assert back.wanted_transports == ("pigeon", "teleport", "shm")
    with pytest.raises(DecodeError, match="distinct"):
        open_request(transports=("shm", "shm"))
    with pytest.raises(DecodeError, match="transport must be"):
        open_request(transports=("a/b",))
    with pytest.raises(DecodeError, match=f"at most {MAX_TRANSPORTS}"):
        open_request(transports=tuple(f"t{i}" for i in range(MAX_TRANSPORTS + 1)))


def test_an_older_trainer_asks_for_shared_memory_by_its_flag():
    """A 1.9 trainer's request has no transports; its shm flag means it lists shm."""
    major, _, tag, fields = msgpack.unpackb(codec.encode(open_request(shm=True)), raw=False)
    del fields["transports"]
    frame = msgpack.packb([major, 9, tag, fields], use_bin_type=True)
    back = codec.decode(frame, OpenRequest)
    assert back.transports == () and back.wanted_transports == ("shm",)
    assert open_request().wanted_transports == ()  # zenoh only


def test_an_older_server_s_reply_decodes_with_no_tagged_offer():
    offer = shm_offer()
    major, _, tag, fields = msgpack.unpackb(codec.encode(opened(shm=offer)), raw=False)
    del fields["offer"]
    back = codec.decode(msgpack.packb([major, 9, tag, fields], use_bin_type=True), Opened)
    assert back.offer is None and back.shm == offer


def test_a_layout_still_checks_inside_a_tagged_offer():
    layout = (ShmArray(name="agents", offset=128, dtype="int32", shape=(1,)),)
    with pytest.raises(DecodeError, match="layout names each"):
        ShmOffer(name="overtake-1-ab", nonce=bytes(16), size_bytes=4096, layout=layout)
