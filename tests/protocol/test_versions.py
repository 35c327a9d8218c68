"""The wire protocol: codec round trips, robustness against garbage, validation messages,
numpy scalars, key expressions and the error hierarchy.

No Zenoh here: everything is bytes in, bytes out, so the whole file runs in a few seconds.
"""

from __future__ import annotations

import dataclasses
import inspect
from dataclasses import fields

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from overtake.protocol import codec, errors, keys, messages
from overtake.protocol.codec import decode, encode, version_text
from overtake.protocol.errors import (
    ERRORS_BY_CODE,
    DecodeError,
    ProtocolError,
    VersionMismatch,
    error_from_code,
)
from overtake.protocol.messages import (
    ACTION_COUNT,
    ACTION_NAMES,
    MESSAGE_TYPES,
    NAME_PATTERN,
    PROTOCOL_VERSION,
    WIRE_DTYPES,
    Ack,
    Actions,
    BehaviourSpec,
    CarSpec,
    CloseRequest,
    ErrorReply,
    GroupState,
    GroupStatus,
    JoinRequest,
    Message,
    ObservationSpec,
    Opened,
    OpenRequest,
    Part,
    Reach,
    ResetRequest,
    RestoreRequest,
    RoadSpec,
    ShmArray,
    ShmOffer,
    SnapshotRequest,
    StatusReply,
    StatusRequest,
    Steps,
    WorldFrame,
)
from overtake.protocol.shm_messages import ACTION_ARRAY_NAMES, STEPS_ARRAYS

MAJOR, MINOR = PROTOCOL_VERSION

# Hypothesis runs are sized so the file stays fast; deadlines are off because the first
# example of a strategy pays for numpy and regex compilation and would flake on a slow box.
FAST = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


# --- strategies ----------------------------------------------------------------------------

# Every integer msgpack can carry: the extremes are where a codec loses bits.
ints = st.integers(-(2**63), 2**64 - 1)
# NaN and infinities included: Message equality treats NaN as equal to NaN.
floats = st.floats()
texts = st.text(max_size=12)
names = st.from_regex(NAME_PATTERN, fullmatch=True)
seeds = st.integers(0, 2**63 - 1)
wire_dtype_names = st.sampled_from(sorted(WIRE_DTYPES))


def wire_array(dtype: str, shape, **kwargs):
    return hnp.arrays(WIRE_DTYPES[dtype], shape, **kwargs)


def per_agent_tail_shapes():
    """The axes after the agent axis: up to MAX_ARRAY_DIMS in all, empty sizes included."""
    return hnp.array_shapes(
        min_dims=0, max_dims=messages.MAX_ARRAY_DIMS - 1, min_side=0, max_side=2
    )


@st.composite
def observation_dicts(draw, rows: int):
    obs = {}
    for name in draw(st.lists(names, max_size=3, unique=True)):
        shape = (rows, *draw(per_agent_tail_shapes()))
        obs[name] = draw(wire_array(draw(wire_dtype_names), shape))
    return obs


@st.composite
def observation_specs(draw):
    dtype = draw(wire_dtype_names)
    shape = draw(
        hnp.array_shapes(min_dims=1, max_dims=messages.MAX_ARRAY_DIMS - 1, min_side=1, max_side=2)
    )
    metres = st.floats(min_value=0.0, max_value=1e5)
    return ObservationSpec(
        name=draw(names),
        shape=shape,
        dtype=dtype,
        low=draw(wire_array(dtype, shape)),
        high=draw(wire_array(dtype, shape)),
        columns=tuple(
            draw(st.one_of(st.just([]), st.lists(texts, min_size=shape[-1], max_size=shape[-1])))
        ),
        reach=draw(st.one_of(st.none(), st.builds(Reach, metres, metres, metres, metres))),
    )


