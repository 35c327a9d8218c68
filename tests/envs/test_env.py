"""The single-agent Gymnasium environment: API, registration, episode length, determinism."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import overtake.client  # noqa: F401  (registers overtake/Highway-v0)
from overtake.envs import HIGHWAY_ENV_ID
from overtake.server.engine.env import HighwayEnv
from overtake.server.sim import ConfigError, make_config

FREE_ROAD = {"traffic.vehicle_count": 0}


def run_python(code: str) -> subprocess.CompletedProcess:
    """Run ``code`` in a fresh interpreter (nothing imported yet) and return the result."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=120
    )


def assert_same_observation(a: dict, b: dict) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert a[key].dtype == b[key].dtype
        assert np.array_equal(a[key], b[key]), key


# --- Gymnasium API ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"render_mode": "rgb_array"}, {"overrides": {"camera.rgb": True, "lidar.enabled": False}}],
)
def test_check_env_passes(kwargs):
    with warnings.catch_warnings():
        # Made directly, the env has no spec for the checker to try other render modes with.
        warnings.filterwarnings("ignore", message=".*alternative render modes.*")
        check_env(HighwayEnv(**kwargs))
    check_env(gym.make(HIGHWAY_ENV_ID, **kwargs).unwrapped)


def test_spaces_and_observations():
    env = HighwayEnv()
    assert env.action_space == gym.spaces.Discrete(5)
    assert set(env.observation_space.spaces) == {"lidar", "camera", "ego"}
    assert env.observation_space["lidar"].shape == (360,)
    assert env.observation_space["camera"].shape == (80, 80)
    assert env.observation_space["ego"].shape == (6,)
    obs, info = env.reset(seed=0)
    assert obs["lidar"].dtype == np.float32 and obs["camera"].dtype == np.uint8
    assert info["action_mask"].dtype == np.int8 and info["action_mask"].shape == (5,)
    assert info["action_applied"] == -1
    rng = np.random.default_rng(0)
    for _ in range(30):
        obs, reward, terminated, truncated, info = env.step(int(rng.integers(5)))
        assert env.observation_space.contains(obs)
        assert isinstance(reward, float) and isinstance(terminated, bool)
        assert np.array_equal(info["action_mask"], env.action_masks())
        if terminated or truncated:
            env.reset()
    assert env.decision_period_s == pytest.approx(0.4)


def test_observation_space_follows_overrides():
    env = HighwayEnv(
        overrides={
            "camera.rgb": True,
            "camera.width_px": 32,
            "camera.height_px": 24,
            "lidar.ray_count": 90,
        }
    )
    obs, _ = env.reset(seed=0)
    assert env.observation_space["camera"].shape == (24, 32, 3)
    assert obs["camera"].shape == (24, 32, 3)
    assert obs["lidar"].shape == (90,)
    env = HighwayEnv(overrides={"camera.enabled": False})
    assert set(env.reset(seed=0)[0]) == {"lidar", "ego"}


def test_gym_make_after_importing_the_client():
    env = gym.make(HIGHWAY_ENV_ID)
    assert HIGHWAY_ENV_ID == "overtake/Highway-v0"
    assert isinstance(env.unwrapped, HighwayEnv)
    assert env.unwrapped.config == make_config()
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)
    env.step(0)
    env = gym.make(HIGHWAY_ENV_ID, preset="min2018", overrides={"traffic.density": "heavy"})
    assert env.unwrapped.config.traffic.density == "heavy"


def test_gym_make_refuses_bad_configuration():
    with pytest.raises(ConfigError, match="unknown preset 'nope'"):
        gym.make(HIGHWAY_ENV_ID, preset="nope")
    with pytest.raises(ConfigError, match="road.lane_count"):
        gym.make(HIGHWAY_ENV_ID, overrides={"road.lane_count": 0})
    with pytest.raises(ValueError, match="either a config or a preset"):
        HighwayEnv(overrides=FREE_ROAD, config=make_config())
    with pytest.raises(ValueError, match="render_mode"):
        HighwayEnv(render_mode="human")


def test_explicit_config_is_used():
    config = make_config(
        overrides={"road.lane_count": 3, "ego_vector.fields": ["lane_count"], **FREE_ROAD}
    )
    env = HighwayEnv(config=config)
    obs, _ = env.reset(seed=0)
    assert env.config is config
    assert obs["ego"].tolist() == [3.0]


def test_module_colon_id_imports_what_it_needs():
    result = run_python("""
        import gymnasium as gym
        env = gym.make("overtake.client:overtake/Highway-v0")
        obs, info = env.reset(seed=0)
        obs, *_ = env.step(1)
        print(type(env.unwrapped).__name__, obs["lidar"].shape)
    """)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["HighwayEnv", "(360,)"]


