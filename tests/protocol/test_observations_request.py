"""Protocol 1.10: an open request names the observations the trainer reads, a typed field
instead of ``<sensor>.enabled`` overrides (the server turns the other sensors off)."""

from __future__ import annotations

import msgpack
import pytest

from overtake.protocol import codec
from overtake.protocol.errors import DecodeError
from overtake.protocol.messages import MAX_OBSERVATIONS, OpenRequest


def open_request(**changes) -> OpenRequest:
    values = dict(
        trainer="t", preset="min2018", overrides={}, arenas=1, agents_per_arena=1, claim=1, seed=0
    )
    values.update(changes)
    return OpenRequest(**values)


def test_the_observations_travel_and_are_checked():
    request = open_request(observations=("ego", "lidar"))
    assert codec.decode(codec.encode(request), OpenRequest).observations == ("ego", "lidar")
    with pytest.raises(DecodeError, match="distinct"):
        open_request(observations=("ego", "ego"))
    with pytest.raises(DecodeError, match=f"at most {MAX_OBSERVATIONS} observations"):
        open_request(observations=tuple(f"o{i}" for i in range(MAX_OBSERVATIONS + 1)))
    with pytest.raises(DecodeError, match="observation must be"):
        open_request(observations=("camera/left",))


def test_an_older_trainer_names_none_and_gets_every_observation():
    major, _, tag, fields = msgpack.unpackb(codec.encode(open_request()), raw=False)
    del fields["observations"], fields["transports"]
    back = codec.decode(msgpack.packb([major, 9, tag, fields], use_bin_type=True), OpenRequest)
    assert back.observations == ()
