"""highway-env's ids against a real server (issue 70): ``config={...}`` is translated by the
simulator beside its scene, asked for by name in the open request, so that
``overtake/highway-fast-v0`` with highway-env's observation settings gives on a server exactly
what it gives in process, observations, rewards, flags and info (its speed read back by the
scales the observation's spec carries), and a key or value the translation refuses is said in
the same words either way.

The server is ``python -m overtake.server`` on 127.0.0.1 and a free port, stopped by its PID
(``tests/support/remote.py``).
"""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.client.wire.remote import ArenaGroup
from overtake.protocol.errors import BadConfig, VersionMismatch

from tests.support.same import assert_same

HIGHWAY_FAST = "overtake/highway-fast-v0"
# highway-env's keys as a script gives them: fewer features, other ranges, a longer episode.
CONFIGS = (
    {"observation": {"type": "Kinematics", "features": ["presence", "x", "y"]}},
    {
        "duration": 12,
        "lanes_count": 4,
        "observation": {
            "type": "Kinematics",
            "vehicles_count": 7,
            "features": ["presence", "x", "y", "vx", "vy", "cos_h"],
            "features_range": {"vx": [-40, 40], "vy": [-10, 10]},
        },
        "action": {"type": "DiscreteMetaAction", "target_speeds": [18, 24, 30]},
    },
)


def _play_both(remote, local, steps: int, seed: int, actions) -> int:
    """Reset both with ``seed`` and play ``steps`` decisions of ``actions(step)``; every
    return equal. The episodes that ended."""
    assert_same(remote.reset(seed=seed), local.reset(seed=seed), "reset")
    ends = 0
    for step in range(steps):
        action = actions(step)
        got, want = remote.step(action), local.step(action)
        assert_same(got, want, f"step {step}")
        ended = np.asarray(want[2]) | np.asarray(want[3])
        if ended.any():
            ends += int(ended.sum())
            if ended.ndim == 0:
                assert_same(remote.reset(), local.reset(), f"reset after step {step}")
    return ends


@pytest.mark.timeout(180)
def test_highway_env_config_works_on_a_server_exactly_as_in_process(start_server):
    server = start_server("e2e-highway-env")
    rng = np.random.default_rng(5)
    for config in CONFIGS:
        remote = gym.make(HIGHWAY_FAST, config=config, connect=server.endpoint)
        local = gym.make(HIGHWAY_FAST, config=config)
        try:
            assert remote.observation_space == local.observation_space
            features = config["observation"]["features"]
            count = config["observation"].get("vehicles_count", 5)
            assert local.observation_space.shape == (count, len(features))
            kinematics = remote.unwrapped.env.behaviour_spec.observation("kinematics")
            assert kinematics == local.unwrapped.env.behaviour_spec.observation("kinematics")
            assert kinematics.columns == tuple(features)
            ends = _play_both(remote, local, 40, 11, lambda _: int(rng.integers(0, 5)))
            assert ends >= 1
        finally:
            remote.close()
            local.close()
    # The second configuration's speed is read back by its own vx and vy ranges.
    local = gym.make(HIGHWAY_FAST, config=CONFIGS[1])
    obs, info = local.reset(seed=3)
    vx, vy = obs[0, 3] * 40.0, obs[0, 4] * 10.0  # ranges symmetric about 0
    assert info["speed"] == pytest.approx(math.hypot(vx, vy), rel=1e-6)
    assert 20.0 <= info["speed"] <= 30.0
    local.close()

    # Vectorised, the same.
    remote_vec = gym.make_vec(HIGHWAY_FAST, num_envs=3, config=CONFIGS[1], connect=server.endpoint)
    local_vec = gym.make_vec(HIGHWAY_FAST, num_envs=3, config=CONFIGS[1])
    try:
        assert remote_vec.single_observation_space == local_vec.single_observation_space
        _play_both(remote_vec, local_vec, 30, 21, lambda _: rng.integers(0, 5, size=3))
    finally:
        remote_vec.close()
        local_vec.close()


@pytest.mark.timeout(120)
def test_a_refused_highway_env_key_is_said_alike_on_a_server(start_server, monkeypatch):
    server = start_server("e2e-highway-env-refusals")
    for config, expected in (
        ({"lanes_cuont": 4}, "unknown key 'lanes_cuont'; did you mean 'lanes_count'?"),
        (
            {"observation": {"features": ["presence", "speed"]}},
            "config['observation']['features'] = ('presence', 'speed') is not allowed: "
            "expected distinct names from",
        ),
        ({"lanes_count": "four"}, "config['lanes_count'] = 'four' is not allowed"),
    ):
        with pytest.raises(BadConfig) as in_process:
            gym.make(HIGHWAY_FAST, config=config)
        with pytest.raises(BadConfig) as remote:
            gym.make(HIGHWAY_FAST, config=config, connect=server.endpoint)
        assert expected in str(in_process.value)
        assert str(in_process.value) in str(remote.value)
    assert server.status().arenas_used == 0  # nothing was opened

    # A 1.10 server would ignore the translation and open the scene as its preset has it:
    # refused, naming the versions, and its arenas freed.
    original_open = ArenaGroup._open

    def as_if_1_10(self, reseed=True):
        original_open(self, reseed)
        self.server_minor = 10

    monkeypatch.setattr(ArenaGroup, "_open", as_if_1_10)
    with pytest.raises(VersionMismatch, match=r"speaks protocol 1\.10; .* need 1\.11 .* upgrade"):
        gym.make(HIGHWAY_FAST, config=CONFIGS[0], connect=server.endpoint)
    assert server.status().arenas_used == 0