def test_importing_the_client_does_not_import_the_simulator():
    result = run_python("""
        import sys
        import overtake.client
        import gymnasium as gym
        assert "overtake/Highway-v0" in gym.registry
        print(sorted(m for m in sys.modules if m.startswith("overtake.server")))
    """)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"
    # ...while making an environment does import it.
    result = run_python("""
        import sys
        import gymnasium as gym
        import overtake.client
        gym.make("overtake/Highway-v0")
        print("overtake.server.sim" in sys.modules)
    """)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "True"


# --- episode length --------------------------------------------------------------------------


def test_spec_reports_the_presets_episode_length():
    env = gym.make(HIGHWAY_ENV_ID)
    assert env.spec.max_episode_steps == make_config().episode.max_decisions == 1000
    assert env.unwrapped.spec.max_episode_steps == 1000
    env = gym.make(HIGHWAY_ENV_ID, overrides={"episode.max_decisions": 37})
    assert env.spec.max_episode_steps == 37
    assert env.unwrapped.max_episode_steps == 37


@pytest.mark.parametrize("maker", ["make", "direct"])
def test_truncation_at_the_episode_length(maker):
    overrides = {"episode.max_decisions": 20, **FREE_ROAD}
    env = (
        gym.make(HIGHWAY_ENV_ID, overrides=overrides)
        if maker == "make"
        else HighwayEnv(overrides=overrides)
    )
    for episode in range(2):
        env.reset(seed=episode)
        for k in range(1, 21):
            _, _, terminated, truncated, info = env.step(0)
            assert not terminated
            assert truncated == (k == 20), k
        assert info["metrics"]["decisions"] == 20


def test_default_episode_ends_at_2600_m_or_1000_decisions():
    small = {**FREE_ROAD, "lidar.enabled": False, "camera.width_px": 8, "camera.height_px": 8}
    env = HighwayEnv(overrides=small)
    env.reset(seed=0)
    # 60 km/h on a free road: 2,600 m after 156 s, the 390th decision of 0.4 s (or the 391st,
    # as the sum of 390 steps rounds).
    truncations, distances = [], []
    for _ in range(400):
        _, _, _, truncated, _ = env.step(0)
        truncations.append(truncated)
        distances.append(float(env.sim.metrics()["distance_m"][0, 0]))
    first = truncations.index(True)
    assert first in (389, 390)
    assert distances[first - 1] < 2600.0 <= distances[first]
    # Without the distance, 1,000 decisions.
    env = HighwayEnv(overrides={**small, "episode.max_distance_m": None})
    env.reset(seed=0)
    truncations = [env.step(0)[3] for _ in range(1000)]
    assert truncations.index(True) == 999


# --- render ----------------------------------------------------------------------------------


def test_render_rgb_array():
    env = gym.make(HIGHWAY_ENV_ID, render_mode="rgb_array")
    env.reset(seed=0)
    image = env.render()
    assert isinstance(image, np.ndarray)
    assert image.ndim == 3 and image.shape[2] == 3 and image.dtype == np.uint8
    assert image.shape[0] > 10 and image.shape[1] > 10
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 3  # road, grass, cars, markings
    env.step(0)
    assert env.render().shape == image.shape


def test_render_without_mode_returns_none():
    env = HighwayEnv()
    env.reset(seed=0)
    assert env.render() is None


# --- actions ---------------------------------------------------------------------------------


@pytest.mark.parametrize("action", [5, -1, 2.5, np.float32(1.0), 7])
def test_out_of_range_actions_are_refused(action):
    env = HighwayEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError) as err:
        env.step(action)
    message = str(err.value)
    assert "[0, 5)" in message
    assert "expected" in message or "must be" in message


@pytest.mark.parametrize("action", [0, np.int64(3), np.array(2), np.array([[4]])])
def test_integer_actions_of_any_integer_type_are_taken(action):
    env = HighwayEnv(overrides=FREE_ROAD)
    env.reset(seed=0)
    mask = env.action_masks()
    *_, info = env.step(action)
    wanted = int(np.asarray(action).reshape(()))
    assert info["action_applied"] == (wanted if mask[wanted] else 0)


def test_stepping_before_reset_is_refused():
    env = HighwayEnv()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(0)


def test_info_reports_applied_action_and_terms():
    env = HighwayEnv(overrides=FREE_ROAD)
    env.reset(seed=0)
    lane = env.sim.state.lane[0, 0]
    *_, info = env.step(1)
    assert info["action_applied"] == 1
    assert list(info["reward_terms"]) == [
        "speed",
        "collision",
        "lane_change",
        "overtake",
        "warning",
    ]
    move = 3 if lane < 4 else 4
    _, reward, *_, info = env.step(move)
    assert info["action_applied"] == move
    assert info["reward_terms"]["lane_change"] == -0.25
    assert reward == pytest.approx(sum(info["reward_terms"].values()))
    assert info["action_mask"].tolist() == [1, 1, 1, 0, 0]
    *_, info = env.step(move)
    assert info["action_applied"] == 0