@st.composite
def behaviour_specs(draw):
    observations = draw(
        st.lists(observation_specs(), min_size=1, max_size=3, unique_by=lambda o: o.name)
    )
    return BehaviourSpec(
        name=draw(texts),
        preset=draw(texts),
        observations=tuple(observations),
        action_branches=(ACTION_COUNT,),
        action_names=tuple(draw(st.lists(texts, min_size=ACTION_COUNT, max_size=ACTION_COUNT))),
        reward_terms=tuple(draw(st.lists(texts, max_size=3))),
        metric_fields=tuple(draw(st.lists(texts, max_size=3))),
        decision_period_s=draw(st.floats(min_value=0.0, exclude_min=True)),
        max_episode_steps=draw(st.integers(1, 2**62)),
        agents_per_arena=draw(st.integers(1, messages.MAX_AGENTS_PER_ARENA)),
        config_json=draw(texts),
        road=RoadSpec(lane_count=draw(st.integers(1, 64)), lane_width_m=3.5),
        car=CarSpec(length_m=4.5, width_m=1.8, min_speed_kmh=0.0, max_speed_kmh=110.0),
    )


@st.composite
def steps_messages(draw):
    k = draw(st.integers(0, 4))
    terms, metrics = draw(st.integers(0, 3)), draw(st.integers(0, 3))
    return Steps(
        server=draw(names),
        group=draw(ints),
        round=draw(ints),
        agents=draw(wire_array("int32", (k,))),
        observations=draw(observation_dicts(k)),
        reward=draw(wire_array("float64", (k,))),
        terminated=draw(wire_array("bool", (k,))),
        truncated=draw(wire_array("bool", (k,))),
        action_applied=draw(wire_array("int64", (k,))),
        late=draw(wire_array("bool", (k,))),
        action_mask=draw(wire_array("int8", (k, ACTION_COUNT))),
        reward_terms=draw(wire_array("float64", (k, terms))),
        metrics=draw(wire_array("float64", (k, metrics))),
    )


@st.composite
def group_statuses(draw):
    return GroupStatus(
        group=draw(ints),
        preset=draw(texts),
        arenas=tuple(draw(st.lists(ints, max_size=4))),
        agents_per_arena=draw(ints),
        trainers=tuple(draw(st.lists(texts, max_size=3))),
        rounds=draw(ints),
        rounds_per_s=draw(floats),
        agent_steps_per_s=draw(floats),
        late_agents=draw(ints),
    )


@st.composite
def status_replies(draw):
    return StatusReply(
        server=draw(names),
        package_version=draw(texts),
        max_arenas=draw(ints),
        arenas_used=draw(ints),
        step_deadline_s=draw(floats),
        uptime_s=draw(floats),
        groups=tuple(draw(st.lists(group_statuses(), max_size=3))),
    )


overrides = st.dictionaries(texts, st.one_of(st.booleans(), ints, floats, texts), max_size=4)


@st.composite
def open_requests(draw):
    agents = draw(st.integers(1, messages.MAX_AGENTS_PER_ARENA))
    return OpenRequest(
        trainer=draw(names),
        preset=draw(names),
        overrides=draw(overrides),
        arenas=draw(st.integers(1, messages.MAX_ARENAS_PER_REQUEST)),
        agents_per_arena=agents,
        claim=draw(st.integers(1, agents)),
        seed=draw(st.none() | seeds),
        shm=draw(st.booleans()),
    )


@st.composite
def opened_messages(draw):
    return Opened(
        server=draw(names),
        group=draw(ints),
        arenas=tuple(draw(st.lists(ints, min_size=1, max_size=4))),
        ticket=draw(st.binary(min_size=16, max_size=64)),
        spec=draw(behaviour_specs()),
        steps=draw(steps_messages()),
        shm=draw(st.none() | shm_offers()),
    )


@st.composite
def shm_offers(draw):
    observations = draw(st.lists(names, max_size=3, unique=True))
    fields = [*ACTION_ARRAY_NAMES, *STEPS_ARRAYS, *(f"obs/{n}" for n in observations)]
    layout = tuple(
        ShmArray(
            name=name,
            offset=draw(st.integers(128, 2**20)),
            dtype=draw(st.sampled_from(sorted(messages.WIRE_DTYPES))),
            shape=tuple(draw(st.lists(st.integers(0, 100), max_size=4))),
        )
        for name in fields
    )
    return ShmOffer(
        name=draw(names),
        nonce=draw(st.binary(min_size=16, max_size=16)),
        size_bytes=draw(st.integers(128, messages.MAX_FRAME_BYTES)),
        layout=draw(st.just(()) | st.just(layout)),
    )


