"""The sensors' compiled loops (numba): the LIDAR scan, the camera's ground, boxes and colours,
and the LIDAR grid map. Compiled and cached as
:mod:`overtake.server.sim.kernels` says.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lidar_scan(
    origin_x: np.ndarray,
    origin_y: np.ndarray,
    heading: np.ndarray,
    cos_h: np.ndarray,
    sin_h: np.ndarray,
    rel_x: np.ndarray,
    rel_y: np.ndarray,
    half_length: np.ndarray,
    half_width: np.ndarray,
    visible: np.ndarray,
    centre: np.ndarray,
    corner_angle: np.ndarray,
    ray_cos: np.ndarray,
    ray_sin: np.ndarray,
    rail_left_y: float,
    rail_right_y: float,
    max_range_m: float,
    dist: np.ndarray,
) -> None:
    """The LIDAR's distances (O, R) into ``dist`` (float32): the guard rails, then each
    visible car box (``rel_x``/``rel_y`` (O, V) relative to its observer) intersected with only
    the rays its angular extent covers, the nearest hit kept (0 from inside a box).

    The bearings of the cars' centres (``centre`` (O, V)) and corners (``corner_angle``
    (O, V, 4)) come in from numpy's arctan2, whose rounding (SIMD on some CPUs) a compiled
    arctan2 would not match bit for bit; ``cos_h``/``sin_h`` likewise. See
    :meth:`.sensors.lidar.Lidar.scan`.
    """
    observers, vehicles = rel_x.shape
    rays = ray_cos.shape[0]
    step = 2.0 * np.pi / rays
    max_range_sq = max_range_m**2
    ray_dx = np.empty(rays)
    ray_dy = np.empty(rays)
    best = np.empty(rays)
    for o in range(observers):
        for r in range(rays):
            dx = cos_h[o] * ray_cos[r] - sin_h[o] * ray_sin[r]
            dy = sin_h[o] * ray_cos[r] + cos_h[o] * ray_sin[r]
            ray_dx[r], ray_dy[r] = dx, dy
            # Guard rails: the rail on the side the ray points to (a ray exactly along the
            # road gets a vanishing sideways component and so an out-of-range distance).
            safe_dy = 1e-12 if abs(dy) < 1e-12 else dy
            rail_y = rail_left_y if safe_dy > 0.0 else rail_right_y
            best[r] = min((rail_y - origin_y[o]) / safe_dy, max_range_m)
        for v in range(vehicles):
            if not visible[o, v]:
                continue
            x_lo, x_hi = rel_x[o, v] - half_length[o, v], rel_x[o, v] + half_length[o, v]
            y_lo, y_hi = rel_y[o, v] - half_width[o, v], rel_y[o, v] + half_width[o, v]
            near_x = max(x_lo, min(0.0, x_hi))  # the box's nearest point
            near_y = max(y_lo, min(0.0, y_hi))
            if near_x * near_x + near_y * near_y > max_range_sq:
                continue
            if near_x == 0.0 and near_y == 0.0:
                first, count = 0, rays  # inside the box: every ray
            else:
                # Angular extent: the corners' bearings relative to the centre's (wrapped, so a
                # car behind, across the +-pi seam, is handled like any other).
                lo, hi = np.inf, -np.inf
                for k in range(4):
                    offset = (corner_angle[o, v, k] - centre[o, v] + np.pi) % (2.0 * np.pi) - np.pi
                    lo, hi = min(lo, offset), max(hi, offset)
                relative = (centre[o, v] - heading[o]) / step
                first = int(np.ceil(relative + lo / step))
                last = int(np.floor(relative + hi / step))
                count = min(max(last - first + 1, 0), rays)
            for j in range(count):
                ray = (first + j) % rays
                # A ray exactly parallel to a slab: a tiny component keeps the test exact
                # enough (the hit moves by far less than a millimetre) without 0/0.
                dx = ray_dx[ray]
                dy = ray_dy[ray]
                if dx == 0.0:
                    dx = 1e-12
                if dy == 0.0:
                    dy = 1e-12
                tx1, tx2 = x_lo / dx, x_hi / dx
                ty1, ty2 = y_lo / dy, y_hi / dy
                enter = max(min(tx1, tx2), min(ty1, ty2))
                leave = min(max(tx1, tx2), max(ty1, ty2))
                if leave >= enter and leave >= 0.0:
                    hit = max(enter, 0.0)
                    if hit < best[ray]:
                        best[ray] = hit
        for r in range(rays):
            dist[o, r] = best[r]


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


@njit(cache=True, nogil=True, inline="always")
def _pixel_span(lo: float, hi: float) -> tuple[float, float]:
    """The first and last pixel centres inside the span [lo, hi] of screen offsets (pixel p
    covers [p, p + 1)); a sliver narrower than a pixel still covers one."""
    first, last = np.ceil(lo - 0.5), np.floor(hi - 0.5)
    if last < first:
        middle = np.floor(0.5 * (lo + hi))
        return middle, middle
    return first, last


@njit(cache=True, nogil=True)
def paint_cars(
    image: np.ndarray,
    eye_x: np.ndarray,
    eye_y: np.ndarray,
    cos_h: np.ndarray,
    sin_h: np.ndarray,
    car_x: np.ndarray,
    car_y: np.ndarray,
    car_half_length: np.ndarray,
    car_half_width: np.ndarray,
    car_visible: np.ndarray,
    corner_l: np.ndarray,
    corner_w: np.ndarray,
    cos_p: float,
    sin_p: float,
    drop_sin: np.ndarray,
    drop_cos: np.ndarray,
    focal_px: float,
    near_m: float,
    max_distance_m: float,
    value: np.uint8,
) -> None:
    """Paint every car some observer sees into its image (O, H, W) uint8, in place: the
    screen rectangle bounding the box's eight corners (four ground corners ``corner_l`` x
    ``corner_w`` half sizes, at the heights whose drops below the camera ``drop_sin`` /
    ``drop_cos`` (2,) give, pitched by ``cos_p`` / ``sin_p``), seen where it is visible, some
    corner is beyond the near plane and the nearest is within ``max_distance_m``.

    ``eye_*``, ``cos_h``, ``sin_h`` (O,) the camera of each observer; ``car_*`` (O, V). The
    arithmetic of :meth:`..camera.Camera.render`, car by car."""
    observers, vehicles = car_x.shape
    height, width = image.shape[1], image.shape[2]
    half_h, half_w = height / 2.0, width / 2.0
    for o in range(observers):
        ex, ey, ch, sh = eye_x[o], eye_y[o], cos_h[o], sin_h[o]
        for v in range(vehicles):
            if not car_visible[o, v]:
                continue
            dx = car_x[o, v] - ex
            dy = car_y[o, v] - ey
            hl, hw = car_half_length[o, v], car_half_width[o, v]
            fwd_max = -np.inf
            fwd_min = np.inf
            col_max = -np.inf
            col_min = np.inf
            row_max = -np.inf
            row_min = np.inf
            for k in range(4):
                cdx = dx + corner_l[k] * hl
                cdy = dy + corner_w[k] * hw
                rel_fwd = ch * cdx + sh * cdy
                rel_left = ch * cdy - sh * cdx
                fwd_min = min(fwd_min, rel_fwd)
                for h in range(2):
                    cam_fwd = rel_fwd * cos_p - drop_sin[h]
                    cam_up = rel_fwd * sin_p + drop_cos[h]
                    fwd_max = max(fwd_max, cam_fwd)
                    inv_depth = focal_px / max(cam_fwd, near_m)
                    col = rel_left * inv_depth
                    row = cam_up * inv_depth
                    col_max = max(col_max, col)
                    col_min = min(col_min, col)
                    row_max = max(row_max, row)
                    row_min = min(row_min, row)
            if not (fwd_max > near_m and fwd_min < max_distance_m):
                continue
            c_lo, c_hi = _pixel_span(half_w - col_max, half_w - col_min)
            r_lo, r_hi = _pixel_span(half_h - row_max, half_h - row_min)
            r0 = max(r_lo, 0.0)
            r1 = min(r_hi, height - 1.0)
            c0 = max(c_lo, 0.0)
            c1 = min(c_hi, width - 1.0)
            if r0 > r1 or c0 > c1:
                continue
            for r in range(int(r0), int(r1) + 1):
                for c in range(int(c0), int(c1) + 1):
                    image[o, r, c] = value


@njit(cache=True, nogil=True)
def colour(classes: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(O, H, W, 3) uint8: each pixel's surface class (O, H, W) looked up in ``palette``."""
    observers, height, width = classes.shape
    image = np.empty((observers, height, width, 3), dtype=np.uint8)
    for o in range(observers):
        for r in range(height):
            for c in range(width):
                k = classes[o, r, c]
                image[o, r, c, 0] = palette[k, 0]
                image[o, r, c, 1] = palette[k, 1]
                image[o, r, c, 2] = palette[k, 2]
    return image


