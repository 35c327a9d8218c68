"""Compiled loops (numba) for the simulation's inner work where numpy pays per call.

Each kernel replaces a run of whole-array numpy calls whose temporaries and per-call overhead
dominated a decision (one arena: dozens of calls on arrays of a few dozen elements; 64 arenas:
several passes over every camera pixel). They do the same float operations in the same order
as the numpy code they replace, so results are bit for bit the same (``tests/test_golden.py``).

Compiled on first use and cached on disk (``cache=True``: next to this file, or under
``NUMBA_CACHE_DIR`` where that is not writable); the first decision of a fresh install pays the
compile (``bench/RESULTS.md`` states the figure), later processes load the cache. With
``NUMBA_DISABLE_JIT=1`` they run as plain Python (slow, for debugging).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lidar_hits(
    count: np.ndarray,
    first: np.ndarray,
    x_lo: np.ndarray,
    x_hi: np.ndarray,
    y_lo: np.ndarray,
    y_hi: np.ndarray,
    ray_dx: np.ndarray,
    ray_dy: np.ndarray,
    dist: np.ndarray,
) -> None:
    """Intersect each (observer, car) box with the rays it covers, keeping the nearest hit.

    ``count``, ``first``, ``x_lo`` ... ``y_hi``: (O, V), the rays ``first .. first+count-1``
    (mod R) a car covers and its box relative to the observer; ``ray_dx``/``ray_dy`` (O, R) the
    rays' world directions; ``dist`` (O, R) float64 is lowered in place to each hit's entry
    distance (0 from inside a box). The slab test of :meth:`.sensors.lidar.Lidar.scan`.
    """
    observers, vehicles = count.shape
    rays = dist.shape[1]
    for o in range(observers):
        for v in range(vehicles):
            n = count[o, v]
            if n == 0:
                continue
            xl, xh, yl, yh = x_lo[o, v], x_hi[o, v], y_lo[o, v], y_hi[o, v]
            for j in range(n):
                ray = (first[o, v] + j) % rays
                # A ray exactly parallel to a slab: a tiny component keeps the test exact
                # enough (the hit moves by far less than a millimetre) without 0/0.
                dx = ray_dx[o, ray]
                dy = ray_dy[o, ray]
                if dx == 0.0:
                    dx = 1e-12
                if dy == 0.0:
                    dy = 1e-12
                tx1, tx2 = xl / dx, xh / dx
                ty1, ty2 = yl / dy, yh / dy
                enter = max(min(tx1, tx2), min(ty1, ty2))
                leave = min(max(tx1, tx2), max(ty1, ty2))
                if leave >= enter and leave >= 0.0:
                    hit = max(enter, 0.0)
                    if hit < dist[o, ray]:
                        dist[o, ray] = hit


@njit(cache=True, nogil=True)
def paint_ground(
    image: np.ndarray,
    first_row: int,
    lanes: np.ndarray,
    line_half: np.ndarray,
    gap: np.ndarray,
    half_road: np.float32,
    shoulder_edge: np.float32,
    line_edge: np.float32,
    inner_edge: np.float32,
    values: np.ndarray,
) -> None:
    """Shade the ground rows of ``image`` (O, H, W) uint8 from ``lanes`` (O, R, W) float32,
    each ground pixel's position across the road in lane widths from the right edge.

    ``values``: the grass, shoulder, road and marking values (grey levels or classes);
    ``line_half`` (R, W) float32: a lane line's half width per pixel; ``gap`` (O, R) bool: rows
    that meet the road between two dashes; the edges: the road's half width, the shoulder's
    edge, the outer lines' outer edge and the inner lines' (all lane widths from the middle).
    """
    grass, shoulder, road, marking = values[0], values[1], values[2], values[3]
    observers, rows, width = lanes.shape
    for o in range(observers):
        for r in range(rows):
            row_gap = gap[o, r]
            out = image[o, first_row + r]
            for c in range(width):
                lane = lanes[o, r, c]
                from_middle = abs(lane - half_road)
                near_line = (
                    abs(lane - np.rint(lane)) <= line_half[r, c] and from_middle <= line_edge
                )
                if near_line and row_gap and from_middle < inner_edge:
                    near_line = False
                if near_line:
                    out[c] = marking
                elif from_middle <= half_road:
                    out[c] = road
                elif from_middle <= shoulder_edge:
                    out[c] = shoulder
                else:
                    out[c] = grass


@njit(cache=True, nogil=True)
def paint_boxes(
    image: np.ndarray,
    shown: np.ndarray,
    row_lo: np.ndarray,
    row_hi: np.ndarray,
    col_lo: np.ndarray,
    col_hi: np.ndarray,
    value: np.uint8,
) -> None:
    """Fill each shown (O, K) car's screen rectangle, inclusive pixel bounds (float, whole
    numbers, possibly off screen), with ``value`` in ``image`` (O, H, W) uint8."""
    observers, cars = shown.shape
    height, width = image.shape[1], image.shape[2]
    for o in range(observers):
        for k in range(cars):
            if not shown[o, k]:
                continue
            r0 = max(row_lo[o, k], 0.0)
            r1 = min(row_hi[o, k], height - 1.0)
            c0 = max(col_lo[o, k], 0.0)
            c1 = min(col_hi[o, k], width - 1.0)
            if r0 > r1 or c0 > c1:
                continue
            for r in range(int(r0), int(r1) + 1):
                for c in range(int(c0), int(c1) + 1):
                    image[o, r, c] = value
