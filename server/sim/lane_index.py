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

from .lane_index_kernels import entry_leaders, sort_entries

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
    """Builds :class:`LaneIndex` objects (one compiled loop, :mod:`.lane_index_kernels`)."""

    def __init__(self, lane_count: int) -> None:
        self.lane_count = lane_count

    def build(
        self, x_rel: np.ndarray, lane: np.ndarray, target_lane: np.ndarray, active: np.ndarray
    ) -> LaneIndex:
        """Sort the entries: each vehicle's lane and, while it changes lanes, its target lane."""
        arenas, vehicles = x_rel.shape
        entries = arenas * 2 * vehicles
        index = LaneIndex(
            sorted_keys=np.empty(entries),
            sorted_group=np.empty(entries),
            sorted_vehicle=np.empty(entries, dtype=np.int64),
            entry_position=np.empty((arenas, 2 * vehicles), dtype=np.int64),
            lanes_plus_one=self.lane_count + 1,
        )
        sort_entries(
            x_rel, lane, target_lane, active, self.lane_count, KEY_SPAN, KEY_OFFSET,
            index.sorted_keys, index.sorted_group, index.sorted_vehicle, index.entry_position,
        )  # fmt: skip
        return index


def leaders(index: LaneIndex) -> tuple[np.ndarray, np.ndarray]:
    """For each entry (A, 2V): the flat index of the vehicle next ahead in its lane.

    Returns (leader, valid); where not valid (no leader, or an entry in the unused lane) the
    leader is some other vehicle's index: safe to index with, its values must be masked.
    """
    lead = np.empty(index.entry_position.shape, dtype=np.int64)
    valid = np.empty(index.entry_position.shape, dtype=bool)
    entry_leaders(
        index.sorted_group, index.sorted_vehicle, index.entry_position, index.lanes_plus_one,
        lead, valid,
    )  # fmt: skip
    return lead, valid
