"""LIDAR and camera against geometry computed by hand from scripted scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from overtake.protocol.vocabulary import EGO_FIELDS
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.physics import headings
from overtake.server.sim.sensors.camera import VEHICLE_HEIGHT_M

from tests.support.scenes import (
    HALF_LENGTH,
    HALF_WIDTH,
    LANE_WIDTH,
    Car,
    camera_of,
    keep,
    lidar_of,
    place,
    scripted_sim,
)

MAX_RANGE = 80.0
BARRIER_OFFSET = 1.0
LANES = 5


def rail_distances(ego_lane: int) -> tuple[float, float]:
    """Lateral distance from the ego's centre to the left and the right guard rail."""
    y = (ego_lane + 0.5) * LANE_WIDTH
    return LANES * LANE_WIDTH + BARRIER_OFFSET - y, y + BARRIER_OFFSET


# --- LIDAR -----------------------------------------------------------------------------------


def test_empty_road_reads_rails_sideways_and_max_range_along_the_road():
    lidar = lidar_of(scripted_sim([], ego_lane=2))
    assert lidar.shape == (360,) and lidar.dtype == np.float32
    left, right = rail_distances(2)
    for ray in range(360):
        a = math.radians(ray)
        s = math.sin(a)
        if abs(s) < 1e-9:
            expected = MAX_RANGE
        else:
            expected = min((left if s > 0 else right) / abs(s), MAX_RANGE)
        assert lidar[ray] == pytest.approx(expected, rel=1e-5), ray
    # Along the road nothing is in range: exactly the maximum.
    assert lidar[0] == MAX_RANGE and lidar[180] == MAX_RANGE
    assert lidar[90] == pytest.approx(left) and lidar[270] == pytest.approx(right)


@pytest.mark.parametrize("ego_lane", [0, 4])
def test_rails_from_an_outer_lane(ego_lane):
    lidar = lidar_of(scripted_sim([], ego_lane=ego_lane))
    left, right = rail_distances(ego_lane)
    assert lidar[90] == pytest.approx(left, rel=1e-6)
    assert lidar[270] == pytest.approx(right, rel=1e-6)
    assert lidar[30] == pytest.approx(min(left / math.sin(math.radians(30)), MAX_RANGE), rel=1e-5)
    assert lidar[330] == pytest.approx(min(right / math.sin(math.radians(30)), MAX_RANGE), rel=1e-5)
    # The outer rail is 1.75 + 1 m away: a shallow ray still reaches it within range.
    near = right if ego_lane == 0 else left
    ray = 355 if ego_lane == 0 else 5
    assert near == pytest.approx(2.75)
    assert lidar[ray] == pytest.approx(near / math.sin(math.radians(5)), rel=1e-5)


def test_car_straight_ahead_is_seen_at_its_rear_bumper():
    distance = 20.0
    lidar = lidar_of(scripted_sim([Car(distance, 2, 60)], ego_lane=2))
    rear = distance - HALF_LENGTH  # the LIDAR sits at the ego's centre
    assert rear == 17.75
    assert lidar[0] == pytest.approx(rear, rel=1e-6)
    # Rays a few degrees either side still hit the rear face: rear / cos(angle) ...
    for degrees in (1, 2):
        expected = rear / math.cos(math.radians(degrees))
        assert abs(rear * math.tan(math.radians(degrees))) < HALF_WIDTH
        assert lidar[degrees] == pytest.approx(expected, rel=1e-6)
        assert lidar[360 - degrees] == pytest.approx(expected, rel=1e-6)
    # ... and the next ray passes beside the car (tan(3 deg) * 17.75 > 0.9) and sees nothing.
    assert rear * math.tan(math.radians(3)) > HALF_WIDTH
    assert lidar[3] == MAX_RANGE and lidar[357] == MAX_RANGE
    # Behind, nothing.
    assert lidar[180] == MAX_RANGE


def test_car_behind_is_seen_at_its_front_bumper():
    lidar = lidar_of(scripted_sim([Car(-30.0, 2, 60)], ego_lane=2))
    front = 30.0 - HALF_LENGTH
    assert lidar[180] == pytest.approx(front, rel=1e-6)
    assert lidar[181] == pytest.approx(front / math.cos(math.radians(1)), rel=1e-6)
    assert lidar[0] == MAX_RANGE


