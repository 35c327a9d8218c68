"""A round's rows named once (protocol/rows.py): the schema, the Steps message, the
shared-memory layout's names and the operations on rows all follow :data:`ROW_ARRAYS`, so a
per-step field added there (and where the round makes it, server/engine/rounds.py) reaches every
carrier; a carrier that spelled the row on its own would miss it and fail here."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from overtake.protocol.codec import decode, encode
from overtake.protocol.errors import DecodeError
from overtake.protocol.messages import Steps
from overtake.protocol.records import WIRE_DTYPES
from overtake.protocol.rows import (
    ROW_ARRAY_NAMES,
    ROW_ARRAYS,
    Rows,
    joined,
    row_values,
)
from overtake.protocol.shm_messages import STEPS_ARRAYS
from overtake.server.engine.rounds import RoundRows


def _rows(k: int, start: int = 0, **carrier) -> dict:
    """Every row field of k agents, each array's values distinct from the others'."""
    rng = np.random.default_rng(start)
    values: dict = {}
    for index, array in enumerate(ROW_ARRAYS):
        shape = (k, *(3 + index if n is None else n for n in array.row_shape))
        values[array.name] = rng.integers(0, 100, shape).astype(WIRE_DTYPES[array.dtype])
    values["agents"] = np.arange(start, start + k, dtype=np.int32)
    values["observations"] = {"lidar": rng.random((k, 4)).astype(np.float32)}
    return {**values, **carrier}


def _same(a: Rows, b: Rows) -> None:
    for name in ROW_ARRAY_NAMES:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        assert getattr(a, name).dtype == getattr(b, name).dtype, name
    assert a.observations.keys() == b.observations.keys()
    for name in a.observations:
        np.testing.assert_array_equal(a.observations[name], b.observations[name])


def test_the_schema_is_the_rows_fields_and_every_carrier_takes_it_whole() -> None:
    array_fields = [f.name for f in dataclasses.fields(Rows) if f.name != "observations"]
    assert tuple(array_fields) == ROW_ARRAY_NAMES
    steps_fields = {f.name for f in dataclasses.fields(Steps)}
    assert steps_fields == {f.name for f in dataclasses.fields(Rows)} | {"server", "group", "round"}
    assert STEPS_ARRAYS == ROW_ARRAY_NAMES  # the shared-memory layout's names
    assert RoundRows is Rows  # the in-process engine's rows


def test_rows_go_through_the_codec_the_layout_names_a_take_and_a_join_whole() -> None:
    steps = Steps(server="s", group=1, round=7, **_rows(5))
    _same(decode(encode(steps)), steps)  # type: ignore[arg-type]
    _same(Steps(server="s", group=1, round=7, **row_values(steps.arrays())), steps)
    picked = np.array([4, 1])
    taken = Rows(**steps.taken(picked))
    for name in ROW_ARRAY_NAMES:
        np.testing.assert_array_equal(getattr(taken, name), getattr(steps, name)[picked])
    assert taken.taken(None)["reward"] is taken.reward  # every row: the arrays themselves
    other = Steps(server="t", group=2, round=9, **_rows(3, start=5))
    both = joined([steps, other])
    assert isinstance(both, Steps) and (both.server, both.round) == ("s", 7)
    for name in ROW_ARRAY_NAMES:
        assert len(getattr(both, name)) == 8
        np.testing.assert_array_equal(getattr(both, name)[5:], getattr(other, name))


@pytest.mark.parametrize("array", ROW_ARRAYS, ids=lambda a: a.name)
def test_every_row_array_is_checked_for_its_dtype_and_its_rows(array) -> None:
    wrong_dtype = "float32" if array.dtype != "float32" else "int64"
    bad = _rows(4)
    bad[array.name] = bad[array.name].astype(WIRE_DTYPES[wrong_dtype])
    if array.name != "agents":
        with pytest.raises(DecodeError, match=f"{array.name} must be {array.dtype}"):
            Steps(server="s", group=1, round=0, **bad)
        short = _rows(4)
        short[array.name] = short[array.name][:3]
        with pytest.raises(DecodeError, match=f"{array.name} must have shape"):
            Steps(server="s", group=1, round=0, **short)
    else:
        with pytest.raises(DecodeError, match="agents must be int32"):
            Steps(server="s", group=1, round=0, **bad)