@njit(cache=True, nogil=True)
def lidar_grid(
    distance: np.ndarray,
    ray_cos: np.ndarray,
    ray_sin: np.ndarray,
    hit_below_m: float,
    ahead_m: float,
    half_width_m: float,
    row_m: float,
    column_m: float,
    cells: int,
) -> np.ndarray:
    """(O, cells * cells) uint8: 255 in each cell of the car-centred grid that a ray's hit
    (``distance`` (O, R) below ``hit_below_m``) falls in, rows from ``ahead_m`` in front
    backwards, columns from ``half_width_m`` on the left rightwards
    (:class:`.sensors.lidar_map.LidarMap`)."""
    observers, rays = distance.shape
    image = np.zeros((observers, cells * cells), dtype=np.uint8)
    for o in range(observers):
        for r in range(rays):
            d = np.float64(distance[o, r])
            if not d < hit_below_m:
                continue
            row = np.floor((ahead_m - d * ray_cos[r]) / row_m)
            column = np.floor((half_width_m - d * ray_sin[r]) / column_m)
            if 0 <= row < cells and 0 <= column < cells:
                image[o, int(row) * cells + int(column)] = 255
    return image


# --- highway-env's Kinematics observation (kinematics.py) ----------------------------------------

# envs/common/abstract.py: PERCEPTION_DISTANCE = 5 * Vehicle.MAX_SPEED.
PERCEPTION_M = 200.0