def test_car_directly_left_is_seen_at_its_near_side():
    lidar = lidar_of(scripted_sim([Car(0.0, 3, 60)], ego_lane=2))
    side = LANE_WIDTH - HALF_WIDTH
    assert lidar[90] == pytest.approx(side, rel=1e-6)
    for degrees in (85, 95):
        # The near side spans x in [-2.25, 2.25]: 5 degrees off stays on it.
        assert abs(side / math.tan(math.radians(degrees))) < HALF_LENGTH
        assert lidar[degrees] == pytest.approx(side / math.sin(math.radians(degrees)), rel=1e-6)
    # The right side still sees its rail.
    assert lidar[270] == pytest.approx(rail_distances(2)[1], rel=1e-6)


def test_car_directly_right_is_seen_by_ray_270():
    lidar = lidar_of(scripted_sim([Car(0.0, 1, 60)], ego_lane=2))
    assert lidar[270] == pytest.approx(LANE_WIDTH - HALF_WIDTH, rel=1e-6)
    assert lidar[90] == pytest.approx(rail_distances(2)[0], rel=1e-6)


def test_diagonal_car_is_hit_on_the_nearest_face():
    # Car one lane left, 10 m ahead: its near side is the plane y = 2.6, its rear x = 7.75.
    lidar = lidar_of(scripted_sim([Car(10.0, 3, 60)], ego_lane=2))
    side = LANE_WIDTH - HALF_WIDTH
    rear = 10.0 - HALF_LENGTH
    for ray in range(360):
        a = math.radians(ray)
        c, s = math.cos(a), math.sin(a)
        hits = []
        if c > 1e-9:  # rear face x = rear, y in [2.6, 4.4]
            t = rear / c
            if side <= t * s <= side + 2 * HALF_WIDTH:
                hits.append(t)
        if s > 1e-9:  # right-hand face y = side, x in [7.75, 12.25]
            t = side / s
            if rear <= t * c <= rear + 2 * HALF_LENGTH:
                hits.append(t)
        if hits:
            assert lidar[ray] == pytest.approx(min(hits), rel=1e-5), ray
    empty = lidar_of(scripted_sim([], ego_lane=2))
    covered = np.flatnonzero(lidar != empty).tolist()
    expected_lo = math.ceil(math.degrees(math.atan2(side, 12.25)))
    expected_hi = math.floor(math.degrees(math.atan2(side + 2 * HALF_WIDTH, rear)))
    assert covered == list(range(expected_lo, expected_hi + 1))


def test_nearer_car_hides_a_farther_one():
    lidar = lidar_of(scripted_sim([Car(40.0, 2, 60), Car(15.0, 2, 60)], ego_lane=2))
    assert lidar[0] == pytest.approx(15.0 - HALF_LENGTH, rel=1e-6)


def test_car_beyond_range_is_not_seen():
    lidar = lidar_of(scripted_sim([Car(MAX_RANGE + HALF_LENGTH + 1.0, 2, 60)], ego_lane=2))
    assert lidar[0] == MAX_RANGE
    lidar = lidar_of(scripted_sim([Car(MAX_RANGE + HALF_LENGTH - 1.0, 2, 60)], ego_lane=2))
    assert lidar[0] == pytest.approx(MAX_RANGE - 1.0, rel=1e-6)


def test_inactive_slots_are_invisible():
    sim = scripted_sim([Car(20.0, 2, 60)], ego_lane=2)
    sim.state.active[0, 1] = False
    assert lidar_of(sim)[0] == MAX_RANGE


