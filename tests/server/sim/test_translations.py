"""A configuration in another simulator's words, translated beside its scene (issue 70,
``OpenRequest.translation``): highway-env's config dict as the simulator's settings, the
scene's own defaults read from its preset, and every refusal naming what was expected and
what came."""

from __future__ import annotations

import json

import pytest

from overtake.protocol.messages import Translation
from overtake.protocol.vocabulary import HIGHWAY_ENV_FACE_KEYS
from overtake.server.engine.requested import resolve_config
from overtake.server.sim import ConfigError, make_config
from overtake.server.sim.translations import translate


def test_highway_env_s_config_becomes_the_settings_of_its_scene():
    config = {"duration": 20, "observation": {"features": ["presence", "x"]}}
    translated = translate("highway-env", "highway", json.dumps(config))
    assert translated.overrides == {
        "episode.frames_per_decision": 15,  # the preset's own rate, read from it
        "episode.physics_dt_s": 1.0 / 15,
        "episode.max_decisions": 20,
        "kinematics.features": ["presence", "x"],
    }
    # Defaults only: the scene as its preset has it.
    again = translate("highway-env", "highway-fast", "{}").overrides
    assert make_config("highway-fast", again) == make_config("highway-fast")
    # The face's keys are known and left to the face.
    face = dict.fromkeys(HIGHWAY_ENV_FACE_KEYS, 1)
    assert not set(translate("highway-env", "highway", json.dumps(face)).overrides) & set(face)


def test_a_translation_that_cannot_be_made_says_what_was_expected_and_what_came():
    with pytest.raises(ConfigError, match="unknown translation 'carla': expected one of"):
        translate("carla", "highway", "{}")
    with pytest.raises(ConfigError, match="configuration is not JSON"):
        translate("highway-env", "highway", "{lanes")
    with pytest.raises(ConfigError, match="is a dict of its keys, got list"):
        translate("highway-env", "highway", "[3]")
    with pytest.raises(ConfigError, match="for its scenes, .* not preset min2018"):
        translate("highway-env", "min2018", "{}")
    with pytest.raises(ConfigError, match=r"features_range'\]: unknown key 'speed'"):
        translate("highway-env", "highway", '{"observation": {"features_range": {"speed": 1}}}')
    # A server says the same, in the user's words, as a protocol error.
    request = Translation("highway-env", json.dumps({"vehicles_count": -1}))
    with pytest.raises(ConfigError, match=r"config\['vehicles_count'\] = -1"):
        resolve_config("highway-fast", {}, translation=request)
