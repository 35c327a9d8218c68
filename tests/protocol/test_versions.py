"""Protocol versions: another major version is refused naming both; a newer minor may add fields
and an older one may leave out what later minors added (1.1's reward terms, 1.2's step counts,
sizes and headings, 1.3's retired cars, 1.5's spec facts), each with its own checks.
"""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from overtake.protocol.codec import decode, encode, version_text
from overtake.protocol.errors import DecodeError, VersionMismatch
from overtake.protocol.messages import Ack, Actions, CarSpec, Reach, RoadSpec, WorldFrame

from tests.support.protocol_messages import (
    MAJOR,
    MINOR,
    frame_of,
    pack,
    sample_actions,
    sample_opened,
    sample_spec,
    sample_status,
)

# --- the major version ---------------------------------------------------------------------


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


def test_non_integer_version_is_refused():
    with pytest.raises(DecodeError, match="integer protocol version"):
        decode(pack(["1", 0, "ack", {"message": "m"}]))


@pytest.mark.parametrize("version", [(1, -7), (-1, 0)])
def test_negative_version_numbers_are_refused(version):
    with pytest.raises(DecodeError, match="non-negative"):
        decode(pack([*version, "ack", {"message": "m"}]))


# --- minor versions: what a newer peer may add, what an older one may leave out -------------


def test_newer_minor_version_may_add_fields_the_current_minor_may_not():
    body = {"message": "hello", "added_in_a_later_minor": [1, 2]}
    assert decode(pack([MAJOR, MINOR + 1, "ack", body])) == Ack(message="hello")
    with pytest.raises(DecodeError) as err:
        decode(pack([MAJOR, MINOR, "ack", body]))
    assert "added_in_a_later_minor" in str(err.value)  # what came
    assert "'message'" in str(err.value)  # what was expected


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


def test_only_fields_added_in_a_later_minor_may_be_missing_from_an_older_peer():
    # ErrorReply.group has a default but was in 1.0 from the start: a 1.0 peer must send it.
    with pytest.raises(DecodeError, match="group"):
        decode(pack([MAJOR, 0, "error", {"code": "x", "message": "m"}]))


# --- what each minor version added, and the checks on it --------------------------------------


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