def test_lidar_turns_with_the_ego_during_a_lane_change():
    # Mid-change the ego heads left, so ray 0 no longer points along the road: a car far ahead
    # in the origin lane is missed by ray 0 but found a little clockwise of it.
    sim = scripted_sim([Car(60.0, 2, 60)], ego_lane=2)
    straight = lidar_of(sim)
    sim.step(np.array([[3]]))
    sim.step(np.array([[3]]))  # ignored: the change is under way
    heading = float(headings(sim.state, sim.kinds, sim.road.lane_width_m, sim.agents)[0, 0])
    assert heading > math.radians(1.0)
    turned = lidar_of(sim)
    assert straight[0] == pytest.approx(60.0 - HALF_LENGTH, rel=1e-6)
    # Ray 0 now meets the left rail at (lateral distance) / sin(heading) ...
    ego_y = float(sim.state.y_m[0, 0])
    rail_left = LANES * LANE_WIDTH + BARRIER_OFFSET
    assert turned[0] == pytest.approx((rail_left - ego_y) / math.sin(heading), rel=1e-5)
    assert turned[0] < 60.0 - HALF_LENGTH
    # ... and the car's rear is found by the ray pointing at it, clockwise of ray 0.
    dx = float(sim.state.x_m[0, 1] - sim.state.x_m[0, 0]) - HALF_LENGTH
    dy = float(sim.state.y_m[0, 1]) - ego_y
    bearing = math.degrees(math.atan2(dy, dx) - heading) % 360.0
    ray = round(bearing) % 360
    assert 340 < ray < 360
    angle = math.radians(ray) + heading
    assert turned[ray] == pytest.approx(dx / math.cos(angle), rel=1e-4)


def test_lidar_ray_count_and_range_follow_the_config():
    sim = scripted_sim(
        [Car(20.0, 2, 60)], ego_lane=2, overrides={"lidar.ray_count": 8, "lidar.max_range_m": 15.0}
    )
    lidar = lidar_of(sim)
    assert lidar.shape == (8,)
    left, right = rail_distances(2)
    # Ray k of 8 points 45 * k degrees left: 0 ahead (car at 17.75 > 15), 2 left, 6 right.
    assert lidar[0] == 15.0
    assert lidar[2] == pytest.approx(left)
    assert lidar[6] == pytest.approx(right)
    assert lidar[1] == pytest.approx(min(left / math.sin(math.pi / 4), 15.0), rel=1e-6)


# --- camera ----------------------------------------------------------------------------------

CAR_GREY = 20
MARKING_GREY = 240
W = H = 80  # the preset's camera (the authors' code's 80x80)
FOV_DEG = 70.0
MOUNT_HEIGHT = 1.2
MOUNT_FORWARD = 0.3
PITCH_DEG = 6.0


def projected_span(
    dx: float, dy: float, width: int = W, height: int = H, fov_deg: float = FOV_DEG
) -> tuple[float, float, float, float]:
    """Screen span (col_lo, col_hi, row_lo, row_hi) of a car centred dx ahead, dy left of the ego.

    Pinhole model: focal length f = (W/2) / tan(fov/2); a point ``left`` metres to the left,
    ``forward`` metres ahead and ``up`` metres above the eye in the (pitched) camera frame lands
    at column W/2 - f * left / forward and row H/2 - f * up / forward. A car is drawn as the
    screen rectangle bounding the projections of its eight corners.
    """
    f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    pitch = math.radians(PITCH_DEG)
    cols, rows = [], []
    for sx in (-1, 1):
        for sy in (-1, 1):
            for z in (0.0, VEHICLE_HEIGHT_M):
                ahead = dx + sx * HALF_LENGTH - MOUNT_FORWARD
                left = dy + sy * HALF_WIDTH
                drop = z - MOUNT_HEIGHT
                forward = ahead * math.cos(pitch) - drop * math.sin(pitch)
                up = ahead * math.sin(pitch) + drop * math.cos(pitch)
                cols.append(width / 2.0 - f * left / forward)
                rows.append(height / 2.0 - f * up / forward)
    return min(cols), max(cols), min(rows), max(rows)


def projected_extent(
    dx: float, dy: float, width: int = W, height: int = H, fov_deg: float = FOV_DEG
) -> tuple[list[int], list[int]]:
    """Pixel columns and rows whose centres (p + 0.5) lie inside the car's screen span."""
    col_lo, col_hi, row_lo, row_hi = projected_span(dx, dy, width, height, fov_deg)
    covered_cols = [c for c in range(width) if col_lo <= c + 0.5 <= col_hi]
    covered_rows = [r for r in range(height) if row_lo <= r + 0.5 <= row_hi]
    return covered_cols, covered_rows


