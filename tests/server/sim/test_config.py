"""Configuration: presets, dotted overrides, validation messages, immutability."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from overtake.server.sim import (
    PRESETS,
    ConfigError,
    HighwaySim,
    SimConfig,
    apply_overrides,
    make_config,
)
from overtake.server.sim.config import field_names


def test_unknown_preset_is_refused_naming_it_and_the_presets():
    with pytest.raises(ConfigError) as err:
        make_config("nope")
    message = str(err.value)
    assert "'nope'" in message
    for name in PRESETS:
        assert name in message


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


def test_default_preset_is_min2018_with_the_papers_numbers():
    config = make_config()
    assert config.preset == "min2018"
    assert config.road.lane_count == 5
    assert (config.ego.cruise_min_kmh, config.ego.cruise_max_kmh) == (40.0, 80.0)
    assert config.lidar.ray_count == 360 and config.lidar.max_range_m == 80.0
    assert (config.camera.width_px, config.camera.height_px) == (80, 80)
    assert not config.camera.rgb
    assert config.episode.decision_period_s == pytest.approx(0.4)
    assert config.reward.collision == -10.0 and config.reward.lane_change == -0.25
    assert config.reward.overtake == 0.5 and config.reward.warning == -0.1
    assert config.reward.terms == ("speed", "collision", "lane_change", "overtake", "warning")
    # Actions set cruise control from the current speed; the car refuses a lane change under a
    # side warning (the authors' DAS), and the mask leaves that refusal to the car.
    assert config.ego.cruise_mode == "current" and config.ego.lane_change_check
    assert not config.ego.mask_refusals
    # Episodes end at 2,600 m (the authors' code), or after 1,000 decisions.
    assert config.episode.max_distance_m == 2600.0 and config.episode.max_decisions == 1000
    assert config.ego_vector.fields == (
        "left_warning",
        "right_warning",
        "forward_warning",
        "ahead_distance_m",
        "ahead_speed_mps",
        "speed_mps",
    )
    # At most 32 traffic cars (the authors' slider), all of Min et al.'s random kind.
    assert config.traffic.density_vehicle_counts == (10, 20, 32)
    assert config.traffic.random.share == 1.0
    assert all(
        getattr(config.traffic, name).share == 0.0
        for name in ("steady", "road_max", "lane_changer")
    )


@pytest.mark.parametrize(
    "dotted, parent_fields",
    [
        ("road.nope", ["lane_count", "lane_width_m", "barrier_offset_m"]),
        # The top level's many names: the first few, and how many more.
        ("nope", ["road.lane_count", "traffic.density", "more)"]),
        ("traffic.steady.nope", ["share", "desired_speed_kmh", "politeness"]),
    ],
)
def test_unknown_field_is_refused_naming_it_and_listing_the_fields(dotted, parent_fields):
    with pytest.raises(ConfigError) as err:
        make_config(overrides={dotted: 1})
    message = str(err.value)
    assert repr(dotted) in message
    for name in parent_fields:
        assert name in message


def test_sub_field_of_a_leaf_is_refused():
    with pytest.raises(ConfigError, match="road.lane_count.x"):
        make_config(overrides={"road.lane_count.x": 1})


def test_a_group_cannot_be_set_as_a_value():
    with pytest.raises(ConfigError) as err:
        make_config(overrides={"road": 3})
    assert "road.lane_count" in str(err.value)


@pytest.mark.parametrize(
    "dotted, value, expected",
    [
        ("road.lane_count", 0, "an integer from 1 to 12"),
        ("road.lane_count", 13, "an integer from 1 to 12"),
        ("road.lane_count", 3.0, "an integer"),
        ("road.lane_count", True, "an integer"),
        ("traffic.density", "jammed", "['light', 'medium', 'heavy']"),
        ("road.lane_width_m", "wide", "a number"),
        ("road.lane_width_m", 1.0, ">= 2.5"),
        ("lidar.enabled", 1, "true or false"),
        ("traffic.vehicle_count", -1, "None or an integer from 0 to 200"),
        ("traffic.spawn_ahead_m", [90.0, 30.0], "min <= max"),
        ("traffic.spawn_ahead_m", [1.0, 2.0, 3.0], "a list of 2 values"),
        ("ego.cruise_max_kmh", 30.0, ">= 40.0"),
        ("camera.width_px", 4, "an integer from 8 to 1024"),
        ("episode.max_decisions", 0, "an integer >= 1"),
        ("episode.physics_dt_s", float("nan"), "a finite number"),
    ],
)
def test_bad_value_is_refused_naming_the_field_and_what_is_allowed(dotted, value, expected):
    with pytest.raises(ConfigError) as err:
        make_config(overrides={dotted: value})
    message = str(err.value)
    assert message.startswith(dotted), message
    assert expected in message
    assert "expected" in message


def test_disabling_every_sensor_is_refused_naming_them():
    with pytest.raises(ConfigError, match="at least one sensor") as err:
        make_config(
            overrides={"lidar.enabled": False, "camera.enabled": False, "ego_vector.enabled": False}
        )
    assert "lidar.enabled / camera.enabled / ego_vector.enabled" in str(err.value)


def test_the_observation_holds_the_enabled_sensors_in_order():
    config = make_config(overrides={"camera.enabled": False})
    assert [key for key, section in config.sensor_sections().items() if section.enabled] == [
        "lidar",
        "ego_vector",
    ]
    sim = HighwaySim(make_config(overrides={"lidar.enabled": False}))
    assert list(sim.observation_spaces()) == ["camera", "ego"]


def test_reward_terms_are_the_presets_list_in_its_order():
    config = make_config(overrides={"reward.terms": ["overtake", "speed"]})
    sim = HighwaySim(config)
    sim.reset(seeds=[0])
    result = sim.step(np.zeros((1, 1), dtype=np.int64))
    assert list(result.reward_terms) == ["overtake", "speed"]
    assert float(result.reward[0, 0]) == float(
        result.reward_terms["overtake"][0, 0] + result.reward_terms["speed"][0, 0]
    )
    for bad in (["speed", "speed"], [], ["speed", "comfort"]):
        with pytest.raises(ConfigError, match="reward.terms"):
            make_config(overrides={"reward.terms": bad})


def test_nested_overrides_apply_and_leave_everything_else():
    base = make_config()
    config = make_config(
        overrides={
            "road.lane_count": 7,
            "traffic.density": "heavy",
            "traffic.road_max.desired_speed_kmh": [60, 70],
            "camera.rgb": True,
            "traffic.vehicle_count": 12,
            "reward.lane_change": -1,
        }
    )
    assert config.road.lane_count == 7
    assert config.traffic.density == "heavy"
    assert config.traffic.road_max.desired_speed_kmh == (60.0, 70.0)
    assert isinstance(config.traffic.road_max.desired_speed_kmh[0], float)
    assert config.camera.rgb is True
    assert config.traffic.resolved_vehicle_count == 12
    assert config.reward.lane_change == -1.0 and isinstance(config.reward.lane_change, float)
    # Untouched fields keep the preset's values, and the preset itself is unchanged.
    assert config.road.lane_width_m == base.road.lane_width_m
    assert config.traffic.steady == base.traffic.steady
    assert config.traffic.road_max.share == base.traffic.road_max.share
    assert base.road.lane_count == 5 and base.camera.rgb is False


def test_apply_overrides_returns_a_copy():
    base = make_config()
    changed = apply_overrides(base, {"episode.max_decisions": 20})
    assert changed.episode.max_decisions == 20
    assert base.episode.max_decisions == 1000
    assert apply_overrides(base, {}) == base


def test_later_overrides_win_and_none_is_allowed_where_typed():
    config = make_config(overrides={"traffic.vehicle_count": 3})
    assert config.traffic.resolved_vehicle_count == 3
    config = apply_overrides(config, {"traffic.vehicle_count": None, "traffic.density": "light"})
    assert config.traffic.vehicle_count is None
    assert config.traffic.resolved_vehicle_count == config.traffic.density_vehicle_counts[0]


def test_density_sets_the_vehicle_count():
    counts = {
        d: make_config(overrides={"traffic.density": d}).traffic.resolved_vehicle_count
        for d in ("light", "medium", "heavy")
    }
    assert counts == {"light": 10, "medium": 20, "heavy": 32}
    ho_counts = make_config(
        overrides={"traffic.density_vehicle_counts": [20, 40, 60], "traffic.density": "heavy"}
    ).traffic.resolved_vehicle_count
    assert ho_counts == 60


def test_every_field_name_can_be_overridden_with_its_own_value():
    config = make_config()
    for dotted in field_names(config):
        value = config
        for part in dotted.split("."):
            value = getattr(value, part)
        plain = list(value) if isinstance(value, tuple) else value
        assert apply_overrides(config, {dotted: plain}) == config, dotted


def test_configs_are_frozen():
    config = make_config()
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.road = config.road  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.road.lane_count = 7  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.traffic.steady.share = 0.9  # type: ignore[misc]
    assert isinstance(config, SimConfig)
    hash(config)  # frozen dataclasses of tuples and scalars hash
