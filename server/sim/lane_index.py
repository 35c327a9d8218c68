"""Who is where on the lanes: every arena's vehicles sorted by (arena, lane, position).

The index answers the two questions car-following and lane changes ask, over every arena and
vehicle at once: the vehicle next ahead of each one in its lane (:func:`leaders`), and the
vehicles just ahead and behind any position of any lane (a binary search of the sorted keys, in
MOBIL's compiled loop: :func:`.traffic.kernels.mobil_decide`). Neighbours are found by sorting
one key per (arena, lane, position) entry: a vehicle that is changing lanes has an entry in
both lanes, so the cars in either lane react to it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Keys are group * KEY_SPAN + (x relative to the arena's first agent) + KEY_OFFSET, so that one
# sort orders entries by arena, then lane, then position. Positions stay within +-KEY_OFFSET of
# the reference agent because traffic is recycled far closer than that.
KEY_SPAN = 1.0e6
KEY_OFFSET = 5.0e5
NO_GAP_M = 1.0e9  # gap reported when there is no vehicle ahead


@dataclass(frozen=True, slots=True)
class LaneIndex:
    """Entries of all arenas sorted by (arena, lane, position); built once per decision."""

    sorted_keys: np.ndarray  # (E,) float64
    sorted_group: np.ndarray  # (E,) float64: arena * (lanes + 1) + lane; lane == lanes is unused
    sorted_vehicle: np.ndarray  # (E,) int64: flat index (arena * V + column) of the entry's vehicle
    entry_position: np.ndarray  # (A, 2V) int64: where each entry landed in the sorted order
    lanes_plus_one: int


class LaneSorter:
    """Builds :class:`LaneIndex` objects, keeping the per-shape constants between frames."""

    def __init__(self, lane_count: int) -> None:
        self.lane_count = lane_count
        self._constants: dict[tuple[int, int], tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def _for_shape(self, arenas: int, vehicles: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (arenas, vehicles)
        if key not in self._constants:
            entries = arenas * 2 * vehicles
            flat_entry = np.arange(entries)
            vehicle_of_entry = (
                flat_entry // (2 * vehicles) * vehicles + flat_entry % (2 * vehicles) % vehicles
            )
            group_base = (np.arange(arenas, dtype=np.float64) * (self.lane_count + 1))[:, None]
            self._constants[key] = (flat_entry, vehicle_of_entry, group_base)
        return self._constants[key]

    def build(
        self, x_rel: np.ndarray, lane: np.ndarray, target_lane: np.ndarray, active: np.ndarray
    ) -> LaneIndex:
        """Sort the entries: each vehicle's lane and, while it changes lanes, its target lane."""
        arenas, vehicles = x_rel.shape
        flat_entry, vehicle_of_entry, group_base = self._for_shape(arenas, vehicles)
        unused = self.lane_count
        group = np.empty((arenas, 2 * vehicles))
        np.copyto(group[:, :vehicles], np.where(active, lane, unused))
        np.copyto(
            group[:, vehicles:], np.where(active & (target_lane != lane), target_lane, unused)
        )
        group += group_base
        keys = group * KEY_SPAN
        shifted = x_rel + KEY_OFFSET
        keys[:, :vehicles] += shifted
        keys[:, vehicles:] += shifted
        flat_keys = keys.reshape(-1)
        order = np.argsort(flat_keys, kind="stable")
        position = np.empty_like(order)
        position[order] = flat_entry
        return LaneIndex(
            sorted_keys=flat_keys[order],
            sorted_group=group.reshape(-1)[order],
            sorted_vehicle=vehicle_of_entry[order],
            entry_position=position.reshape(arenas, 2 * vehicles),
            lanes_plus_one=self.lane_count + 1,
        )


def leaders(index: LaneIndex) -> tuple[np.ndarray, np.ndarray]:
    """For each entry (A, 2V): the flat index of the vehicle next ahead in its lane.

    Returns (leader, valid); where not valid (no leader, or an entry in the unused lane) the
    leader is some other vehicle's index: safe to index with, its values must be masked.
    """
    group = index.sorted_group
    lanes_plus_one = index.lanes_plus_one
    has_next = np.zeros(group.size, dtype=bool)
    np.equal(group[1:], group[:-1], out=has_next[:-1])
    has_next &= (group % lanes_plus_one) != lanes_plus_one - 1
    next_vehicle = np.empty_like(index.sorted_vehicle)
    next_vehicle[:-1] = index.sorted_vehicle[1:]
    next_vehicle[-1:] = index.sorted_vehicle[:1]
    pos = index.entry_position
    return next_vehicle[pos], has_next[pos]
