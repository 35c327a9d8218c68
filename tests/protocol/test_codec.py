"""The codec: round trips of every message type, robustness against garbage (random bytes,
truncations, corruptions, structural mutations) and numpy scalars turned plain.

No Zenoh here: everything is bytes in, bytes out, so the whole file runs in a few seconds.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from overtake.protocol.codec import decode, encode
from overtake.protocol.errors import DecodeError, ProtocolError
from overtake.protocol.messages import MESSAGE_TYPES, Ack, ErrorReply, OpenRequest, ResetRequest

from tests.support.protocol_messages import (
    FAST,
    MAJOR,
    MESSAGES,
    MINOR,
    any_message,
    arrays_in,
    decode_or_refuse,
    frame_of,
    ints,
    pack,
    sample_status,
    sample_steps,
    wire_dtype_names,
)

# --- round trips ---------------------------------------------------------------------------


def test_strategies_cover_every_message_type():
    # A message type added to the protocol without a strategy here would go untested.
    assert set(MESSAGES) == set(MESSAGE_TYPES)


@pytest.mark.parametrize("tag", sorted(MESSAGE_TYPES))
@FAST
@given(data=st.data())
def test_round_trip_preserves_every_message(tag, data):
    message = data.draw(MESSAGES[tag])
    assert type(message) is MESSAGE_TYPES[tag]
    frame = encode(message)
    back = decode(frame)
    assert type(back) is type(message)
    assert back == message
    # The encoding is canonical: what comes back encodes to the very same bytes, which also
    # checks the round trip without relying on Message.__eq__.
    assert encode(back) == frame
    # Zenoh hands payloads over as bytearray or memoryview as often as bytes.
    assert decode(bytearray(frame)) == message
    assert decode(memoryview(frame)) == message
    for array in arrays_in(back):
        # Callers modify what they receive (e.g. in-place normalisation): no read-only views
        # of the frame buffer, and native byte order so numpy math is not slowed down.
        assert array.flags.writeable
        assert array.dtype.isnative
        array[...] = array  # would raise on a read-only array


def test_message_equality_is_not_vacuous():
    # The round trip leans on Message.__eq__; it must see dtype and value differences.
    base = sample_steps()
    assert base == sample_steps()
    other_dtype = sample_steps()
    object.__setattr__(other_dtype, "observations", {"lidar": np.zeros((3, 4), np.float64)})
    assert base != other_dtype
    other_value = sample_steps()
    other_value.observations["lidar"][0, 0] = 1.0
    assert base != other_value
    assert Ack(message="a") != ErrorReply(code="a", message="a")


def test_strided_and_big_endian_arrays_travel_as_native_values():
    # Arrays sliced out of a bigger simulation state are non-contiguous; some sources hand
    # over big-endian data. Both must arrive with the same values in native order.
    state = np.arange(24, dtype=np.float32).reshape(4, 6)
    big = np.arange(3, dtype=">f8")
    steps = sample_steps()
    strided = state[:, ::2].T  # (3, 4), neither C- nor F-contiguous
    assert not strided.flags.c_contiguous
    object.__setattr__(steps, "observations", {"strided": strided, "big": big})
    back = decode(encode(steps))
    np.testing.assert_array_equal(back.observations["strided"], strided)
    assert back.observations["strided"].dtype == np.float32
    np.testing.assert_array_equal(back.observations["big"], big)
    assert back.observations["big"].dtype == np.dtype("<f8")


def test_array_of_a_dtype_the_wire_lacks_is_refused_on_encode():
    steps = sample_steps()
    object.__setattr__(steps, "observations", {"half": np.zeros((3, 2), np.float16)})
    with pytest.raises(TypeError, match="float16"):
        encode(steps)


# --- robustness ----------------------------------------------------------------------------


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=256))
def test_random_bytes_decode_or_raise_protocol_error(data):
    decode_or_refuse(data)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(MESSAGE_TYPES)), st.binary(max_size=256))
def test_random_body_after_a_valid_header_decodes_or_raises_protocol_error(tag, tail):
    # Pure random bytes rarely get past the version check; a real header sends the garbage
    # on into the field converters.
    decode_or_refuse(b"\x94" + pack(MAJOR) + pack(MINOR) + pack(tag) + tail)


@FAST
@given(any_message)
def test_every_truncation_of_a_valid_frame_is_refused(message):
    frame = encode(message)
    for end in range(len(frame)):
        try:
            decode(frame[:end])
        except ProtocolError:
            continue
        pytest.fail(f"a {end}-byte prefix of a {len(frame)}-byte frame decoded")
    # Trailing bytes are as wrong as missing ones.
    with pytest.raises(DecodeError):
        decode(frame + b"\x00")


@settings(
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_single_byte_corruptions_decode_or_raise_protocol_error(data):
    frame = bytearray(encode(data.draw(any_message)))
    at = data.draw(st.integers(0, len(frame) - 1))
    frame[at] = data.draw(st.integers(0, 255).filter(lambda b: b != frame[at]))
    result = decode_or_refuse(bytes(frame))
    if result is not None:
        # Whatever decode accepts is a well-formed message: it re-encodes and round-trips.
        assert decode(encode(result)) == result


# Random msgpack values, including array-like maps with odd dtypes, shapes and data.
_scalars = (
    st.none() | st.booleans() | ints | st.floats() | st.text(max_size=6) | st.binary(max_size=12)
)


_array_like = st.fixed_dictionaries(
    {
        "dtype": wire_dtype_names | st.text(max_size=6) | st.lists(ints, max_size=2),
        "shape": st.lists(st.integers(-2, 2**31) | st.booleans() | st.text(max_size=2), max_size=7),
        "data": st.binary(max_size=24) | st.text(max_size=4),
    }
)


msgpack_values = st.recursive(
    _scalars | _array_like,
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3)
    ),
    max_leaves=8,
)


def _nodes(node, path=()):
    yield path
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _nodes(value, (*path, key))
    elif isinstance(node, list):
        for index, value in enumerate(node):
            yield from _nodes(value, (*path, index))


@settings(
    max_examples=300,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(data=st.data())
def test_structural_mutations_decode_or_raise_protocol_error(data):
    # Byte flips mostly break msgpack itself; replacing, deleting or adding one node of the
    # decoded tree reaches every field converter and every check() with well-formed msgpack.
    frame = frame_of(data.draw(any_message))
    path = data.draw(st.sampled_from(list(_nodes(frame))[1:]))
    parent = frame
    for step in path[:-1]:
        parent = parent[step]
    action = data.draw(st.sampled_from(["replace", "delete", "add"]))
    if action == "delete" and isinstance(parent, dict):
        del parent[path[-1]]
    elif action == "add" and isinstance(parent, dict):
        parent[data.draw(st.text(max_size=6))] = data.draw(msgpack_values)
    else:
        parent[path[-1]] = data.draw(msgpack_values)
    decode_or_refuse(pack(frame))


# --- numpy scalars -------------------------------------------------------------------------


def test_numpy_scalars_encode_and_decode_as_plain_python_values():
    # Trainers routinely pass np.int64 seeds (rng.integers) and numpy-typed overrides. The
    # dataclass checks accept them (comparisons work on numpy scalars); the codec turns them
    # into plain Python values, so the peer sees ints, floats and bools.
    request = OpenRequest(
        trainer=np.str_("trainer"),
        preset="min2018",
        overrides={
            "f": np.float32(0.1),
            "i": np.int64(-3),
            "b": np.bool_(True),
            "d": np.float64(2.5),
        },
        arenas=np.int64(2),
        agents_per_arena=np.int32(3),
        claim=np.uint8(2),
        seed=np.int64(7),
    )
    back = decode(encode(request))
    assert back.seed == 7 and type(back.seed) is int
    assert (back.arenas, back.agents_per_arena, back.claim) == (2, 3, 2)
    assert all(type(v) is int for v in (back.arenas, back.agents_per_arena, back.claim))
    assert back.overrides == {"f": float(np.float32(0.1)), "i": -3, "b": True, "d": 2.5}
    assert [type(v) for v in back.overrides.values()] == [float, int, bool, float]
    assert type(back.trainer) is str
    assert back == OpenRequest(
        trainer="trainer",
        preset="min2018",
        overrides={"f": float(np.float32(0.1)), "i": -3, "b": True, "d": 2.5},
        arenas=2,
        agents_per_arena=3,
        claim=2,
        seed=7,
    )


def test_numpy_scalars_inside_tuples_and_float_fields_become_plain():
    reset = ResetRequest(
        trainer="t",
        ticket=b"",
        group=np.int16(4),
        arenas=(np.int32(0), np.int64(5)),
        seeds=(np.uint64(9), None),
    )
    back = decode(encode(reset))
    assert back == ResetRequest(trainer="t", ticket=b"", group=4, arenas=(0, 5), seeds=(9, None))
    status = sample_status()
    object.__setattr__(status, "step_deadline_s", np.float32(0.5))
    back = decode(encode(status))
    assert back.step_deadline_s == 0.5 and type(back.step_deadline_s) is float


def test_numpy_seed_out_of_range_is_refused_like_a_python_one():
    with pytest.raises(DecodeError, match="seed must be from 0"):
        OpenRequest(
            trainer="t",
            preset="p",
            overrides={},
            arenas=1,
            agents_per_arena=1,
            claim=1,
            seed=np.uint64(2**64 - 1),
        )