@st.composite
def reset_requests(draw):
    arenas = draw(st.lists(ints, max_size=4, unique=True))
    return ResetRequest(
        trainer=draw(names),
        ticket=draw(st.binary(max_size=64)),
        group=draw(ints),
        arenas=tuple(arenas),
        seeds=tuple(draw(st.lists(st.none() | seeds, min_size=len(arenas), max_size=len(arenas)))),
    )


@st.composite
def actions_messages(draw):
    k = draw(st.integers(0, 6))
    return Actions(
        trainer=draw(names),
        ticket=draw(st.binary(max_size=64)),
        group=draw(ints),
        round=draw(ints),
        agents=draw(wire_array("int32", (k,), unique=True)),
        actions=draw(wire_array("int64", (k,), elements=st.integers(0, ACTION_COUNT - 1))),
        shm=draw(st.booleans()),
    )


@st.composite
def world_frames(draw):
    v, n = draw(st.integers(0, 5)), draw(st.integers(0, 3))
    return WorldFrame(
        server=draw(names),
        group=draw(ints),
        arena=draw(ints),
        round=draw(ints),
        sim_time_s=draw(floats),
        lane_count=draw(ints),
        lane_width_m=draw(floats),
        agent_kind=draw(ints),
        agent_active=draw(wire_array("bool", (n,))),
        x_m=draw(wire_array("float64", (v,))),
        y_m=draw(wire_array("float64", (v,))),
        speed_mps=draw(wire_array("float32", (v,))),
        kind=draw(wire_array("int8", (v,))),
        active=draw(wire_array("bool", (v,))),
        observations=draw(observation_dicts(n)),
        reward=draw(wire_array("float64", (n,))),
        action_applied=draw(wire_array("int64", (n,))),
        **draw(reward_term_fields(n)),
    )


@st.composite
def reward_term_fields(draw, n):
    terms = draw(st.none() | st.integers(0, 3))
    if terms is None:
        return {}
    return {
        "reward_term_names": tuple(draw(st.lists(names, min_size=terms, max_size=terms))),
        "reward_terms": draw(wire_array("float64", (n, terms))),
    }


MESSAGES = {
    StatusRequest.TYPE: st.just(StatusRequest()),
    StatusReply.TYPE: status_replies(),
    OpenRequest.TYPE: open_requests(),
    JoinRequest.TYPE: st.builds(
        JoinRequest,
        trainer=names,
        arena=st.integers(0, 2**62),
        agents=st.integers(1, messages.MAX_AGENTS_PER_ARENA),
    ),
    Opened.TYPE: opened_messages(),
    ResetRequest.TYPE: reset_requests(),
    Steps.TYPE: steps_messages(),
    Actions.TYPE: actions_messages(),
    CloseRequest.TYPE: st.builds(
        CloseRequest, trainer=names, ticket=st.binary(max_size=64), group=ints
    ),
    SnapshotRequest.TYPE: st.builds(
        SnapshotRequest, trainer=names, ticket=st.binary(max_size=64), group=ints
    ),
    GroupState.TYPE: st.builds(GroupState, group=ints, state=st.binary(max_size=256)),
    RestoreRequest.TYPE: st.builds(
        RestoreRequest,
        trainer=names,
        ticket=st.binary(max_size=64),
        group=ints,
        state=st.binary(max_size=256),
    ),
    Ack.TYPE: st.builds(Ack, message=texts),
    ErrorReply.TYPE: st.builds(ErrorReply, code=texts, message=texts),
    WorldFrame.TYPE: world_frames(),
}
any_message = st.sampled_from(sorted(MESSAGES)).flatmap(MESSAGES.__getitem__)


# --- helpers ----------------------------------------------------------------------------------


def arrays_in(value):
    """Every numpy array anywhere inside a message."""
    if isinstance(value, np.ndarray):
        yield value
    elif isinstance(value, Part):
        for f in fields(value):
            yield from arrays_in(getattr(value, f.name))
    elif isinstance(value, dict):
        for item in value.values():
            yield from arrays_in(item)
    elif isinstance(value, (tuple, list)):
        for item in value:
            yield from arrays_in(item)


def frame_of(message: Message) -> list:
    """The frame of ``message`` as plain msgpack values, ready to be tampered with."""
    return msgpack.unpackb(encode(message), raw=False)


