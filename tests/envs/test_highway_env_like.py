"""A highway-env script's ``config`` on overtake's highway-env ids (issue 67): every key of
highway-env 1.12.1's own default configurations taken, each refusal a ``BadConfig`` (a
``ValueError``) in the user's words, the action subsets and the viewer's framing honoured."""

from __future__ import annotations

import json
import warnings

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the ids)
from overtake.envs import highway_env_config
from overtake.envs.highway_env_config import read_config
from overtake.protocol.errors import BadConfig, ProtocolError
from overtake.protocol.vocabulary import HIGHWAY_ENV_FACE_ACTION_KEYS, HIGHWAY_ENV_FACE_KEYS
from overtake.server.sim import ConfigError
from overtake.server.sim.highway_scene.config import HighwaySceneConfig


def test_one_error_type_for_a_configuration_mistake():
    # The simulator's ConfigError is the protocol's BadConfig: one class, a ValueError and a
    # ProtocolError, whichever path finds the mistake.
    assert ConfigError is BadConfig
    assert issubclass(BadConfig, ValueError) and issubclass(BadConfig, ProtocolError)
    with pytest.raises(BadConfig, match="unknown preset 'nope'"):
        gym.make("overtake/Highway-v0", preset="nope")


@pytest.mark.parametrize(
    ("env_id", "scene_class"),
    [("overtake/highway-fast-v0", "HighwayEnvFast"), ("overtake/highway-v0", "HighwayEnv")],
)
def test_highway_env_s_own_default_config_is_taken(env_id, scene_class):
    highway_env = pytest.importorskip("highway_env", reason="highway-env is in the dev extra")
    default = getattr(highway_env.envs.highway_env, scene_class).default_config()
    # Every key of the scene's own configuration, rendering and action included.
    assert {"action", "screen_width", "scaling", "manual_control"} <= set(default)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # highway-env's defaults are not even said
        env = gym.make(env_id, config=default, render_mode="rgb_array")
    env.reset(seed=0)
    inner = env.unwrapped.env.config
    assert inner.road.lane_count == default["lanes_count"]
    assert inner.traffic.resolved_vehicle_count == default["vehicles_count"]
    assert inner.episode.max_decisions == default["duration"]
    assert env.action_space.n == 5
    picture = env.render()
    assert picture.shape == (default["screen_height"], default["screen_width"], 3)
    env.close()


def test_action_target_speeds_and_subsets():
    env = gym.make(
        "overtake/highway-fast-v0",
        config={
            "observation": {"type": "Kinematics"},
            "action": {"type": "DiscreteMetaAction", "target_speeds": [15, 20, 25, 30]},
        },
    )
    assert env.unwrapped.env.config.highway_scene.target_speeds_mps == (15.0, 20.0, 25.0, 30.0)
    env.close()
    # longitudinal only: highway-env's ACTIONS_LONGI, 0 SLOWER 1 IDLE 2 FASTER.
    env = gym.make(
        "overtake/highway-fast-v0",
        config={"action": {"type": "DiscreteMetaAction", "lateral": False}},
    )
    assert env.action_space == gym.spaces.Discrete(3)
    _, info = env.reset(seed=3)
    assert info["action_mask"].shape == (3,)
    _, _, _, _, info = env.step(2)
    assert info["action_applied"] == 1  # overtake's cruise up: FASTER
    with pytest.raises(ValueError, match=r"\[0, 3\) \(0 SLOWER, 1 IDLE, 2 FASTER\), got 3"):
        env.step(3)
    env.close()
    lateral = read_config({"action": {"longitudinal": False}})
    assert lateral.actions == ("LANE_LEFT", "IDLE", "LANE_RIGHT")
    assert lateral.to_overtake.tolist() == [3, 0, 4]
    with pytest.raises(BadConfig, match="both false, expected at least one"):
        read_config({"action": {"longitudinal": False, "lateral": False}})
    with pytest.raises(
        BadConfig, match=r"config\['action'\] is a dict .* got 'DiscreteMetaAction'"
    ):
        read_config({"action": "DiscreteMetaAction"})
    # The simulator's translation refuses what the scene does not take.
    with pytest.raises(BadConfig, match="ContinuousAction"):
        gym.make("overtake/highway-v0", config={"action": {"type": "ContinuousAction"}})


