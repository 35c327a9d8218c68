"""The vector environment: N arenas in one pass, equal to N single environments."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401
from overtake.envs import HIGHWAY_ENV_ID
from overtake.protocol.vocabulary import EGO_FIELDS, METRIC_FIELDS
from overtake.server.engine.env import HighwayEnv, HighwayVectorEnv

NUM = 4
OVERRIDES = {"episode.max_decisions": 15, "traffic.density": "heavy"}


def make_vec(num_envs: int = NUM, **overrides):
    return gym.make_vec(
        HIGHWAY_ENV_ID,
        num_envs=num_envs,
        vectorization_mode="vector_entry_point",
        overrides={**OVERRIDES, **overrides},
    )


def test_make_vec_builds_the_numpy_vector_env():
    envs = make_vec()
    assert isinstance(envs.unwrapped, HighwayVectorEnv)
    assert envs.num_envs == NUM
    assert envs.single_action_space == gym.spaces.Discrete(5)
    assert envs.action_space == gym.spaces.MultiDiscrete([5] * NUM)
    obs, info = envs.reset(seed=0)
    assert obs["lidar"].shape == (NUM, 360) and obs["camera"].shape == (NUM, 80, 80)
    assert obs["ego"].shape == (NUM, 6)
    assert envs.observation_space.contains(obs)
    assert info["action_mask"].shape == (NUM, 5)
    assert envs.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP


def test_vector_env_matches_single_envs_step_by_step_across_episode_ends():
    steps = 70
    seed = 40
    envs = make_vec()
    singles = [HighwayEnv(overrides=OVERRIDES) for _ in range(NUM)]
    rng = np.random.default_rng(5)

    obs, info = envs.reset(seed=seed)  # arena i gets seed + i
    single_obs = [env.reset(seed=seed + i) for i, env in enumerate(singles)]
    for i, (o, single_info) in enumerate(single_obs):
        for key in o:
            assert np.array_equal(obs[key][i], o[key]), key
        assert np.array_equal(info["action_mask"][i], single_info["action_mask"])

    ended = np.zeros(NUM, dtype=bool)
    autoresets = terminations = truncations = 0
    for step in range(steps):
        actions = rng.integers(0, 5, size=NUM)
        obs, reward, terminated, truncated, info = envs.step(actions)
        for i, env in enumerate(singles):
            if ended[i]:
                # Next-step autoreset: a new episode, the action ignored, reward 0, no flags.
                o, single_info = env.reset()
                r, term, trunc = 0.0, False, False
                assert info["action_applied"][i] == -1
                autoresets += 1
            else:
                o, r, term, trunc, single_info = env.step(int(actions[i]))
                assert info["action_applied"][i] == single_info["action_applied"]
                for name, value in single_info["reward_terms"].items():
                    assert info["reward_terms"][name][i] == value
            for key in o:
                assert np.array_equal(obs[key][i], o[key]), (step, i, key)
            assert reward[i] == r, (step, i)
            assert terminated[i] == term and truncated[i] == trunc, (step, i)
            assert np.array_equal(info["action_mask"][i], single_info["action_mask"])
            if term or trunc:
                assert info["_metrics"][i]
                for name in METRIC_FIELDS:
                    assert info["metrics"][name][i] == single_info["metrics"][name], name
            elif "_metrics" in info:
                assert not info["_metrics"][i]
                assert all(info["metrics"][name][i] == 0.0 for name in METRIC_FIELDS)
        terminations += int(terminated.sum())
        truncations += int(truncated.sum())
        ended = terminated | truncated
        assert ("metrics" in info) == bool(ended.any())
    assert truncations >= NUM * 3
    assert autoresets >= NUM * 3


def test_autoreset_step_ignores_the_action_and_returns_zero_reward():
    envs = make_vec(
        num_envs=2,
        **{
            "traffic.vehicle_count": 0,
            "episode.max_decisions": 3,
            # The first six fields: speed, cruise target, lane, lanes, change progress, direction.
            "ego_vector.fields": list(EGO_FIELDS[:6]),
        },
    )
    obs, _ = envs.reset(seed=[1, 2])
    for _ in range(3):
        obs, reward, terminated, truncated, info = envs.step(np.array([1, 0]))
    assert truncated.tolist() == [True, True] and not terminated.any()
    assert info["_metrics"].tolist() == [True, True]
    assert info["metrics"]["decisions"].tolist() == [3, 3]
    final_speed = obs["ego"][:, 1].copy()
    assert final_speed[0] > final_speed[1]  # arena 0 raised its cruise target
    # The autoreset step: a lane change requested in both arenas is not applied.
    obs, reward, terminated, truncated, info = envs.step(np.array([3, 4]))
    assert reward.tolist() == [0.0, 0.0]
    assert not terminated.any() and not truncated.any()
    assert "metrics" not in info
    assert info["action_applied"].tolist() == [-1, -1]
    assert obs["ego"][:, 4].tolist() == [0.0, 0.0]  # no lane change under way
    assert obs["ego"][:, 5].tolist() == [0.0, 0.0]
    assert np.allclose(obs["ego"][:, 1], 60.0 / 3.6)  # fresh episodes at the initial cruise
    assert all(v == 0.0 for v in info["reward_terms"]["lane_change"])
    # The next step acts again.
    obs, reward, *_, info = envs.step(np.array([1, 1]))
    assert (reward > 0).all()
    assert info["action_applied"].tolist() == [1, 1]


def test_arenas_ending_at_different_times_reset_independently():
    envs = HighwayVectorEnv(
        num_envs=3, overrides={"traffic.vehicle_count": 0, "episode.max_decisions": 4}
    )
    envs.reset(seed=0)
    # Put arena 1 one decision behind the others by restarting its episode in the core.
    envs.step(np.zeros(3, dtype=np.int64))
    envs.sim.reset([1])
    flags = []
    for _ in range(6):
        _, _, _, truncated, info = envs.step(np.zeros(3, dtype=np.int64))
        flags.append(truncated.tolist())
        if truncated.any():
            assert info["_metrics"].tolist() == truncated.tolist()
    assert flags[2] == [True, False, True]
    assert flags[3] == [False, True, False]


def test_vector_seeds_and_render():
    envs = HighwayVectorEnv(num_envs=2, render_mode="rgb_array")
    obs_a, _ = envs.reset(seed=[5, 5])
    for key in obs_a:
        assert np.array_equal(obs_a[key][0], obs_a[key][1])
    obs_b, _ = envs.reset(seed=5)  # seeds 5 and 6
    assert np.array_equal(obs_b["lidar"][0], obs_a["lidar"][0])
    assert not np.array_equal(obs_b["lidar"][1], obs_a["lidar"][1])
    frames = envs.render()
    assert len(frames) == 2 and all(f.ndim == 3 and f.dtype == np.uint8 for f in frames)
    with pytest.raises(ValueError, match="expected 2 seeds"):
        envs.reset(seed=[1, 2, 3])


@pytest.mark.parametrize(
    "actions", [np.array([0, 5]), np.array([-1, 0]), np.array([0.0, 1.0]), np.array([0, 1, 2])]
)
def test_vector_env_refuses_bad_actions(actions):
    envs = HighwayVectorEnv(num_envs=2)
    envs.reset(seed=0)
    with pytest.raises(ValueError, match=r"\[0, 5\)"):
        envs.step(actions)
