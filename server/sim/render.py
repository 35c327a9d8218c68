"""Top-down RGB view of one arena for people (``render_mode="rgb_array"``), drawn in numpy."""

from __future__ import annotations

import numpy as np

from overtake.protocol.vocabulary import AGENT_COLOUR, AGENT_KIND, BEHAVIOUR_COLOURS

from .core import HighwaySim

PIXELS_PER_M = 4.0
VIEW_BEHIND_M = 40.0
VIEW_AHEAD_M = 120.0
MARGIN_M = 4.0

_GRASS = np.array([70, 120, 60], dtype=np.uint8)
_ROAD = np.array([90, 90, 95], dtype=np.uint8)
_MARK = np.array([240, 240, 240], dtype=np.uint8)
_RAIL = np.array([180, 180, 170], dtype=np.uint8)
# Traffic by behaviour and the watched agent as every view draws them (the vocabulary's
# colours); the other agents on a shared road yellow.
_KIND_COLOURS = np.array([*BEHAVIOUR_COLOURS, (250, 250, 60), AGENT_COLOUR], dtype=np.uint8)
_OTHER_AGENT = AGENT_KIND
_WATCHED_AGENT = AGENT_KIND + 1


def render_top_down(
    sim: HighwaySim,
    arena: int = 0,
    agent: int = 0,
    *,
    size_px: tuple[int, int] | None = None,
    pixels_per_m: float = PIXELS_PER_M,
    centering: tuple[float, float] = (0.25, 0.5),
) -> np.ndarray:
    """(H, W, 3) uint8: the road from above, the road running left to right, centred on
    ``agent``; traffic coloured by behaviour, the watched agent red, other agents yellow.

    By default the whole width of the road, 40 m behind the car to 120 m ahead. ``size_px``
    (width, height) frames it as highway-env's viewer does instead: that many pixels at
    ``pixels_per_m``, the watched car at ``centering`` (fractions of the width and height)."""
    st = sim.state
    road_width = sim.road.lane_count * sim.road.lane_width_m
    rail = sim.config.road.barrier_offset_m
    centre_x = st.x_m[arena, agent]
    # World coordinates of pixel centres: x to the right, y (left of the road) upwards.
    if size_px is None:
        width = int((VIEW_BEHIND_M + VIEW_AHEAD_M) * PIXELS_PER_M)
        height = int((road_width + 2 * (rail + MARGIN_M)) * PIXELS_PER_M)
        wx = centre_x - VIEW_BEHIND_M + (np.arange(width) + 0.5) / PIXELS_PER_M
        wy = road_width + rail + MARGIN_M - (np.arange(height) + 0.5) / PIXELS_PER_M
    else:
        (width, height), scale = size_px, pixels_per_m
        left_m = centre_x - centering[0] * width / scale
        top_m = st.y_m[arena, agent] + centering[1] * height / scale
        wx = left_m + (np.arange(width) + 0.5) / scale
        wy = top_m - (np.arange(height) + 0.5) / scale
    img = np.empty((height, width, 3), dtype=np.uint8)
    img[:] = _GRASS
    on_road = (wy >= 0) & (wy <= road_width)
    img[on_road] = _ROAD
    rail_rows = (np.abs(wy - (road_width + rail)) < 0.3) | (np.abs(wy + rail) < 0.3)
    img[rail_rows] = _RAIL
    lane_width = sim.road.lane_width_m
    line_rows = np.abs(wy / lane_width - np.rint(wy / lane_width)) * lane_width < 0.15
    line_rows &= (wy >= -0.2) & (wy <= road_width + 0.2)
    edge_rows = line_rows & ((np.abs(wy) < 0.3) | (np.abs(wy - road_width) < 0.3))
    dashes = (wx % 12.0) < 6.0
    img[np.ix_(line_rows & ~edge_rows, dashes)] = _MARK
    img[edge_rows] = _MARK

    active = st.active[arena]
    x, y = st.x_m[arena][active], st.y_m[arena][active]
    kind = st.kind[arena][active].copy()
    column = np.flatnonzero(active)
    kind[column == agent] = _WATCHED_AGENT
    half_l = sim.kinds.half_length[np.minimum(kind, AGENT_KIND)]
    half_w = sim.kinds.half_width[np.minimum(kind, AGENT_KIND)]
    # Per pixel, the last car (in slot order) whose box covers it; the watched agent on top.
    order = np.argsort(kind == _WATCHED_AGENT, kind="stable")
    x, y, kind, half_l, half_w = x[order], y[order], kind[order], half_l[order], half_w[order]
    in_x = np.abs(wx[None, :] - x[:, None]) <= half_l[:, None]  # (C, W)
    in_y = np.abs(wy[None, :] - y[:, None]) <= half_w[:, None]  # (C, H)
    cover = in_y[:, :, None] & in_x[:, None, :]  # (C, H, W)
    if cover.shape[0]:
        any_car = cover.any(axis=0)
        top = cover.shape[0] - 1 - np.argmax(cover[::-1], axis=0)
        img[any_car] = _KIND_COLOURS[kind[top[any_car]]]
    return img
