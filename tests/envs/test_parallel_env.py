"""``HighwayParallelEnv``: several learning cars on one road, in PettingZoo's Parallel API."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from overtake.client.envs.parallel_env import RemoteHighwayParallelEnv
from overtake.client.wire.remote import ArenaGroup
from overtake.protocol import errors
from overtake.server.engine.env import HighwayEnv
from overtake.server.engine.parallel_env import HighwayParallelEnv

from tests.support.remote import remote_config

# Short episodes on a road of 10 cars, where these seeds' random driving does not crash.
SHORT = {"episode.max_decisions": 30, "traffic.vehicle_count": 10}
# An empty road (no traffic) where car_1 and car_2 start in adjacent lanes, car_2 30 m behind;
# the cars change lanes as told (min2018's lane-change check off), so that one can cut in.
EMPTY_ROAD = {
    "episode.max_decisions": 60,
    "traffic.vehicle_count": 0,
    "ego.lane_change_check": False,
}


def test_pettingzoo_parallel_api_test_passes():
    env = HighwayParallelEnv(agents=3, overrides=SHORT)
    with warnings.catch_warnings():
        # The API test reports most of what it finds wrong as warnings: make them failures.
        warnings.simplefilter("error")
        parallel_api_test(env, num_cycles=100)


def test_one_car_is_the_single_agent_env_bit_for_bit():
    parallel = HighwayParallelEnv(agents=1, overrides=SHORT)
    single = HighwayEnv(overrides=SHORT)
    observations, infos = parallel.reset(seed=7)
    observation, info = single.reset(seed=7)
    for key in observation:
        np.testing.assert_array_equal(observations["car_0"][key], observation[key])
    np.testing.assert_array_equal(infos["car_0"]["action_mask"], info["action_mask"])
    rng = np.random.default_rng(0)
    for _ in range(SHORT["episode.max_decisions"]):
        action = int(rng.integers(0, 5))
        observations, rewards, terminations, truncations, infos = parallel.step({"car_0": action})
        observation, reward, terminated, truncated, info = single.step(action)
        for key in observation:
            np.testing.assert_array_equal(observations["car_0"][key], observation[key])
        assert rewards["car_0"] == reward
        assert (terminations["car_0"], truncations["car_0"]) == (terminated, truncated)
        assert infos["car_0"]["reward_terms"] == info["reward_terms"]
        if terminated or truncated:
            assert infos["car_0"]["metrics"] == info["metrics"]
            break
    assert truncated and parallel.agents == []


def test_the_same_seed_and_actions_give_the_same_road():
    def run() -> list[np.ndarray]:
        env = HighwayParallelEnv(agents=2, overrides=SHORT)
        env.reset(seed=3)
        rng = np.random.default_rng(1)
        lidar = []
        while env.agents:
            observations, *_ = env.step({a: int(rng.integers(0, 5)) for a in env.agents})
            lidar.extend(observations[a]["lidar"] for a in sorted(observations))
        return lidar

    first, second = run(), run()
    assert len(first) == 2 * SHORT["episode.max_decisions"]
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def crash_car_2_into_car_1(env: HighwayParallelEnv):
    """car_1 brakes in its lane; car_2 catches up in the next lane and cuts into it."""
    state = env.sim.state
    changed = False
    for _ in range(EMPTY_ROAD["episode.max_decisions"]):
        gap_m = state.x_m[0, 1] - state.x_m[0, 2]
        if not changed and gap_m < 10.0:
            car_2, changed = 4, True  # right, into car_1's lane
        else:
            car_2 = 0 if changed else 1
        plan = {"car_0": 0, "car_1": 2, "car_2": car_2}
        result = env.step({a: plan[a] for a in env.agents})
        if any(result[2].values()):
            return result
    raise AssertionError("the two cars never collided")


def test_a_crashed_car_leaves_the_road_and_the_others_drive_on():
    env = HighwayParallelEnv(agents=3, overrides=EMPTY_ROAD)
    env.reset(seed=1)
    assert env.sim.state.y_m[0, 1] != env.sim.state.y_m[0, 2]
    _, rewards, terminations, truncations, infos = crash_car_2_into_car_1(env)
    assert terminations == {"car_0": False, "car_1": True, "car_2": True}
    assert rewards["car_1"] <= -10.0 + 1.0  # the collision penalty of Table I
    assert infos["car_1"]["metrics"]["collisions"] == 1.0
    assert env.agents == ["car_0"]
    # The crash's picture still shows them; with the next step they have left the road.
    assert env.sim.agents_present().tolist() == [[True, True, True]]
    # Acting for a car that has left is refused by name, as is leaving out a live one.
    with pytest.raises(ValueError, match=r"finished this episode: \['car_1'\]"):
        env.step({"car_0": 0, "car_1": 0})
    with pytest.raises(ValueError, match=r"missing \['car_0'\]"):
        env.step({})
    steps = 0
    while env.agents:
        observations, rewards, terminations, truncations, infos = env.step({"car_0": 1})
        assert set(observations) == {"car_0"}  # only the live car is reported
        assert env.sim.agents_present().tolist() == [[True, False, False]]
        steps += 1
    assert truncations == {"car_0": True}
    with pytest.raises(RuntimeError, match="call reset"):
        env.step({"car_0": 0})
    # A reset brings every car back.
    observations, _ = env.reset()
    assert env.agents == ["car_0", "car_1", "car_2"] == sorted(observations)
    assert env.sim.agents_present().all()


@pytest.mark.parametrize("action", [5, -1, 1.5, "left"])
def test_an_out_of_range_action_is_refused_naming_the_car(action):
    env = HighwayParallelEnv(agents=2, overrides=SHORT)
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action of 'car_1' must be"):
        env.step({"car_0": 0, "car_1": action})


def test_an_unknown_agent_is_named_with_the_road_s_agents():
    env = HighwayParallelEnv(agents=2, overrides=SHORT)
    with pytest.raises(KeyError, match=r"no agent 'car_7'.*\['car_0', 'car_1'\]"):
        env.observation_space("car_7")
    assert env.observation_space("car_1") is env.observation_space("car_0")


# --- the remote twin --------------------------------------------------------------------------


def remote_parallel(server, agents: int, overrides) -> RemoteHighwayParallelEnv:
    return RemoteHighwayParallelEnv(
        agents=agents,
        overrides=overrides,
        remote=remote_config(server.endpoint, server.name),
    )


@pytest.mark.timeout(120)
def test_remote_road_equals_in_process_bit_for_bit_through_a_crash(start_server):
    # The crash takes car_1 and car_2 off the road; had the server restarted them behind
    # car_0 (as on shared roads), car_0's LIDAR would see them and the two runs would part.
    local = HighwayParallelEnv(agents=3, overrides=EMPTY_ROAD)
    local.reset(seed=1)
    plan: list[dict[str, int]] = []
    original_step = local.step

    def recording_step(actions):
        plan.append(dict(actions))
        return original_step(actions)

    local.step = recording_step  # type: ignore[method-assign]
    crash_car_2_into_car_1(local)
    while local.agents:
        local.step({a: 1 for a in local.agents})

    server = start_server("parallel-remote")
    remote = remote_parallel(server, 3, EMPTY_ROAD)
    replay = HighwayParallelEnv(agents=3, overrides=EMPTY_ROAD)
    try:
        got, _ = remote.reset(seed=1)
        want, _ = replay.reset(seed=1)
        assert_same_observations(got, want)
        for actions in plan:
            got_step = remote.step(actions)
            want_step = replay.step(actions)
            assert_same_observations(got_step[0], want_step[0])
            assert got_step[1:4] == want_step[1:4]  # rewards, terminations, truncations
            for agent, info in want_step[4].items():
                assert got_step[4][agent]["reward_terms"] == info["reward_terms"]
                assert got_step[4][agent].get("metrics") == info.get("metrics")
            assert remote.agents == replay.agents
        assert remote.agents == [] and len(plan) == EMPTY_ROAD["episode.max_decisions"]
        # A new episode brings every car back, on the server too.
        got, _ = remote.reset(seed=2)
        want, _ = replay.reset(seed=2)
        assert_same_observations(got, want)
    finally:
        remote.close()
    assert server.status().arenas_used == 0


def assert_same_observations(got, want) -> None:
    assert sorted(got) == sorted(want)
    for agent in want:
        for key in want[agent]:
            np.testing.assert_array_equal(got[agent][key], want[agent][key], err_msg=agent)


@pytest.mark.timeout(120)
def test_remote_road_passes_pettingzoo_parallel_api_test(start_server):
    server = start_server("parallel-api")
    env = remote_parallel(server, 2, {"episode.max_decisions": 20})
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            parallel_api_test(env, num_cycles=40)
    finally:
        env.close()


@pytest.mark.timeout(60)
def test_a_server_too_old_to_retire_cars_is_refused_and_its_arena_freed(start_server, monkeypatch):
    server = start_server("parallel-old")
    original_open = ArenaGroup._open

    def as_if_1_2(self, reseed=True):
        original_open(self, reseed)
        self.server_minor = 2  # what a 1.2 server's Opened decodes to

    monkeypatch.setattr(ArenaGroup, "_open", as_if_1_2)
    with pytest.raises(errors.VersionMismatch, match=r"speaks protocol 1\.2; .* need 1\.3"):
        remote_parallel(server, 2, SHORT)
    assert server.status().arenas_used == 0