def pack(frame) -> bytes:
    return msgpack.packb(frame, use_bin_type=True)


def decode_or_refuse(data: bytes) -> Message | None:
    """decode's contract on untrusted bytes: a Message or a ProtocolError, nothing else.

    Any other exception propagates and fails the calling test.
    """
    try:
        result = decode(data)
    except ProtocolError:
        return None
    assert isinstance(result, Message)
    return result


def wire_array_value(array: np.ndarray) -> dict:
    return {"dtype": array.dtype.name, "shape": list(array.shape), "data": array.tobytes()}


def sample_actions(agents=(3, 1, 2), actions=(0, 4, 2)) -> Actions:
    return Actions(
        trainer="trainer-0",
        ticket=b"t" * 16,
        group=7,
        round=11,
        agents=np.array(agents, dtype=np.int32),
        actions=np.array(actions, dtype=np.int64),
    )


def sample_steps(k: int = 3, reward_rows: int | None = None) -> Steps:
    rows = k if reward_rows is None else reward_rows
    return Steps(
        server="srv",
        group=1,
        round=2,
        agents=np.arange(k, dtype=np.int32),
        observations={"lidar": np.zeros((k, 4), np.float32)},
        reward=np.zeros(rows, np.float64),
        terminated=np.zeros(k, bool),
        truncated=np.zeros(k, bool),
        action_applied=np.full(k, -1, np.int64),
        late=np.zeros(k, bool),
        action_mask=np.ones((k, ACTION_COUNT), np.int8),
        reward_terms=np.zeros((k, 2)),
        metrics=np.zeros((k, 3)),
    )


def sample_spec() -> BehaviourSpec:
    obs = ObservationSpec(
        name="lidar",
        shape=(4,),
        dtype="float32",
        low=np.zeros(4, np.float32),
        high=np.ones(4, np.float32),
        reach=Reach(range_m=80.0),
    )
    return BehaviourSpec(
        name="Highway",
        preset="min2018",
        observations=(obs,),
        action_branches=(ACTION_COUNT,),
        action_names=ACTION_NAMES,
        reward_terms=("a", "b"),
        metric_fields=("x", "y", "z"),
        decision_period_s=0.4,
        max_episode_steps=100,
        agents_per_arena=1,
        config_json="{}",
        road=RoadSpec(lane_count=5, lane_width_m=3.5),
        car=CarSpec(length_m=4.5, width_m=1.8, min_speed_kmh=40.0, max_speed_kmh=80.0),
    )


def sample_opened() -> Opened:
    return Opened(
        server="srv",
        group=1,
        arenas=(0, 1),
        ticket=b"k" * 16,
        spec=sample_spec(),
        steps=sample_steps(),
    )


def sample_status() -> StatusReply:
    group = GroupStatus(
        group=1,
        preset="min2018",
        arenas=(0, 1),
        agents_per_arena=1,
        trainers=("t",),
        rounds=10,
        rounds_per_s=5.0,
        agent_steps_per_s=10.0,
        late_agents=0,
    )
    return StatusReply(
        server="srv",
        package_version="0.1.0",
        max_arenas=8,
        arenas_used=2,
        step_deadline_s=0.5,
        uptime_s=3.0,
        groups=(group,),
    )


# --- 1. round trips ------------------------------------------------------------------------


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


# --- 2. robustness -------------------------------------------------------------------------


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


# --- 3. validation with clear messages -----------------------------------------------------


@pytest.mark.parametrize("major", [MAJOR + 1, MAJOR - 1])
def test_other_major_version_is_refused_naming_both_versions(major):
    body = frame_of(sample_actions())[3]
    with pytest.raises(VersionMismatch) as err:
        decode(pack([major, 0, "actions", body]))
    assert f"{major}.0" in str(err.value)
    assert version_text() in str(err.value)
    assert version_text() == f"{MAJOR}.{MINOR}"


def test_major_version_is_checked_before_the_body():
    # A peer of another major version may lay out its bodies differently: the version must
    # be what the trainer is told about, not some field error.
    with pytest.raises(VersionMismatch):
        decode(pack([MAJOR + 1, 0, "no-such-type", "not even a map"]))


