"""A round's rows: what one step (or reset) gives each agent, named once for every carrier.

A round gives each agent a row: its observations and :data:`ROW_ARRAYS`. Three carry rows,
and all three are :class:`Rows`: the :class:`~.messages.Steps` a server sends a trainer (a
:class:`Rows` with the server, group and round it answers), the shared-memory layout a round is
written in (:mod:`.shm_messages`: an array per name here, and ``obs/<observation>``), and the
in-process engine's rows of a round (``overtake.server.engine.rounds``: the :class:`Rows`
themselves, no message). What takes or maps rows is here too: :meth:`Rows.taken` (some agents'
rows), :func:`joined` (several engines' rows, one vector environment's), :meth:`Rows.arrays` and
:func:`row_values` (to and from a layout's named arrays), :meth:`Rows.check_rows`.

A per-step field is added here (its :class:`RowArray` and its field on :class:`Rows`) and where
the simulator makes it (``server/engine/rounds.py``); the message, the layout and the faces' rows
follow (a new wire field also takes its protocol minor version, ``since`` in its metadata).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np

from .errors import DecodeError
from .records import check_array, check_name
from .vocabulary import ACTION_COUNT


@dataclass(frozen=True)
class RowArray:
    """One array of a round's rows: its name (a :class:`Rows` field), wire dtype and the
    shape of one agent's row (None: any length, the same for every row)."""

    name: str
    dtype: str
    row_shape: tuple[int | None, ...] = ()


# Every array a round gives each agent, besides its observations; in the order Steps lists them.
ROW_ARRAYS: tuple[RowArray, ...] = (
    RowArray("agents", "int32"),  # ids within the group: arena index x agents per arena + slot
    RowArray("reward", "float64"),
    RowArray("terminated", "bool"),
    RowArray("truncated", "bool"),
    RowArray("action_applied", "int64"),  # -1 where nothing was applied (a reset)
    RowArray("late", "bool"),  # no action came: keep was applied
    RowArray("action_mask", "int8", (ACTION_COUNT,)),  # 1 = the action can be taken now
    RowArray("reward_terms", "float64", (None,)),  # each reward term, the spec's order
    RowArray("metrics", "float64", (None,)),  # each episode so far, the spec's metric fields
)
ROW_ARRAY_NAMES: tuple[str, ...] = tuple(a.name for a in ROW_ARRAYS)
OBSERVATION_PREFIX = "obs/"
"""A layout names an observation's array ``obs/<observation name>``."""

R = TypeVar("R", bound="Rows")


@dataclass(frozen=True, eq=False, kw_only=True)
class Rows:
    """What a round gave some agents, one row each (the first axis of every array). Keyword
    only, so that a field added later with a default (for peers of an older minor version)
    can sit before a carrier's own fields."""

    agents: np.ndarray  # int32 (k,): ids within the group
    observations: dict[str, np.ndarray]  # name -> (k, ...)
    reward: np.ndarray  # float64 (k,)
    terminated: np.ndarray  # bool (k,)
    truncated: np.ndarray  # bool (k,)
    action_applied: np.ndarray  # int64 (k,), -1 where nothing was applied (reset)
    late: np.ndarray  # bool (k,): no action came in time, keep was applied
    action_mask: np.ndarray  # int8 (k, ACTION_COUNT)
    reward_terms: np.ndarray  # float64 (k, terms)
    metrics: np.ndarray  # float64 (k, metric fields): each episode so far

    @property
    def ended(self) -> np.ndarray:
        """(k,) bool: whose episode ended in this round."""
        return self.terminated | self.truncated

    def check_rows(self) -> None:
        """Every array of :data:`ROW_ARRAYS` in its dtype with a row per agent, and every
        observation with a row per agent; raises :class:`~.errors.DecodeError` saying which
        is not."""
        check_array("agents", self.agents, "int32", (None,))
        k = self.agents.shape[0]
        for name, value in self.observations.items():
            check_name("observation name", name)
            if value.ndim < 1 or value.shape[0] != k:
                raise DecodeError(
                    f"observation {name!r} must have {k} rows (one per agent), "
                    f"got shape {value.shape}"
                )
        for array in ROW_ARRAYS[1:]:
            check_array(array.name, getattr(self, array.name), array.dtype, (k, *array.row_shape))

    def row_values(self) -> dict[str, Any]:
        """The rows' fields by name (observations included), as :class:`Rows` takes them."""
        values: dict[str, Any] = {name: getattr(self, name) for name in ROW_ARRAY_NAMES}
        values["observations"] = self.observations
        return values

    def taken(self, index: np.ndarray | slice | None) -> dict[str, Any]:
        """The fields of the rows ``index`` picks (None: every row, the arrays themselves), by
        name, as :class:`Rows` (or a :class:`~.messages.Steps`) takes them; the ``agents`` a
        copy, the others views or copies as numpy's indexing gives them."""
        if index is None:
            return self.row_values()
        values: dict[str, Any] = {name: getattr(self, name)[index] for name in ROW_ARRAY_NAMES}
        values["observations"] = {name: v[index] for name, v in self.observations.items()}
        return values

    def arrays(self) -> dict[str, np.ndarray]:
        """Every array by the name a layout gives it: :data:`ROW_ARRAY_NAMES` and
        ``obs/<observation>``."""
        arrays = {name: getattr(self, name) for name in ROW_ARRAY_NAMES}
        arrays.update({OBSERVATION_PREFIX + k: v for k, v in self.observations.items()})
        return arrays


def row_values(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    """:class:`Rows`' fields from a layout's named arrays (:meth:`Rows.arrays` undone)."""
    values: dict[str, Any] = {name: arrays[name] for name in ROW_ARRAY_NAMES}
    values["observations"] = {
        name.removeprefix(OBSERVATION_PREFIX): value
        for name, value in arrays.items()
        if name.startswith(OBSERVATION_PREFIX)
    }
    return values


def joined(parts: Sequence[R]) -> R:
    """One set of rows of several engines' rows, in the order given, of the first part's type
    (a Steps' server, group and round are the first part's: the rows are what a vector
    environment reads)."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]
    values: dict[str, Any] = {
        name: np.concatenate([getattr(p, name) for p in parts]) for name in ROW_ARRAY_NAMES
    }
    values["observations"] = {
        name: np.concatenate([p.observations[name] for p in parts]) for name in first.observations
    }
    return dataclasses.replace(first, **values)
