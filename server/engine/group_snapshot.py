"""A group's rounds as they stand, to put back later: the simulator's snapshot and what each
agent slot carries from one round to the next.

Between rounds a group's :class:`~.rounds.Rounds` holds, beside its simulator, whose episodes
ended last round (they restart next round: Gymnasium's next-step autoreset), which cars were
retired, and what each slot got last round (reward, applied action, reward terms: what world
frames show). :class:`GroupSnapshot` keeps all of it, so that rounds restored from one play on
exactly as the rounds it was taken from would have (a server's group or an in-process engine).
Membership (who owns which slot, their tickets) and the round counter are not in it: they
belong to the connections of now, not to the road.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..sim.snapshot import SimSnapshot, SnapshotMismatch, spliced
from .rounds import SLOT_ARRAYS

if TYPE_CHECKING:
    from .rounds import Rounds


@dataclass(frozen=True)
class GroupSnapshot:
    """A group's simulator and its per-slot round state (:data:`SLOT_ARRAYS`)."""

    sim: SimSnapshot
    slots: Mapping[str, np.ndarray]

    @classmethod
    def of(cls, rounds: Rounds) -> GroupSnapshot:
        return cls(
            sim=rounds.sim.snapshot(),
            slots={name: getattr(rounds, name).copy() for name in SLOT_ARRAYS},
        )

    def restore_into(self, rounds: Rounds) -> None:
        """Put the road and its rounds back as they were (checked first: a snapshot of
        another configuration or size changes nothing and raises
        :class:`~.sim.snapshot.SnapshotMismatch`)."""
        for name in SLOT_ARRAYS:
            want, have = getattr(rounds, name), self.slots.get(name)
            if have is None or have.shape != want.shape or have.dtype != want.dtype:
                found = "nothing" if have is None else f"{have.dtype}{have.shape}"
                raise SnapshotMismatch(
                    f"the snapshot's {name} is {found}, the group needs {want.dtype}{want.shape}"
                )
        rounds.sim.restore(self.sim)
        for name in SLOT_ARRAYS:
            getattr(rounds, name)[...] = self.slots[name]
        # Spectators are shown the restored road, observed afresh.
        rounds.last_observations = None

    def arenas(self, first: int, count: int) -> GroupSnapshot:
        """Arenas ``first`` .. ``first + count - 1`` alone: what the rounds of ``count`` arenas
        of the same configuration would keep of them (the slot arrays are (A, N), arenas first,
        as every simulator array is)."""
        return GroupSnapshot(
            sim=self.sim.arenas(first, count),
            slots={name: value[first : first + count].copy() for name, value in self.slots.items()},
        )

    def with_arenas(self, first: int, part: GroupSnapshot) -> GroupSnapshot:
        """This snapshot with arenas ``first`` .. taken from ``part`` (:meth:`arenas` of a
        snapshot like this one, or a smaller engine's whole snapshot); checked first."""
        sim = self.sim.with_arenas(first, part.sim)
        slots = spliced(self.slots, first, part.slots, len(part.sim.rng_states), "group")
        return GroupSnapshot(sim=sim, slots=slots)

    def to_bytes(self) -> bytes:
        """The snapshot as one ``.npz`` archive (arrays, and the generators' states and the
        configuration as JSON text): what a remote trainer keeps (GroupState) and hands back."""
        sim = self.sim.to_plain()
        meta = {"config_json": sim["config_json"], "rng_states_json": sim["rng_states_json"]}
        arrays = {f"sim.{name}": value for name, value in sim["arrays"].items()}
        arrays.update({f"slot.{name}": value for name, value in self.slots.items()})
        arrays["needs_reset"] = sim["needs_reset"]
        arrays["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
        out = io.BytesIO()
        np.savez(out, **arrays)
        return out.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> GroupSnapshot:
        """Read :meth:`to_bytes`' archive (no pickles); anything else raises
        :class:`~.sim.snapshot.SnapshotMismatch`."""
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as archive:
                arrays = {name: archive[name] for name in archive.files}
            meta = json.loads(arrays.pop("meta").tobytes().decode())
            plain = {
                "sim": {
                    "config_json": meta["config_json"],
                    "rng_states_json": meta["rng_states_json"],
                    "needs_reset": arrays.pop("needs_reset"),
                    "arrays": {
                        k.removeprefix("sim."): v for k, v in arrays.items() if k.startswith("sim.")
                    },
                },
                "slots": {
                    k.removeprefix("slot."): v for k, v in arrays.items() if k.startswith("slot.")
                },
            }
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as error:
            raise SnapshotMismatch(f"not a group snapshot ({error!r})") from None
        return cls.from_plain(plain)

    def to_plain(self) -> dict[str, Any]:
        return {"sim": self.sim.to_plain(), "slots": dict(self.slots)}

    @classmethod
    def from_plain(cls, plain: Mapping[str, Any]) -> GroupSnapshot:
        try:
            sim, slots = plain["sim"], plain["slots"]
            return cls(
                sim=SimSnapshot.from_plain(sim),
                slots={name: np.asarray(slots[name]) for name in SLOT_ARRAYS},
            )
        except (KeyError, TypeError) as error:
            raise SnapshotMismatch(f"not a group snapshot ({error!r})") from None