def test_newer_minor_version_may_add_fields_the_current_minor_may_not():
    body = {"message": "hello", "added_in_a_later_minor": [1, 2]}
    assert decode(pack([MAJOR, MINOR + 1, "ack", body])) == Ack(message="hello")
    with pytest.raises(DecodeError) as err:
        decode(pack([MAJOR, MINOR, "ack", body]))
    assert "added_in_a_later_minor" in str(err.value)  # what came
    assert "'message'" in str(err.value)  # what was expected


def _world_frame(agents: int = 1, **extra) -> WorldFrame:
    """A small valid frame: ``agents`` agents and two traffic cars."""
    vehicles = agents + 2
    return WorldFrame(
        server="s",
        group=0,
        arena=1,
        round=2,
        sim_time_s=0.4,
        lane_count=5,
        lane_width_m=3.5,
        agent_kind=4,
        agent_active=np.ones(agents, bool),
        x_m=np.zeros(vehicles),
        y_m=np.zeros(vehicles),
        speed_mps=np.zeros(vehicles, np.float32),
        kind=np.array([4] * agents + [0, 1], np.int8),
        active=np.ones(vehicles, bool),
        observations={},
        reward=np.ones(agents),
        action_applied=np.zeros(agents, np.int64),
        **extra,
    )


def test_world_frame_of_a_1_0_peer_decodes_without_reward_terms():
    # 1.1 added the reward terms to world frames: a spectator of this version still reads an
    # older server's frames, and gets none...
    frame = _world_frame(
        reward_terms=np.array([[0.5, -0.25]]), reward_term_names=("speed", "lane_change")
    )
    *_, body = msgpack.unpackb(encode(frame), raw=False)
    assert body.pop("reward_term_names") == ["speed", "lane_change"]
    body.pop("reward_terms")
    old = decode(pack([MAJOR, 0, "world", body]))
    assert old.reward_terms is None and old.reward_term_names == ()
    assert old == dataclasses.replace(frame, reward_terms=None, reward_term_names=())
    # ...while a peer of this minor version must send them.
    with pytest.raises(DecodeError, match="reward_term"):
        decode(pack([MAJOR, MINOR, "world", body]))


def test_world_frame_reward_terms_must_match_their_names():
    with pytest.raises(DecodeError, match=r"reward_terms must have shape \(2, 3\)"):
        _world_frame(2, reward_terms=np.zeros((2, 2)), reward_term_names=("a", "b", "c"))
    with pytest.raises(DecodeError, match="without reward_terms"):
        _world_frame(2, reward_term_names=("a",))


def test_newer_minor_version_still_needs_every_known_field():
    with pytest.raises(DecodeError, match="message"):
        decode(pack([MAJOR, MINOR + 1, "ack", {"extra": 1}]))


def _status_group(frame):
    return frame[3]["groups"][0]


def _opened_spec(frame):
    return frame[3]["spec"]


def _opened_spec_observation(frame):
    return frame[3]["spec"]["observations"][0]


def _opened_steps(frame):
    return frame[3]["steps"]


# Nested records (GroupStatus, BehaviourSpec, ObservationSpec, the Steps inside Opened) are
# judged by the peer's minor version too, not only the top-level message.
@pytest.mark.parametrize(
    "message, nested",
    [
        (sample_status, _status_group),
        (sample_opened, _opened_spec),
        (sample_opened, _opened_spec_observation),
        (sample_opened, _opened_steps),
    ],
    ids=["status.groups[0]", "opened.spec", "opened.spec.observations[0]", "opened.steps"],
)
def test_newer_minor_version_may_add_fields_to_nested_records(message, nested):
    original = message()
    frame = frame_of(original)
    frame[1] = MINOR + 1
    nested(frame)["added_in_a_later_minor"] = 1
    assert decode(pack(frame)) == original
    # ...while at the current minor the same extra field is refused.
    frame[1] = MINOR
    with pytest.raises(DecodeError, match="added_in_a_later_minor"):
        decode(pack(frame))


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


def test_non_integer_version_is_refused():
    with pytest.raises(DecodeError, match="integer protocol version"):
        decode(pack(["1", 0, "ack", {"message": "m"}]))


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