def car_pixels(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    car = image == CAR_GREY
    return np.flatnonzero(car.any(axis=0)), np.flatnonzero(car.any(axis=1))


def test_empty_road_image_has_sky_road_and_markings_but_no_car():
    image = camera_of(scripted_sim([], ego_lane=2))
    assert image.shape == (H, W) and image.dtype == np.uint8
    assert not (image == CAR_GREY).any()
    assert (image == MARKING_GREY).any()
    # Sky on top, road under the car's nose at the bottom middle.
    top, bottom = image[0], image[-1]
    assert len(np.unique(top)) == 1 and top[0] != MARKING_GREY
    assert bottom[W // 2] != top[0]


@pytest.mark.parametrize("ego_x", [0.0, 6.0])
def test_lane_markings_are_where_the_lane_lines_project(ego_x):
    # The ego is centred in its lane, so the nearest lines are 1.75 m either side of the eye;
    # they are dashed (6 m dash, 6 m gap), so near rows show them or not by where the ego is.
    sim = scripted_sim([], ego_lane=2)
    place(sim, 0, x=ego_x, lane=2, speed_kmh=60.0)
    image = camera_of(sim)
    f = (W / 2.0) / math.tan(math.radians(FOV_DEG) / 2.0)
    pitch = math.radians(PITCH_DEG)

    def ground_ahead(row: int) -> float:
        """Metres ahead of the eye where the centre ray of ``row`` meets the road (inf: sky)."""
        up = -((row + 0.5) - H / 2.0) / f  # ray direction in the camera frame
        ray_x = math.cos(pitch) + up * math.sin(pitch)
        ray_z = -math.sin(pitch) + up * math.cos(pitch)
        return math.inf if ray_z >= 0 else ray_x * MOUNT_HEIGHT / -ray_z

    on_dash = off_dash = 0
    for row in range(1, H):
        ahead = ground_ahead(row)
        along = ground_ahead(row - 1) - ahead  # road length one row spans
        if not math.isfinite(along) or along > 1.0:
            continue  # far rows: dashes blur into solid lines
        phase = (ego_x + MOUNT_FORWARD + ahead) % 12.0  # dashes 6 m long every 12 m
        if min(phase, abs(phase - 6.0), 12.0 - phase) < 1.0:
            continue  # too close to a dash's end to call
        for side in (-1, 1):
            # A ground point ``left`` metres to the side lands at column W/2 - f * left / depth;
            # the ray's depth per metre ahead is fixed per row, so use the ray's own scale.
            up = -((row + 0.5) - H / 2.0) / f
            depth = ahead / (math.cos(pitch) + up * math.sin(pitch))
            col = W / 2.0 - side * (LANE_WIDTH / 2.0) * f / depth
            c = math.floor(col)
            if not 1 <= c < W - 1:
                continue
            window = image[row, c - 1 : c + 2]
            if phase < 6.0:
                on_dash += 1
                assert (window == MARKING_GREY).any(), (row, side, col)
            else:
                off_dash += 1
                assert not (window == MARKING_GREY).any(), (row, side, col)
    assert (on_dash if ego_x == 0.0 else off_dash) >= 20, (on_dash, off_dash)
    # Markings never appear in the middle of the ego's own lane near the car.
    assert not (image[H - 10 :, W // 2 - 5 : W // 2 + 5] == MARKING_GREY).any()


def test_dashes_scroll_past_as_the_car_drives():
    sim = scripted_sim([], ego_lane=2, ego_speed_kmh=54.0)  # 15 m/s: 6 m per decision
    before = camera_of(sim)
    keep(sim)
    assert sim.state.x_m[0, 0] == pytest.approx(6.0)
    # Half a dash period on, the dashes beside the car and the gaps between them swap.
    assert not np.array_equal(camera_of(sim), before)


@pytest.mark.parametrize("distance", [12.0, 20.0, 35.0])
def test_car_straight_ahead_is_in_the_centre_columns(distance):
    image = camera_of(scripted_sim([Car(distance, 2, 60)], ego_lane=2))
    cols, rows = car_pixels(image)
    expected_cols, expected_rows = projected_extent(distance, 0.0)
    assert cols.tolist() == expected_cols
    assert rows.tolist() == expected_rows
    # Symmetric about the centre.
    assert cols.min() + cols.max() == W - 1
    # Every pixel of the bounding rectangle is the car's grey.
    assert (image[np.ix_(rows, cols)] == CAR_GREY).all()


def test_a_car_smaller_than_a_pixel_is_drawn_in_a_pixel_it_covers():
    # On a 32 x 32 image a car 100 m ahead spans less than half a pixel each way. Slide it
    # sideways in small steps: every pixel drawn as car must overlap the car's screen span
    # (pixel p covers [p, p + 1)), and exactly one column and one row are drawn.
    size = 32
    wrong = []
    for dy in np.linspace(-0.6, 0.6, 25):
        sim = scripted_sim(
            [Car(100.0, 2, 60)],
            ego_lane=2,
            overrides={"camera.width_px": size, "camera.height_px": size, "lidar.enabled": False},
        )
        sim.state.y_m[0, 1] += dy
        cols, rows = car_pixels(camera_of(sim))
        col_lo, col_hi, row_lo, row_hi = projected_span(100.0, float(dy), size, size)
        assert col_hi - col_lo < 0.5 and row_hi - row_lo < 0.5
        assert len(cols) == 1 and len(rows) == 1
        if not (cols[0] < col_hi and cols[0] + 1 > col_lo):
            wrong.append(("column", round(float(dy), 2), int(cols[0]), (col_lo, col_hi)))
        if not (rows[0] < row_hi and rows[0] + 1 > row_lo):
            wrong.append(("row", round(float(dy), 2), int(rows[0]), (row_lo, row_hi)))
    assert not wrong, wrong


def test_car_in_the_left_lane_appears_left_of_centre():
    image = camera_of(scripted_sim([Car(20.0, 3, 60)], ego_lane=2))
    cols, rows = car_pixels(image)
    expected_cols, expected_rows = projected_extent(20.0, LANE_WIDTH)
    assert cols.tolist() == expected_cols
    assert rows.tolist() == expected_rows
    assert cols.max() < W / 2


def test_car_in_the_right_lane_appears_right_of_centre():
    image = camera_of(scripted_sim([Car(20.0, 1, 60)], ego_lane=2))
    cols, _ = car_pixels(image)
    assert cols.tolist() == projected_extent(20.0, -LANE_WIDTH)[0]
    assert cols.min() > W / 2


def test_nearer_car_covers_more_pixels():
    counts = []
    for distance in (10.0, 20.0, 40.0, 80.0):
        image = camera_of(scripted_sim([Car(distance, 2, 60)], ego_lane=2))
        counts.append(int((image == CAR_GREY).sum()))
    assert counts[0] > counts[1] > counts[2] > counts[3] > 0


def test_cars_behind_are_not_drawn():
    image = camera_of(scripted_sim([Car(-20.0, 2, 60), Car(-10.0, 3, 60)], ego_lane=2))
    assert not (image == CAR_GREY).any()


def test_rgb_camera_has_three_channels_and_a_red_car():
    sim = scripted_sim([Car(20.0, 2, 60)], ego_lane=2, overrides={"camera.rgb": True})
    image = camera_of(sim)
    assert image.shape == (H, W, 3) and image.dtype == np.uint8
    expected_cols, expected_rows = projected_extent(20.0, 0.0)
    patch = image[np.ix_(expected_rows, expected_cols)]
    assert (patch == np.array([200, 30, 30], dtype=np.uint8)).all()
    # Same scene in grey marks exactly the same pixels as car.
    grey = camera_of(scripted_sim([Car(20.0, 2, 60)], ego_lane=2))
    red = (image == np.array([200, 30, 30])).all(axis=-1)
    assert np.array_equal(red, grey == CAR_GREY)


@pytest.mark.parametrize("width, height", [(64, 48), (120, 30)])
def test_camera_of_another_size(width, height):
    sim = scripted_sim(
        [Car(20.0, 2, 60)],
        ego_lane=2,
        overrides={"camera.width_px": width, "camera.height_px": height},
    )
    image = camera_of(sim)
    assert image.shape == (height, width)
    cols, rows = car_pixels(image)
    expected_cols, expected_rows = projected_extent(20.0, 0.0, width, height)
    assert cols.tolist() == expected_cols
    assert rows.tolist() == expected_rows
    rgb = camera_of(
        scripted_sim(
            [],
            ego_lane=2,
            overrides={"camera.width_px": width, "camera.height_px": height, "camera.rgb": True},
        )
    )
    assert rgb.shape == (height, width, 3)


def test_field_of_view_changes_the_projection():
    sim = scripted_sim(
        [Car(20.0, 3, 60)], ego_lane=2, overrides={"camera.horizontal_fov_deg": 40.0}
    )
    cols, _ = car_pixels(camera_of(sim))
    assert cols.tolist() == projected_extent(20.0, LANE_WIDTH, fov_deg=40.0)[0]


def test_observe_shapes_and_sensor_switches():
    sim = scripted_sim([Car(20.0, 2, 60)], ego_lane=2, overrides={"camera.enabled": False})
    obs = sim.observe()
    assert set(obs) == {"lidar", "ego"}
    assert obs["lidar"].shape == (1, 1, 360) and obs["ego"].shape == (1, 1, 6)
    sim = scripted_sim([Car(20.0, 2, 60)], ego_lane=2, overrides={"lidar.enabled": False})
    assert set(sim.observe()) == {"camera", "ego"}


def test_ego_vector_fields():
    # Every field the ego vector can hold, in the catalogue's order.
    sim = scripted_sim(
        [Car(40.0, 1, 45.0), Car(1.0, 2, 60.0)],
        ego_lane=1,
        ego_speed_kmh=54.0,
        cruise_kmh=72.0,
        overrides={"ego_vector.fields": list(EGO_FIELDS)},
    )
    assert sim.observation_spaces()["ego"].shape == (len(EGO_FIELDS),)
    ego = dict(zip(EGO_FIELDS, sim.observe()["ego"][0, 0].tolist(), strict=True))
    assert ego == pytest.approx(
        {
            "speed_mps": 15.0,
            "cruise_target_mps": 20.0,
            "lane_index": 1.0,
            "lane_count": 5.0,
            "lane_change_progress": 0.0,
            "lane_change_direction": 0.0,
            # A car beside in lane 2: a left warning; lane 0 is clear.
            "left_warning": 1.0,
            "right_warning": 0.0,
            # 40 m ahead, 35.5 m bumper to bumper: beyond 2 s at 15 m/s + 2 m -> no warning.
            "forward_warning": 0.0,
            "ahead_distance_m": 40.0 - 2 * HALF_LENGTH,
            "ahead_speed_mps": 45.0 / 3.6,
        },
        abs=1e-4,
    )
    sim.step(np.array([[4]]))  # start a change to the right
    ego = dict(zip(EGO_FIELDS, sim.observe()["ego"][0, 0].tolist(), strict=True))
    assert ego["lane_change_direction"] == -1.0
    assert 0.0 < ego["lane_change_progress"] < 1.0
    place(sim, 0, x=0.0, lane=3, speed_kmh=54.0)
    ego = dict(zip(EGO_FIELDS, sim.observe()["ego"][0, 0].tolist(), strict=True))
    assert ego["lane_index"] == 3.0
    # Nobody ahead in lane 3: the sensor's range and the car's own speed.
    assert ego["ahead_distance_m"] == 80.0 and ego["ahead_speed_mps"] == pytest.approx(15.0)


def test_min2018_ego_vector_is_the_authors_six():
    # Warnings left, right, forward; the distance to the car ahead and its speed; own speed.
    sim = scripted_sim([Car(15.0, 2, 40.0)], ego_lane=4, ego_speed_kmh=72.0)
    place(sim, 1, x=15.0, lane=4, speed_kmh=40.0)
    ego = sim.observe()["ego"][0, 0]
    assert ego.tolist() == pytest.approx(
        [1.0, 0.0, 1.0, 15.0 - 2 * HALF_LENGTH, 40.0 / 3.6, 20.0], abs=1e-4
    )
    space = sim.observation_spaces()["ego"]
    assert space.low.tolist() == [0.0] * 6
    assert space.high.tolist() == [1.0, 1.0, 1.0, 80.0, 100.0, 100.0]


# --- property tests against an independent ray caster ---------------------------------------


def brute_force_scan(
    car_dx: float, car_dy: float, ego_lane: int, eps: float = 1e-6
) -> tuple[np.ndarray, np.ndarray]:
    """Per ray of 360: expected distance, and whether the ray is clear of any grazing doubt.

    Rays are intersected with each of the car's four faces and with the rails, one ray at a
    time. A ray that passes within ``eps`` of a corner is marked doubtful (hit or miss are
    both right).
    """
    left, right = rail_distances(ego_lane)
    x_lo, x_hi = car_dx - HALF_LENGTH, car_dx + HALF_LENGTH
    y_lo, y_hi = car_dy - HALF_WIDTH, car_dy + HALF_WIDTH
    expected = np.empty(360)
    sure = np.ones(360, dtype=bool)
    for ray in range(360):
        a = math.radians(ray)
        c, s = math.cos(a), math.sin(a)
        best = MAX_RANGE
        if s > 1e-9:
            best = min(best, left / s)
        elif s < -1e-9:
            best = min(best, right / -s)
        for plane, speed, other_speed, lo, hi in (
            (x_lo, c, s, y_lo, y_hi),
            (x_hi, c, s, y_lo, y_hi),
            (y_lo, s, c, x_lo, x_hi),
            (y_hi, s, c, x_lo, x_hi),
        ):
            if abs(speed) < 1e-12:
                continue
            t = plane / speed
            if t < 0:
                continue
            other = t * other_speed
            if lo + eps < other < hi - eps:
                best = min(best, t)
            elif lo - eps <= other <= hi + eps and t < best:
                sure[ray] = False  # grazing a corner
        expected[ray] = best
    return expected, sure


@settings(max_examples=60, deadline=None)
@given(
    ego_lane=st.integers(0, 4),
    car_lane=st.integers(0, 4),
    car_dx=st.floats(-90.0, 90.0, allow_nan=False),
)
def test_lidar_matches_an_independent_ray_caster(ego_lane, car_lane, car_dx):
    assume(car_lane != ego_lane or abs(car_dx) >= 2 * HALF_LENGTH)  # no overlapping boxes
    sim = scripted_sim(
        [Car(car_dx, car_lane, 60.0)], ego_lane=ego_lane, overrides={"camera.enabled": False}
    )
    lidar = lidar_of(sim)
    expected, sure = brute_force_scan(car_dx, (car_lane - ego_lane) * LANE_WIDTH, ego_lane)
    np.testing.assert_allclose(lidar[sure], expected[sure].astype(np.float32), rtol=2e-6, atol=1e-5)


@settings(max_examples=40, deadline=None)
@given(car_lane=st.integers(0, 4), car_dx=st.floats(6.0, 60.0, allow_nan=False))
def test_camera_matches_the_pinhole_model(car_lane, car_dx):
    sim = scripted_sim(
        [Car(car_dx, car_lane, 60.0)], ego_lane=2, overrides={"lidar.enabled": False}
    )
    cols, rows = car_pixels(camera_of(sim))
    dy = (car_lane - 2) * LANE_WIDTH
    expected_cols, expected_rows = projected_extent(car_dx, dy)
    # Boundaries that fall on a pixel centre could go either way: allow one pixel there.
    if expected_cols:
        assert set(cols.tolist()) ^ set(expected_cols) <= {
            expected_cols[0] - 1,
            expected_cols[0],
            expected_cols[-1],
            expected_cols[-1] + 1,
        }
        assert abs(len(cols) - len(expected_cols)) <= 1
        assert set(rows.tolist()) ^ set(expected_rows) <= {
            expected_rows[0] - 1,
            expected_rows[0],
            expected_rows[-1],
            expected_rows[-1] + 1,
        }
    else:
        assert cols.size == 0


# --- several agents --------------------------------------------------------------------------


def test_agents_see_each_other():
    config = make_config(overrides={"traffic.vehicle_count": 0})
    sim = HighwaySim(config, num_arenas=1, agents_per_arena=2)
    sim.reset(seeds=[0])
    place(sim, 0, x=0.0, lane=2, speed_kmh=60.0)
    place(sim, 1, x=-20.0, lane=2, speed_kmh=60.0)
    obs = sim.observe()
    assert obs["lidar"].shape == (1, 2, 360) and obs["camera"].shape == (1, 2, H, W)
    front, back = obs["lidar"][0, 0], obs["lidar"][0, 1]
    assert front[180] == pytest.approx(20.0 - HALF_LENGTH) and front[0] == MAX_RANGE
    assert back[0] == pytest.approx(20.0 - HALF_LENGTH) and back[180] == MAX_RANGE
    # Only the one behind has a car in view.
    assert not (obs["camera"][0, 0] == CAR_GREY).any()
    assert (obs["camera"][0, 1] == CAR_GREY).any()
