"""Validation with clear messages: a malformed frame, field, array, action or name is refused,
built or decoded, with a message that names what was expected and what came; and the size
limits on frames and text.
"""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from overtake.protocol import codec, messages
from overtake.protocol.codec import decode, encode
from overtake.protocol.errors import DecodeError
from overtake.protocol.messages import (
    ACTION_COUNT,
    PROTOCOL_VERSION,
    Ack,
    Actions,
    ErrorReply,
    JoinRequest,
    StatusRequest,
    Steps,
)

from tests.support.protocol_messages import (
    MAJOR,
    MINOR,
    frame_of,
    pack,
    sample_actions,
    sample_status,
    sample_steps,
    wire_array_value,
)


@pytest.mark.parametrize("tag", ["bogus", 7, None])
def test_unknown_type_tag_is_refused_naming_the_known_ones(tag):
    with pytest.raises(DecodeError) as err:
        decode(pack([MAJOR, MINOR, tag, {}]))
    assert repr(tag) in str(err.value)
    for known in ("actions", "steps", "status_request"):
        assert repr(known) in str(err.value)


@pytest.mark.parametrize(
    "frame",
    [[], [MAJOR, MINOR, "ack"], {"a": 1}, "ack", [MAJOR, MINOR, "ack", {"message": "m"}, 0]],
)
def test_frame_that_is_not_a_four_element_list_is_refused(frame):
    with pytest.raises(DecodeError, match=r"\[major, minor, type, body\]"):
        decode(pack(frame))


def test_missing_field_is_refused_naming_it():
    frame = frame_of(JoinRequest(trainer="t", arena=0, agents=1))
    del frame[3]["agents"]
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert "JoinRequest" in str(err.value) and "'agents'" in str(err.value)


@pytest.mark.parametrize(
    "field, value, expected, came",
    [
        ("arena", "3", "integer", "str"),
        ("arena", 3.0, "integer", "float"),
        ("arena", True, "integer", "bool"),  # bool is an int subclass in Python, not on the wire
        ("arena", None, "integer", "NoneType"),
        ("trainer", 5, "text", "int"),
    ],
)
def test_wrong_field_type_is_refused_naming_field_expectation_and_arrival(
    field, value, expected, came
):
    frame = frame_of(JoinRequest(trainer="t", arena=0, agents=1))
    frame[3][field] = value
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    message = str(err.value)
    assert f"join.{field}" in message and expected in message and came in message


def test_wrong_type_inside_a_tuple_and_a_nested_record_names_the_path():
    frame = frame_of(sample_status())
    frame[3]["groups"][0]["arenas"][1] = "one"
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert "status.groups[0].arenas[1]" in str(err.value) and "str" in str(err.value)


def test_array_with_the_wrong_wire_dtype_is_refused():
    frame = frame_of(sample_actions())
    frame[3]["agents"] = wire_array_value(np.array([3, 1, 2], dtype=np.int64))
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert "agents" in str(err.value) and "int32" in str(err.value) and "int64" in str(err.value)


def test_array_with_a_dtype_the_wire_lacks_is_refused():
    frame = frame_of(sample_actions())
    frame[3]["agents"]["dtype"] = "float16"
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert "'float16'" in str(err.value) and "int32" in str(err.value)


def test_array_whose_bytes_do_not_match_its_shape_is_refused():
    frame = frame_of(sample_actions())
    frame[3]["agents"]["data"] = frame[3]["agents"]["data"][:8]
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert "actions.agents" in str(err.value)
    assert "needs 12 bytes" in str(err.value) and "got 8" in str(err.value)


@pytest.mark.parametrize("shape", [[1, 1, 1, 1, 1, 1], [-1], [True], "3"])
def test_array_shape_that_is_not_a_short_list_of_sizes_is_refused(shape):
    frame = frame_of(sample_actions())
    frame[3]["agents"]["shape"] = shape
    with pytest.raises(DecodeError, match="shape must be a list"):
        decode(pack(frame))


def test_bool_array_holding_a_byte_other_than_0_or_1_is_refused():
    frame = frame_of(sample_steps())
    frame[3]["terminated"]["data"] = b"\x00\x02\x01"
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert "steps.terminated" in str(err.value) and "0 and 1" in str(err.value)


@pytest.mark.parametrize("bad", [ACTION_COUNT, -1])
def test_out_of_range_action_is_refused_built_or_decoded(bad):
    with pytest.raises(DecodeError) as err:
        sample_actions(actions=(0, bad, 1))
    assert f"[0, {ACTION_COUNT})" in str(err.value) and f"[{bad}]" in str(err.value)
    frame = frame_of(sample_actions())
    frame[3]["actions"]["data"] = np.array([0, bad, 1], dtype="<i8").tobytes()
    with pytest.raises(DecodeError) as err:
        decode(pack(frame))
    assert f"[0, {ACTION_COUNT})" in str(err.value) and f"[{bad}]" in str(err.value)


