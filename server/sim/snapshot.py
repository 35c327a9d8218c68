"""A simulator's whole state at one moment, to put back later: what an exact resume needs.

A :class:`SimSnapshot` is every array of the structure-of-arrays state, each arena's random
generator and which arenas wait for a reset, together with the configuration they belong to.
Restored into a simulator of the same configuration and size, the arenas go on bit for bit as
if they had never been interrupted: the same seed and actions give the same episode whether or
not a snapshot and a restore came between (a training run's checkpoint holds one, so that a
stopped run resumes exactly; ``tests/server/sim/test_snapshot.py`` checks it for every preset).

It converts to plain data (:meth:`SimSnapshot.to_plain`: arrays, strings and numbers) and back,
so whoever stores it picks the format.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .settings_history import snapshot_differences
from .state import ADDED_FIELDS, SimState


class SnapshotMismatch(ValueError):
    """A snapshot that does not fit the simulator it is restored into (another configuration,
    other counts of arenas or agents, or a damaged snapshot); the message says what differs."""


def spliced(
    whole: Mapping[str, np.ndarray],
    first: int,
    part: Mapping[str, np.ndarray],
    count: int,
    holder: str,
) -> dict[str, np.ndarray]:
    """Copies of ``whole``'s arrays (arenas first) with arenas ``first`` .. ``first + count - 1``
    from ``part``'s arrays of the same names; every one checked before anything is copied
    (``holder``: what needs them, for the message)."""
    for name, value in whole.items():
        have, need = part.get(name), (count, *value.shape[1:])
        if have is None or have.shape != need or have.dtype != value.dtype:
            found = "nothing" if have is None else f"{have.dtype}{have.shape}"
            raise SnapshotMismatch(
                f"the part's {name} is {found}, {count} arena(s) of this {holder} need "
                f"{value.dtype}{need}"
            )
    merged = {name: value.copy() for name, value in whole.items()}
    for name, value in merged.items():
        value[first : first + count] = part[name]
    return merged


@dataclass(frozen=True)
class SimSnapshot:
    """One simulator's state: ``arrays`` (every :class:`SimState` field, by name),
    ``rng_states`` (each arena's generator, as ``bit_generator.state``), ``needs_reset`` (A,)
    and the configuration as JSON (what it may be restored into)."""

    config_json: str
    arrays: Mapping[str, np.ndarray]
    rng_states: tuple[dict[str, Any], ...]
    needs_reset: np.ndarray

    @classmethod
    def take(
        cls,
        config_json: str,
        state: SimState,
        rngs: list[np.random.Generator],
        needs_reset: np.ndarray,
    ) -> SimSnapshot:
        """Copies of everything, so that the simulator may go on stepping."""
        return cls(
            config_json=config_json,
            arrays={f.name: getattr(state, f.name).copy() for f in dataclasses.fields(state)},
            rng_states=tuple(dict(rng.bit_generator.state) for rng in rngs),
            needs_reset=needs_reset.copy(),
        )

    def put_back(
        self,
        config_json: str,
        state: SimState,
        rngs: list[np.random.Generator],
        needs_reset: np.ndarray,
    ) -> None:
        """Write the snapshot into a simulator's ``state``, ``rngs`` and ``needs_reset``
        (checked first: nothing is written unless all of it fits)."""
        differing = (
            snapshot_differences(json.loads(self.config_json), json.loads(config_json))
            if config_json != self.config_json
            else []
        )
        if differing:
            said = differing[0].replace("the record", "the snapshot").replace(" now", " here")
            raise SnapshotMismatch(f"the snapshot is of another simulator configuration: {said}")
        if len(self.rng_states) != len(rngs):
            raise SnapshotMismatch(
                f"the snapshot holds {len(self.rng_states)} arena(s), the simulator {len(rngs)}"
            )
        # A field added to the state since the snapshot was taken: its simulator used none
        # (its configuration, checked above, has none of what uses it), so it starts as a new
        # state's.
        added_since = {
            field.name
            for field in dataclasses.fields(state)
            if field.name not in self.arrays and field.name in ADDED_FIELDS
        }
        for field in dataclasses.fields(state):
            want = getattr(state, field.name)
            have = self.arrays.get(field.name)
            if field.name in added_since:
                continue
            if have is None:
                raise SnapshotMismatch(f"the snapshot has no {field.name!r}")
            if have.shape != want.shape or have.dtype != want.dtype:
                raise SnapshotMismatch(
                    f"the snapshot's {field.name} is {have.dtype}{have.shape}, the simulator "
                    f"needs {want.dtype}{want.shape} (other counts of arenas, agents or cars)"
                )
        if self.needs_reset.shape != needs_reset.shape:
            raise SnapshotMismatch(
                f"the snapshot's needs_reset is {self.needs_reset.shape}, the simulator needs "
                f"{needs_reset.shape}"
            )
        for rng, saved in zip(rngs, self.rng_states, strict=True):
            # Tried on a fresh generator first: a damaged state is refused before anything
            # is written.
            try:
                type(rng.bit_generator)().state = dict(saved)
            except (TypeError, ValueError, KeyError) as error:
                raise SnapshotMismatch(
                    f"the snapshot's generator state is not one ({error})"
                ) from None
        for field in dataclasses.fields(state):
            if field.name in added_since:
                getattr(state, field.name)[...] = 0
            else:
                getattr(state, field.name)[...] = self.arrays[field.name]
        for rng, saved in zip(rngs, self.rng_states, strict=True):
            rng.bit_generator.state = dict(saved)
        needs_reset[...] = self.needs_reset

    def arenas(self, first: int, count: int) -> SimSnapshot:
        """Arenas ``first`` .. ``first + count - 1`` alone: the snapshot a simulator of
        ``count`` arenas of the same configuration would take of them (each arena's state and
        generator are its own: no array mixes arenas)."""
        self._check_range(first, count)
        rows = slice(first, first + count)
        return SimSnapshot(
            config_json=self.config_json,
            arrays={name: value[rows].copy() for name, value in self.arrays.items()},
            rng_states=self.rng_states[rows],
            needs_reset=self.needs_reset[rows].copy(),
        )

    def with_arenas(self, first: int, part: SimSnapshot) -> SimSnapshot:
        """This snapshot with arenas ``first`` .. taken from ``part`` (a snapshot of fewer
        arenas of the same configuration, as :meth:`arenas` gives one); checked first."""
        count = len(part.rng_states)
        self._check_range(first, count)
        differing = (
            snapshot_differences(json.loads(part.config_json), json.loads(self.config_json))
            if part.config_json != self.config_json
            else []
        )
        if differing:
            said = differing[0].replace("the record", "the part").replace(" now", " here")
            raise SnapshotMismatch(f"the part is of another simulator configuration: {said}")
        added = {
            # Added to the state since the part was taken: its simulator used none (as
            # put_back reads it), so its arenas hold a new state's zeros.
            name: np.zeros((count, *value.shape[1:]), dtype=value.dtype)
            for name, value in self.arrays.items()
            if name in ADDED_FIELDS and name not in part.arrays
        }
        arrays = spliced(self.arrays, first, {**part.arrays, **added}, count, "simulator")
        rows = slice(first, first + count)
        needs_reset = self.needs_reset.copy()
        needs_reset[rows] = part.needs_reset
        states = list(self.rng_states)
        states[rows] = part.rng_states
        return SimSnapshot(self.config_json, arrays, tuple(states), needs_reset)

    def _check_range(self, first: int, count: int) -> None:
        total = len(self.rng_states)
        if count < 1 or first < 0 or first + count > total:
            raise SnapshotMismatch(
                f"arenas {first}..{first + count - 1} asked of a snapshot of arenas 0..{total - 1}"
            )

    def to_plain(self) -> dict[str, Any]:
        """Plain data: arrays by name, the generators' states as JSON (their integers exceed
        64 bits), the configuration's JSON."""
        return {
            "config_json": self.config_json,
            "arrays": dict(self.arrays),
            "rng_states_json": json.dumps(list(self.rng_states)),
            "needs_reset": self.needs_reset,
        }

    @classmethod
    def from_plain(cls, plain: Mapping[str, Any]) -> SimSnapshot:
        try:
            return cls(
                config_json=str(plain["config_json"]),
                arrays={k: np.asarray(v) for k, v in plain["arrays"].items()},
                rng_states=tuple(json.loads(plain["rng_states_json"])),
                needs_reset=np.asarray(plain["needs_reset"], dtype=bool),
            )
        except (KeyError, TypeError, AttributeError, ValueError) as error:
            raise SnapshotMismatch(f"not a simulator snapshot ({error!r})") from None
