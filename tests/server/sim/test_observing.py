"""A trainer asks for the observations it reads (protocol 1.10, ``OpenRequest.observations``)
and the simulator renders no other sensor: the request is typed, not ``<sensor>.enabled``
overrides, and it can only switch sensors off."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.protocol import errors
from overtake.server.engine.env import HighwayVectorEnv
from overtake.server.service.groups import Group
from overtake.server.sim import PRESETS, ConfigError, HighwaySim, make_config

QUIET = {"traffic.vehicle_count": 4, "episode.max_decisions": 20}


def make_sim(config) -> HighwaySim:
    sim = HighwaySim(config, num_arenas=2)
    sim.reset(seeds=[3, 4])
    return sim


def test_each_sensor_section_names_the_observation_its_sensor_makes():
    for preset in PRESETS:
        config = make_config(preset)
        for name, section in config.sensor_sections().items():
            assert section.build(config).key == section.OBSERVATION, (preset, name)


def test_only_the_observations_asked_for_are_rendered_and_the_road_is_the_same():
    config = make_config("min2018", QUIET)
    assert {"camera", "lidar", "ego"} <= set(make_sim(config).observe())
    lean = config.observing(("ego", "lidar"))
    assert not lean.camera.enabled and lean.lidar.enabled and lean.ego_vector.enabled
    full_sim, lean_sim = make_sim(config), make_sim(lean)
    actions = np.random.default_rng(0).integers(0, 5, (15, 2, 1))
    for step in actions:
        full_sim.step(step)
        lean_sim.step(step)
        full, lean_obs = full_sim.observe(), lean_sim.observe()
        assert set(lean_obs) == {"ego", "lidar"}
        for key in lean_obs:  # the sensors left on see what they saw with every sensor on
            np.testing.assert_array_equal(lean_obs[key], full[key])
    assert config.observing(()) is config


def test_an_observation_whose_sensor_is_off_is_refused_naming_those_that_are_on():
    with pytest.raises(ConfigError, match=r"\['grid'\] are not observed by preset min2018.*"):
        make_config("min2018").observing(("ego", "grid"))
    with pytest.raises(ConfigError, match="it observes"):
        make_config("min2018", {"camera.enabled": False}).observing(("camera",))


def test_an_in_process_environment_and_a_server_group_take_the_request():
    envs = HighwayVectorEnv(2, "min2018", QUIET, observations=("ego", "lidar"))
    try:
        assert set(envs.single_observation_space.spaces) == {"ego", "lidar"}
        obs, _ = envs.reset(seed=1)
        assert set(obs) == {"ego", "lidar"}
    finally:
        envs.close()
    group = Group.open(0, "srv", [0], "min2018", dict(QUIET), 1, seed=1, observations=("camera",))
    assert [o.name for o in group.spec.observations] == ["camera"]
    with pytest.raises(errors.BadConfig, match="not observed by preset min2018"):
        Group.open(0, "srv", [0], "min2018", {}, 1, seed=1, observations=("kinematics",))


def test_a_record_made_with_sensors_off_replays_with_them_off():
    """A record keeps the configuration it was made on, sensors a trainer did not ask for off
    among it; the simulator builds it again with them off. A sensor on in the record and off
    now is a difference, as any other."""
    from overtake.server.sim import settings_history
    from overtake.server.sim.config import as_json

    lean = make_config("min2018").observing(("ego", "lidar"))
    again = settings_history.as_recorded("min2018", {}, as_json(lean))
    assert again == lean and not again.camera.enabled
    with pytest.raises(ConfigError, match="camera.enabled: True in the record, False now"):
        settings_history.as_recorded(
            "min2018", {"camera.enabled": False}, as_json(make_config("min2018"))
        )


def test_the_ego_fields_a_trainer_reads_are_asked_for_by_the_request():
    """Protocol 1.11 (``OpenRequest.ego_fields``): the camera-only network's ego vector of the
    car's speed alone, asked for by a typed field in process and of a server's group; an
    unknown field, an ego vector that is off, or an override that says otherwise is refused
    by name; a record made with them replays with them."""
    from overtake.server.sim import settings_history
    from overtake.server.sim.config import as_json

    envs = HighwayVectorEnv(2, "min2018", QUIET, ego_fields=("speed_mps",))
    try:
        assert envs.single_observation_space["ego"].shape == (1,)
        assert envs.behaviour_spec.observation("ego").columns == ("speed_mps",)
    finally:
        envs.close()
    group = Group.open(0, "srv", [0], "min2018", dict(QUIET), 1, seed=1, ego_fields=("lane_index",))
    assert group.spec.observation("ego").columns == ("lane_index",)
    with pytest.raises(errors.BadConfig, match=r"ego_vector.fields .* distinct names from"):
        Group.open(0, "srv", [0], "min2018", {}, 1, seed=1, ego_fields=("speed",))
    with pytest.raises(errors.BadConfig, match="observes no ego vector"):
        Group.open(0, "srv", [0], "highway-fast", {}, 1, seed=1, ego_fields=("speed_mps",))
    with pytest.raises(ConfigError, match="one or the other"):
        settings_history.requested_config(
            "min2018", {"ego_vector.fields": ["lane_index"]}, ego_fields=("speed_mps",)
        )
    speed_only = make_config("min2018").reading_ego_fields(("speed_mps",))
    again = settings_history.as_recorded("min2018", {}, as_json(speed_only))
    assert again == speed_only