def test_duplicate_agent_ids_in_actions_are_refused_built_or_decoded():
    with pytest.raises(DecodeError, match=r"distinct, got \[1, 2, 1\]"):
        sample_actions(agents=(1, 2, 1))
    frame = frame_of(sample_actions())
    frame[3]["agents"]["data"] = np.array([1, 2, 1], dtype="<i4").tobytes()
    with pytest.raises(DecodeError, match=r"distinct, got \[1, 2, 1\]"):
        decode(pack(frame))


def test_actions_of_another_length_than_agents_are_refused():
    with pytest.raises(DecodeError, match=r"actions must have shape \(3\), got \(2,\)"):
        sample_actions(agents=(1, 2, 3), actions=(0, 0))


def test_steps_whose_reward_length_differs_from_agents_is_refused():
    with pytest.raises(DecodeError, match=r"reward must have shape \(3\), got \(2,\)"):
        sample_steps(k=3, reward_rows=2)


def test_steps_observation_without_a_row_per_agent_is_refused():
    steps = sample_steps()
    frame = frame_of(steps)
    frame[3]["observations"]["lidar"] = wire_array_value(np.zeros((2, 4), np.float32))
    with pytest.raises(DecodeError, match=r"'lidar' must have 3 rows.*\(2, 4\)"):
        decode(pack(frame))


@pytest.mark.parametrize("name", ["a/b", "*", "**", "team*", "a$b", "a b", "", "x" * 65])
def test_trainer_name_that_would_break_a_key_expression_is_refused(name):
    with pytest.raises(DecodeError) as err:
        JoinRequest(trainer=name, arena=0, agents=1)
    assert "trainer" in str(err.value) and repr(name) in str(err.value)
    frame = frame_of(JoinRequest(trainer="ok", arena=0, agents=1))
    frame[3]["trainer"] = name
    with pytest.raises(DecodeError, match="trainer"):
        decode(pack(frame))


def test_expect_refuses_another_type_but_always_accepts_an_error_reply():
    with pytest.raises(DecodeError) as err:
        decode(encode(StatusRequest()), expect=Actions)
    assert "actions" in str(err.value) and "status_request" in str(err.value)
    error = ErrorReply(code="bad_action", message="no")
    assert decode(encode(error), expect=Actions) == error
    assert decode(encode(StatusRequest()), expect=(Actions, StatusRequest)) == StatusRequest()
    with pytest.raises(DecodeError, match="actions or steps"):
        decode(encode(Ack(message="m")), expect=(Actions, Steps))


def test_frame_over_the_size_limit_is_refused_without_unpacking(monkeypatch):
    # Patching the limit codec.decode reads spares allocating 256 MiB; recording unpack
    # calls proves the size is checked before msgpack sees a byte.
    limit = 64
    monkeypatch.setattr(codec, "MAX_FRAME_BYTES", limit)
    calls = []
    real_unpackb = msgpack.unpackb

    def recording_unpackb(*args, **kwargs):
        calls.append(len(args[0]))
        return real_unpackb(*args, **kwargs)

    monkeypatch.setattr(codec.msgpack, "unpackb", recording_unpackb)
    with pytest.raises(DecodeError) as err:
        decode(b"\x00" * (limit + 1))
    assert calls == []
    assert str(limit + 1) in str(err.value) and str(limit) in str(err.value)
    # A frame exactly at the limit goes on to be unpacked.
    at_limit = next(
        Ack(message="x" * n) for n in range(limit) if len(encode(Ack(message="x" * n))) == limit
    )
    assert decode(encode(at_limit)) == at_limit
    assert calls == [limit]


def test_text_over_the_limit_is_refused_both_ways():
    too_long = "x" * (messages.MAX_TEXT_CHARS + 1)
    # A peer that skipped the check still cannot make us accept it...
    frame = msgpack.packb(
        [PROTOCOL_VERSION[0], PROTOCOL_VERSION[1], "ack", {"message": too_long}], use_bin_type=True
    )
    with pytest.raises(DecodeError, match=str(messages.MAX_TEXT_CHARS)):
        decode(frame)
    # ...and we never build a frame the other side would refuse.
    with pytest.raises(ValueError, match=str(messages.MAX_TEXT_CHARS)):
        encode(Ack(message=too_long))


# The limit is in characters: msgpack's own limit counts UTF-8 bytes, so non-ASCII text near
# the limit must still pass.
def test_text_under_the_character_limit_round_trips_whatever_its_script():
    text = "é" * (messages.MAX_TEXT_CHARS // 2 + 1)  # fewer characters than the limit...
    assert len(text) < messages.MAX_TEXT_CHARS < len(text.encode())  # ...more bytes
    assert decode(encode(Ack(message=text))) == Ack(message=text)


def test_real_size_limit_is_the_documented_one():
    assert codec.MAX_FRAME_BYTES == messages.MAX_FRAME_BYTES == 256 * 2**20


def test_encode_refuses_what_is_not_a_message():
    with pytest.raises(TypeError, match="dict"):
        encode({"message": "m"})  # type: ignore[arg-type]