@njit(cache=True, nogil=True)
def _features(x, y_sim, speed, heading_sim, lanes, lane_width, codes, row):
    """One car's features in highway-env's coordinates (Vehicle.to_dict, no route)."""
    y = (lanes - 0.5) * lane_width - y_sim
    heading = -heading_sim
    lane = min(max(int(y / lane_width + 0.5), 0), lanes - 1)
    for column in range(codes.shape[0]):
        code = codes[column]
        if code == 0:
            value = 1.0
        elif code == 1:
            value = x
        elif code == 2:
            value = y
        elif code == 3:
            value = speed * math.cos(heading)
        elif code == 4:
            value = speed * math.sin(heading)
        elif code == 5:
            value = heading
        elif code == 6:
            value = math.cos(heading)
        elif code == 7:
            value = math.sin(heading)
        elif code == 10:
            value = x
        elif code == 11:
            value = y - lane * lane_width
        elif code == 12:
            value = ((heading + math.pi) % (2.0 * math.pi)) - math.pi
        else:  # cos_d, sin_d: no destination, as highway-env's without a route
            value = 0.0
        row[column] = value


@njit(cache=True, nogil=True)
def _scale(row, codes, scaled, low, high, clip):
    for column in range(codes.shape[0]):
        code = codes[column]
        if scaled[code]:
            value = 2.0 * (row[column] - low[code]) / (high[code] - low[code]) - 1.0
            row[column] = min(max(value, -1.0), 1.0) if clip else value


@njit(cache=True, nogil=True)
def observe_kinematics(
    x, y, speed, heading, active, agents, lanes, lane_width, length, codes, scaled, low, high,
    clip, absolute, see_behind, out,
):  # fmt: skip
    arenas, cars = x.shape
    count = out.shape[2]
    features = codes.shape[0]
    order = np.empty(cars, dtype=np.int64)
    key = np.empty(cars)
    origin = np.empty(features)
    row = np.empty(features)
    for a in range(arenas):
        for k in range(agents):
            if not active[a, k]:
                continue
            _features(x[a, k], y[a, k], speed[a, k], heading[a, k], lanes, lane_width, codes,
                      origin)  # fmt: skip
            row[:] = origin
            _scale(row, codes, scaled, low, high, clip)
            out[a, k, 0, :] = row
            found = 0
            for v in range(cars):
                if v == k or not active[a, v]:
                    continue
                dx, dy = x[a, v] - x[a, k], y[a, v] - y[a, k]
                if math.sqrt(dx * dx + dy * dy) >= PERCEPTION_M:
                    continue
                if not see_behind and not dx > -2.0 * length:
                    continue
                order[found] = v
                key[found] = abs(dx)
                found += 1
            # Nearest along the road first; equals keep the cars' order (a stable sort).
            nearest = np.argsort(key[:found], kind="mergesort")
            for r in range(min(found, count - 1)):
                v = order[nearest[r]]
                _features(x[a, v], y[a, v], speed[a, v], heading[a, v], lanes, lane_width,
                          codes, row)  # fmt: skip
                if not absolute:
                    for column in range(features):
                        if 1 <= codes[column] <= 4:  # x, y, vx, vy (Vehicle.to_dict's origin)
                            row[column] -= origin[column]
                _scale(row, codes, scaled, low, high, clip)
                out[a, k, r + 1, :] = row
