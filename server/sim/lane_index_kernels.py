"""The lane index's compiled loops (numba): the sort of every arena's (arena, lane, position)
entries and each entry's leader, in the same float operations as the numpy they replaced (the
sort is stable, so the order is the same too; the golden digests were not recorded again).
Compiled and cached as :mod:`.kernels` says.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def sort_entries(
    x_rel: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    active: np.ndarray,
    lane_count: int,
    key_span: float,
    key_offset: float,
    sorted_keys: np.ndarray,
    sorted_group: np.ndarray,
    sorted_vehicle: np.ndarray,
    entry_position: np.ndarray,
) -> None:
    """Fill a :class:`.lane_index.LaneIndex`'s arrays from the (A, V) state: each vehicle's
    entry in its lane (columns 0..V-1 of ``entry_position`` (A, 2V)) and, while it changes
    lanes, in its target lane (V..2V-1); an inactive vehicle's entries and an entry of no
    lane change sit in the unused lane ``lane_count``. Keys are
    ``(arena * (lane_count + 1) + lane) * key_span + (x_rel + key_offset)``."""
    arenas, vehicles = x_rel.shape
    width = 2 * vehicles
    keys = np.empty(arenas * width)
    group = np.empty(arenas * width)
    for a in range(arenas):
        base = float(a) * (lane_count + 1)
        for v in range(vehicles):
            shifted = x_rel[a, v] + key_offset
            own = lane[a, v] if active[a, v] else lane_count
            changing = active[a, v] and target_lane[a, v] != lane[a, v]
            other = target_lane[a, v] if changing else lane_count
            e = a * width + v
            group[e] = float(own) + base
            keys[e] = group[e] * key_span + shifted
            group[e + vehicles] = float(other) + base
            keys[e + vehicles] = group[e + vehicles] * key_span + shifted
    order = np.argsort(keys, kind="mergesort")
    for i in range(order.size):
        e = order[i]
        a, column = e // width, e % width
        sorted_keys[i] = keys[e]
        sorted_group[i] = group[e]
        sorted_vehicle[i] = a * vehicles + column % vehicles
        entry_position[a, column] = i


@njit(cache=True, nogil=True)
def entry_leaders(
    sorted_group: np.ndarray,
    sorted_vehicle: np.ndarray,
    entry_position: np.ndarray,
    lanes_plus_one: int,
    lead: np.ndarray,
    valid: np.ndarray,
) -> None:
    """Each entry's (A, 2V) leader: the flat index of the vehicle next in the sorted order,
    valid where it is in the same lane (not the unused one); where not valid it is some other
    vehicle's index (the first entry's after the last)."""
    size = sorted_group.size
    arenas, width = entry_position.shape
    for a in range(arenas):
        for column in range(width):
            i = entry_position[a, column]
            following = i + 1 if i + 1 < size else 0
            lead[a, column] = sorted_vehicle[following]
            valid[a, column] = (
                i + 1 < size
                and sorted_group[i + 1] == sorted_group[i]
                and sorted_group[i] % lanes_plus_one != lanes_plus_one - 1
            )