# --- 4. numpy scalars ------------------------------------------------------------------------


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


# --- 5. key expressions ----------------------------------------------------------------------


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


# --- 6. error hierarchy ----------------------------------------------------------------------


@pytest.mark.parametrize("code, cls", sorted(ERRORS_BY_CODE.items()))
def test_error_from_code_rebuilds_the_class_with_that_code(code, cls):
    error = error_from_code(code, "the server's own words")
    assert type(error) is cls
    assert error.code == code
    assert str(error) == "the server's own words"
    # Through the wire, as the client does with an ErrorReply.
    reply = decode(encode(ErrorReply(code=code, message="m")))
    assert type(error_from_code(reply.code, reply.message)) is cls


def test_error_from_an_unknown_code_is_the_base_class():
    error = error_from_code("added_by_a_newer_peer", "m")
    assert type(error) is ProtocolError and str(error) == "m"


def test_every_error_class_has_its_own_code():
    # Two classes sharing a code would silently drop one from ERRORS_BY_CODE.
    classes = [
        obj
        for obj in vars(errors).values()
        if inspect.isclass(obj) and issubclass(obj, ProtocolError)
    ]
    assert sorted(ERRORS_BY_CODE.values(), key=lambda c: c.__name__) == sorted(
        classes, key=lambda c: c.__name__
    )
    assert all(issubclass(cls, ProtocolError) for cls in ERRORS_BY_CODE.values())


def test_only_fields_added_in_a_later_minor_may_be_missing_from_an_older_peer():
    # ErrorReply.group has a default but was in 1.0 from the start: a 1.0 peer must send it.
    with pytest.raises(DecodeError, match="group"):
        decode(pack([MAJOR, 0, "error", {"code": "x", "message": "m"}]))


@pytest.mark.parametrize("version", [(1, -7), (-1, 0)])
def test_negative_version_numbers_are_refused(version):
    with pytest.raises(DecodeError, match="non-negative"):
        decode(pack([*version, "ack", {"message": "m"}]))


def _one_action(trainer_step: int) -> Actions:
    """One agent's action, sent at ``trainer_step``."""
    return Actions(
        trainer="t",
        ticket=b"k",
        group=0,
        round=3,
        agents=np.zeros(1, np.int32),
        actions=np.ones(1, np.int64),
        trainer_step=trainer_step,
    )


def test_step_counts_sizes_and_headings_of_a_1_1_peer_decode_as_not_given():
    # 1.2 added the trainer's step count to Actions and world frames, and the vehicles' sizes
    # and agents' headings to world frames: a 1.1 peer's messages decode with none...
    actions = _one_action(1234)
    assert decode(encode(actions)).trainer_step == 1234
    *_, body = msgpack.unpackb(encode(actions), raw=False)
    assert body.pop("trainer_step") == 1234
    assert decode(pack([MAJOR, 1, "actions", body])).trainer_step == -1
    frame = _world_frame(
        trainer_step=99,
        half_length_m=np.array([2.25, 2.5, 6.0], np.float32),
        half_width_m=np.array([0.9, 0.9, 1.25], np.float32),
        agent_heading_rad=np.array([0.05], np.float32),
    )
    assert decode(encode(frame)) == frame
    *_, body = msgpack.unpackb(encode(frame), raw=False)
    for name in ("trainer_step", "half_length_m", "half_width_m", "agent_heading_rad"):
        body.pop(name)
    old = decode(pack([MAJOR, 1, "world", body]))
    assert old.trainer_step == -1 and old.half_length_m is None and old.agent_heading_rad is None
    # ...while a peer of this minor version must send them.
    with pytest.raises(DecodeError, match="trainer_step"):
        decode(pack([MAJOR, MINOR, "world", body]))


def test_bad_step_counts_sizes_and_headings_are_refused_saying_what_came():
    with pytest.raises(
        DecodeError, match=r"trainer_step must be >= 0 \(or -1: not given\), got -2"
    ):
        _one_action(-2)
    with pytest.raises(DecodeError, match="half_length_m and half_width_m must come together"):
        _world_frame(half_length_m=np.ones(3, np.float32))
    with pytest.raises(DecodeError, match=r"half_width_m must have shape \(3\), got \(2,\)"):
        _world_frame(half_length_m=np.ones(3, np.float32), half_width_m=np.ones(2, np.float32))
    with pytest.raises(DecodeError, match=r"agent_heading_rad must have shape \(1\), got \(3,\)"):
        _world_frame(agent_heading_rad=np.zeros(3, np.float32))