# --- determinism -----------------------------------------------------------------------------


def run_episodes(env: HighwayEnv, seed: int, steps: int, action_seed: int):
    rng = np.random.default_rng(action_seed)
    obs, info = env.reset(seed=seed)
    trace = [(obs, None, None, None, info["action_mask"])]
    resets = 0
    for _ in range(steps):
        action = int(rng.choice(np.flatnonzero(info["action_mask"])))
        obs, reward, terminated, truncated, info = env.step(action)
        trace.append((obs, reward, terminated, truncated, info["action_mask"]))
        if terminated or truncated:
            obs, info = env.reset()  # unseeded: continues the seeded stream
            trace.append((obs, None, None, None, info["action_mask"]))
            resets += 1
    return trace, resets


def test_same_seed_and_actions_give_identical_episodes():
    overrides = {"episode.max_decisions": 60, "traffic.density": "heavy"}
    a, resets = run_episodes(HighwayEnv(overrides=overrides), 7, 250, action_seed=1)
    b, _ = run_episodes(HighwayEnv(overrides=overrides), 7, 250, action_seed=1)
    assert resets >= 4
    assert len(a) == len(b)
    for (oa, ra, ta, ua, ma), (ob, rb, tb, ub, mb) in zip(a, b):
        assert_same_observation(oa, ob)
        assert ra == rb and ta == tb and ua == ub  # bit-identical floats
        assert np.array_equal(ma, mb)


def test_different_seeds_give_different_episodes():
    env_a, env_b = HighwayEnv(), HighwayEnv()
    obs_a, _ = env_a.reset(seed=0)
    obs_b, _ = env_b.reset(seed=1)
    assert not np.array_equal(obs_a["lidar"], obs_b["lidar"])
    differ = False
    for _ in range(20):
        oa, ra, *_ = env_a.step(0)
        ob, rb, *_ = env_b.step(0)
        differ |= not np.array_equal(oa["camera"], ob["camera"]) or ra != rb
    assert differ


def test_a_seeded_reset_forgets_the_history():
    env_a, env_b = HighwayEnv(), HighwayEnv()
    env_a.reset(seed=3)
    for action in (1, 3, 0, 2, 4, 0, 0, 1):
        env_a.step(action)
    obs_a, _ = env_a.reset(seed=11)
    obs_b, _ = env_b.reset(seed=11)
    assert_same_observation(obs_a, obs_b)
    for action in (0, 1, 3, 0, 0, 2):
        step_a, step_b = env_a.step(action), env_b.step(action)
        assert_same_observation(step_a[0], step_b[0])
        assert step_a[1:4] == step_b[1:4]


def test_the_behaviour_spec_states_what_each_preset_sees_and_drives():
    """The road, the car and each observation's columns and reach, from the configuration
    (protocol 1.5): what the rule drivers and the recordings read instead of it."""
    from overtake.server.engine.env import HighwayVectorEnv

    def spec(preset, **overrides):
        return HighwayVectorEnv(preset=preset, overrides=overrides).behaviour_spec

    min2018 = spec("min2018")
    assert (min2018.road.lane_count, min2018.road.lane_width_m) == (5, 3.5)
    assert (min2018.car.min_speed_kmh, min2018.car.max_speed_kmh) == (40.0, 80.0)
    assert min2018.observation("lidar").reach.range_m == 80.0
    ego = min2018.observation("ego")
    assert ego.columns[-1] == "speed_mps" and len(ego.columns) == ego.shape[0] == 6
    assert ego.reach.ahead_m == 80.0
    assert min2018.observation("camera").columns == ()
    ho = spec("ho2018")
    assert (ho.car.length_m, ho.car.width_m, ho.road.lane_width_m) == (7.0, 3.4, 5.0)
    grid = ho.observation("grid")
    assert grid.columns == ("left_1", "own", "right_1")
    assert (grid.reach.ahead_m, grid.reach.behind_m) == (24.5, 11.5)
    assert ho.observation("actions").reach is None
    wider = spec("ho2018", **{"grid.side_lanes": 2}).observation("grid").columns
    assert wider == ("left_2", "left_1", "own", "right_1", "right_2")
    lidar_map = spec("fayjie2018").observation("lidar_map").reach
    assert (lidar_map.ahead_m, lidar_map.behind_m, lidar_map.side_m) == (40.0, 0.0, 20.0)
