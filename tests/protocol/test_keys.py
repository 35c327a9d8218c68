"""Key expressions: the builders make the documented keys, the parsers invert them, and a name
or key that would change the key's meaning is refused.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from overtake.protocol import keys
from overtake.protocol.errors import DecodeError

from tests.support.protocol_messages import names


def test_builders_produce_the_documented_keys():
    assert keys.server_request("s1") == "overtake/server/s1/request"
    assert keys.server_actions("s1", "t1") == "overtake/server/s1/actions/t1"
    assert keys.server_actions_all("s1") == "overtake/server/s1/actions/*"
    assert keys.trainer_steps("t1", "s1") == "overtake/trainer/t1/steps/s1"
    assert keys.trainer_steps_all("t1") == "overtake/trainer/t1/steps/*"
    assert keys.world("s1", 3) == "overtake/server/s1/world/3"
    assert keys.world("s1") == "overtake/server/s1/world/*"
    assert keys.world_all() == "overtake/server/*/world/*"
    assert keys.server_alive("s1") == "overtake/alive/server/s1"
    assert keys.trainer_alive("t1") == "overtake/alive/trainer/t1"
    assert keys.ALL_SERVER_REQUESTS == "overtake/server/*/request"
    assert keys.ALL_TRAINERS_ALIVE == "overtake/alive/trainer/*"
    assert keys.ALL_SERVERS_ALIVE == "overtake/alive/server/*"


@settings(max_examples=100, deadline=None)
@given(server=names, trainer=names, arena=st.integers(0, 2**62))
def test_parsers_invert_builders(server, trainer, arena):
    assert keys.parse_server_actions(keys.server_actions(server, trainer)) == (server, trainer)
    assert keys.parse_trainer_alive(keys.trainer_alive(trainer)) == trainer
    assert keys.parse_server_alive(keys.server_alive(server)) == server
    assert keys.parse_server_request(keys.server_request(server)) == server
    assert keys.parse_world(keys.world(server, arena)) == (server, arena)


@pytest.mark.parametrize(
    "build",
    [
        lambda bad: keys.server_request(bad),
        lambda bad: keys.server_actions("s", bad),
        lambda bad: keys.server_actions(bad, "t"),
        lambda bad: keys.server_actions_all(bad),
        lambda bad: keys.trainer_steps(bad, "s"),
        lambda bad: keys.trainer_steps("t", bad),
        lambda bad: keys.trainer_steps_all(bad),
        lambda bad: keys.world(bad),
        lambda bad: keys.server_alive(bad),
        lambda bad: keys.trainer_alive(bad),
    ],
)
@pytest.mark.parametrize("bad", ["a/b", "*", "**", "", "a?b"])
def test_builders_refuse_names_that_would_change_the_key(build, bad):
    with pytest.raises(DecodeError):
        build(bad)


@pytest.mark.parametrize(
    "parse, key",
    [
        (keys.parse_server_actions, "other/server/s/actions/t"),  # wrong root
        (keys.parse_server_actions, "overtake/server/s/actions"),  # too few segments
        (keys.parse_server_actions, "overtake/server/s/actions/t/x"),  # too many segments
        (keys.parse_server_actions, "overtake/server/s/world/t"),  # wrong literal
        (keys.parse_server_actions, "overtake/server/*/actions/t"),  # wildcard server
        (keys.parse_server_actions, "overtake/server/s/actions/**"),  # wildcard trainer
        (keys.parse_server_actions, "overtake/server/s/actions/"),  # empty name
        (keys.parse_trainer_alive, "overtake/alive/trainer/a/b"),  # name with '/'
        (keys.parse_trainer_alive, "overtake/alive/server/t"),
        (keys.parse_trainer_alive, "overtake/alive/trainer/t*"),
        (keys.parse_server_alive, "overtake/alive/server"),
        (keys.parse_server_alive, "/overtake/alive/server/s"),
        (keys.parse_server_request, "overtake/server/s/requests"),
        (keys.parse_server_request, "overtake/server/*/request"),
        (keys.parse_world, "overtake/server/s/world/*"),
        (keys.parse_world, "overtake/server/s/world/x"),
        (keys.parse_world, "overtake/server/s/world/-1"),
        (keys.parse_world, "overtake/server/s/world"),
        (keys.parse_world, "overtake/trainer/s/world/1"),
    ],
)
def test_malformed_keys_are_refused(parse, key):
    with pytest.raises(DecodeError) as err:
        parse(key)
    # The message shows what came: the whole key, or the one segment that is wrong.
    assert any(repr(part) in str(err.value) for part in [key, *key.split("/")])