def test_retired_cars_and_the_server_minor_of_a_1_2_peer_decode_as_none_and_2():
    # 1.3 added Actions.retire (cars leaving the road until their arena resets) and
    # Opened.server_minor: a 1.2 peer's messages decode with no retired cars and minor 2...
    actions = dataclasses.replace(_one_action(7), retire=np.array([4, 2], np.int32))
    assert decode(encode(actions)).retire.tolist() == [4, 2]
    *_, body = msgpack.unpackb(encode(actions), raw=False)
    body.pop("retire")
    assert decode(pack([MAJOR, 2, "actions", body])).retire is None
    opened = dataclasses.replace(sample_opened(), server_minor=MINOR)
    assert decode(encode(opened)).server_minor == MINOR
    *_, opened_body = msgpack.unpackb(encode(opened), raw=False)
    opened_body.pop("server_minor")
    assert decode(pack([MAJOR, 2, "opened", opened_body])).server_minor == 2
    # ...while a peer of this minor version must send them.
    with pytest.raises(DecodeError, match="retire"):
        decode(pack([MAJOR, MINOR, "actions", body]))


@pytest.mark.parametrize(
    ("retire", "expected"),
    [
        (np.array([0], np.int32), r"agents \[0\] both act and retire"),
        (np.array([2, 2], np.int32), r"retire must be distinct, got \[2, 2\]"),
        (np.array([2], np.int64), "retire must be int32, got int64"),
        (np.array([[2]], np.int32), r"retire must have shape \(n\), got \(1, 1\)"),
    ],
)
def test_bad_retire_lists_are_refused_saying_what_came(retire, expected):
    with pytest.raises(DecodeError, match=expected):
        dataclasses.replace(_one_action(7), retire=retire)


def test_an_unsupported_render_mode_is_refused_naming_what_there_is():
    from overtake.envs.registry import check_render_mode

    check_render_mode(None, [])
    check_render_mode("rgb_array", ["rgb_array"])
    with pytest.raises(ValueError, match=r"one of \['rgb_array'\] or None, got 'human'"):
        check_render_mode("human", ["rgb_array"])
    with pytest.raises(ValueError, match="does not render; watch it with a spectator"):
        check_render_mode("rgb_array", [])


def test_a_1_4_peers_spec_decodes_without_the_road_the_car_and_the_observations_facts():
    # 1.5 added the typed facts of the spec: a 1.4 server's Opened decodes without them (the
    # remote environments then refuse it, tests/e2e/test_remote_env.py)...
    opened = sample_opened()
    assert decode(encode(opened)) == opened
    *_, body = msgpack.unpackb(encode(opened), raw=False)
    for name in ("road", "car"):
        body["spec"].pop(name)
    for observation in body["spec"]["observations"]:
        observation.pop("columns"), observation.pop("reach")
    old = decode(pack([MAJOR, 4, "opened", body])).spec
    assert old.road is None and old.car is None
    assert old.observation("lidar").reach is None and old.observation("lidar").columns == ()
    # ...while a peer of this minor version must send them.
    with pytest.raises(DecodeError, match="road"):
        decode(pack([MAJOR, MINOR, "opened", body]))


def test_bad_spec_facts_are_refused_saying_what_came():
    with pytest.raises(DecodeError, match="names 2 columns for a last axis of 4"):
        dataclasses.replace(sample_spec().observations[0], columns=("a", "b"))
    with pytest.raises(DecodeError, match="reach ahead_m must be from 0 to 1e6 m, got -1.0"):
        Reach(ahead_m=-1.0)
    with pytest.raises(DecodeError, match="lane count must be from 1 to 64, got 0"):
        RoadSpec(lane_count=0, lane_width_m=3.5)
    with pytest.raises(DecodeError, match="0 <= min <= max, got 90.0 and 80.0 km/h"):
        CarSpec(length_m=4.5, width_m=1.8, min_speed_kmh=90.0, max_speed_kmh=80.0)
