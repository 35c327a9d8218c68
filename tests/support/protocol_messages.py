"""Protocol messages for the wire protocol's tests (tests/protocol): a Hypothesis strategy for
every message type (:data:`MESSAGES`, :data:`any_message`), small valid sample messages, and
helpers that take a frame apart and put it back together to tamper with it.
"""

from __future__ import annotations

import json
from dataclasses import fields

import msgpack
import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from overtake.protocol import messages
from overtake.protocol.codec import decode, encode
from overtake.protocol.errors import ProtocolError
from overtake.protocol.messages import (
    ACTION_COUNT,
    ACTION_NAMES,
    NAME_PATTERN,
    PROTOCOL_VERSION,
    WIRE_DTYPES,
    Ack,
    Actions,
    BehaviourSpec,
    CarSpec,
    CloseRequest,
    ColumnScale,
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
    Translation,
    WorldFrame,
)
from overtake.protocol.rows import ROW_ARRAYS
from overtake.protocol.shm_messages import ACTION_ARRAY_NAMES, STEPS_ARRAYS
from overtake.protocol.vocabulary import TRANSLATIONS

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
    columns = tuple(
        draw(
            st.one_of(
                st.just([]),
                st.lists(texts, min_size=shape[-1], max_size=shape[-1], unique=True),
            )
        )
    )
    # Some of the named columns scaled, each from a range of its own.
    scaled = draw(st.lists(st.sampled_from(columns), unique=True)) if columns else []
    low = st.floats(min_value=-1e6, max_value=1e6)
    scales = []
    for column in scaled:
        start = draw(low)
        scales.append(ColumnScale(column, start, start + draw(st.floats(1e-3, 1e6))))
    return ObservationSpec(
        name=draw(names),
        shape=shape,
        dtype=dtype,
        low=draw(wire_array(dtype, shape)),
        high=draw(wire_array(dtype, shape)),
        columns=columns,
        reach=draw(st.one_of(st.none(), st.builds(Reach, metres, metres, metres, metres))),
        scales=tuple(scales),
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
    """Steps of k agents, every row array of the contract's schema (:data:`ROW_ARRAYS`) drawn
    in its dtype, each "any length" axis of its own drawn length."""
    k = draw(st.integers(0, 4))
    rows = {
        array.name: draw(
            wire_array(
                array.dtype,
                (k, *(draw(st.integers(0, 3)) if n is None else n for n in array.row_shape)),
            )
        )
        for array in ROW_ARRAYS
    }
    rows["agents"] = rows["agents"][:k]
    return Steps(
        server=draw(names),
        group=draw(ints),
        round=draw(ints),
        observations=draw(observation_dicts(k)),
        **rows,
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
        ego_fields=tuple(draw(st.lists(names, max_size=4, unique=True))),
        translation=draw(
            st.none()
            | st.builds(
                Translation,
                source=st.sampled_from(TRANSLATIONS),
                config_json=st.dictionaries(names, ints, max_size=3).map(json.dumps),
            )
        ),
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