def test_the_viewer_s_keys_frame_the_picture_and_the_others_are_said_once(monkeypatch):
    monkeypatch.setattr(highway_env_config, "_SAID", set())
    config = {
        "screen_width": 200,
        "screen_height": 80,
        "scaling": 2.0,
        "centering_position": [0.5, 0.5],
    }
    env = gym.make("overtake/highway-fast-v0", config=config, render_mode="rgb_array")
    env.reset(seed=0)
    picture = env.render()
    assert picture.shape == (80, 200, 3)
    # The car (red, the agent's colour) covers the middle pixel at this centring.
    red = np.all(picture == picture[40, 100], axis=-1)
    assert red[40, 100] and red.sum() == pytest.approx(5 * 2 * 2.0**2, rel=0.6)
    env.close()
    with pytest.warns(UserWarning, match=r"show_trajectories, manual_control have no effect"):
        gym.make(
            "overtake/highway-fast-v0", config={"show_trajectories": True, "manual_control": True}
        ).close()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # said once in a process
        gym.make("overtake/highway-fast-v0", config={"show_trajectories": True}).close()
    with pytest.raises(BadConfig, match=r"config\['screen_width'\] = -3 .* a positive integer"):
        read_config({"screen_width": -3})


def test_a_refused_value_names_the_key_given():
    with pytest.raises(BadConfig) as refused:
        gym.make("overtake/highway-fast-v0", config={"lanes_count": "four"})
    assert str(refused.value).startswith("config['lanes_count'] = 'four' is not allowed")
    assert "overtake's road.lane_count" in str(refused.value)
    with pytest.raises(BadConfig, match=r"config\['action'\]\['target_speeds'\]"):
        gym.make_vec(
            "overtake/highway-fast-v0", num_envs=2, config={"action": {"target_speeds": [30, 20]}}
        )
    assert HighwaySceneConfig().target_speeds_mps == (20.0, 25.0, 30.0)


def test_preset_on_a_highway_env_id_and_a_dict_for_a_sim_config_are_refused_in_one_line():
    with pytest.raises(
        BadConfig, match=r"preset='min2018' is not taken by overtake/highway-fast-v0"
    ):
        gym.make("overtake/highway-fast-v0", preset="min2018")
    with pytest.raises(BadConfig, match="preset='highway'") as refused:
        gym.make_vec("overtake/highway-fast-v0", num_envs=2, preset="highway")
    assert "\n" not in str(refused.value)
    with pytest.raises(BadConfig, match="config= takes a SimConfig .* got a dict: highway-env's"):
        gym.make("overtake/Highway-v0", preset="highway-fast", config={"lanes_count": 3})


def test_the_face_reads_the_keys_the_contract_leaves_to_it_and_sends_the_rest():
    # The simulator's translation leaves these to the face, and the face reads them all.
    assert set(highway_env_config.VIEW_KEYS) | set(highway_env_config.NO_EFFECT_KEYS) == set(
        HIGHWAY_ENV_FACE_KEYS
    )
    assert HIGHWAY_ENV_FACE_ACTION_KEYS == ("longitudinal", "lateral")
    # The whole configuration travels in highway-env's words, numpy's values as JSON's.
    read = read_config({"lanes_count": np.int64(3), "action": {"target_speeds": np.arange(2)}})
    assert read.translation.source == "highway-env"
    assert json.loads(read.translation.config_json) == {
        "lanes_count": 3,
        "action": {"target_speeds": [0, 1]},
    }
    with pytest.raises(BadConfig, match="expected highway-env's plain values"):
        read_config({"observation": {"features": {"x", "y"}}})
