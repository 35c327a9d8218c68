"""highway-env's scene (issue 57): the presets ``highway-fast`` and ``highway``, their ids with
highway-env's interface, and their dynamics held to highway-env's own, car by car.

The strongest check: highway-env 1.12.1 (the dev extra installs it) draws a road, its cars'
state is copied into overtake's simulator, and both play the same decisions; every car's
position, speed, heading and lanes must agree after each decision (its traffic's IDM, MOBIL
and lane-change timer, the controlled car's controllers, the bicycle model, the collision
test and the reward are all in that).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the ids)
from overtake.envs.highway_env_like import ACTION_LABELS, TO_OVERTAKE
from overtake.protocol.errors import BadConfig
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.config import as_json
from overtake.server.sim.highway_scene.highway_env_config import overrides_from_config
from overtake.server.sim.settings_history import as_recorded

highway_env = pytest.importorskip("highway_env", reason="highway-env is in the dev extra")

LANE_WIDTH = 4.0


def _copied(hw, preset: str, overrides=None) -> HighwaySim:
    """overtake's simulator in the state highway-env's ``hw`` is in now."""
    config = make_config(preset, overrides)
    lanes = config.road.lane_count
    sim = HighwaySim(config, num_arenas=1)
    sim.reset(seeds=[0])
    st = sim.state
    vehicles = hw.road.vehicles
    assert len(vehicles) == st.x_m.shape[1]
    for column, v in enumerate(vehicles):
        st.x_m[0, column] = v.position[0]
        st.y_m[0, column] = (lanes - 0.5) * LANE_WIDTH - v.position[1]
        st.speed_mps[0, column] = v.speed
        st.heading_rad[0, column] = -v.heading
        st.lane[0, column] = lanes - 1 - v.lane_index[2]
        st.target_lane[0, column] = lanes - 1 - v.target_lane_index[2]
        st.desired_speed_mps[0, column] = v.target_speed
        st.crashed[0, column] = v.crashed
        if hasattr(v, "timer"):  # an IDMVehicle: traffic, or the controlled car as one
            st.timer_s[0, column] = v.timer
            st.idm_delta[0, column] = v.DELTA
        if column == 0:
            st.speed_index[0, 0] = getattr(v, "speed_index", st.speed_index[0, 0])
    sim.state_written()
    return sim


def _assert_same(hw, sim: HighwaySim, where: str) -> None:
    lanes = sim.config.road.lane_count
    st = sim.state
    for column, v in enumerate(hw.road.vehicles):
        ours = (
            st.x_m[0, column],
            (lanes - 0.5) * LANE_WIDTH - st.y_m[0, column],
            st.speed_mps[0, column],
            -st.heading_rad[0, column],
        )
        theirs = (v.position[0], v.position[1], v.speed, v.heading)
        np.testing.assert_allclose(ours, theirs, atol=1e-6, err_msg=f"car {column}, {where}")
        assert lanes - 1 - st.target_lane[0, column] == v.target_lane_index[2], where
        assert bool(st.crashed[0, column]) == v.crashed, f"car {column} crashed, {where}"


def _available(sim: HighwaySim) -> list[int]:
    """The action mask of ``sim``'s car as highway-env's action numbers, sorted."""
    mask = sim.action_mask()[0, 0]
    return sorted(hw_action for hw_action, ours in enumerate(TO_OVERTAKE) if mask[ours])


@pytest.mark.parametrize(
    ("scene", "preset", "seed"),
    [("highway-fast-v0", "highway-fast", s) for s in (1, 2, 3, 4)] + [("highway-v0", "highway", 5)],
)
def test_every_car_moves_as_in_highway_env(scene, preset, seed):
    hw = gym.make(scene).unwrapped
    hw.reset(seed=seed)
    sim = _copied(hw, preset)
    rng = np.random.default_rng(seed)
    for decision in range(40):
        assert _available(sim) == sorted(hw.action_type.get_available_actions()), decision
        action = int(rng.integers(0, 5))
        _, hw_reward, hw_terminated, _, _ = hw.step(action)
        result = sim.step(np.array([[TO_OVERTAKE[action]]]))
        _assert_same(hw, sim, f"after decision {decision} (action {action})")
        assert result.reward[0, 0] == pytest.approx(hw_reward, abs=1e-9)
        assert bool(result.terminated[0, 0]) == hw_terminated
        if hw_terminated:
            break
    hw.close()


def test_the_action_mask_reads_the_lane_the_car_is_in_as_highway_env_does():
    """Issue 68: at five decisions a second a decision often falls within a lane change; the
    mask offers lane changes from the lane the car is in, as get_available_actions does
    (``highway_scene.action_mask_lane = "target"``, the scene before, from the lane it is
    changing into, differs there). What the car does, and the action applied, are the same
    either way."""
    config = {"policy_frequency": 5, "simulation_frequency": 15}
    hw = gym.make("highway-fast-v0", config=config).unwrapped
    hw.reset(seed=3)
    overrides = overrides_from_config("highway-fast", config)
    sims = {
        lane: _copied(hw, "highway-fast", {**overrides, "highway_scene.action_mask_lane": lane})
        for lane in ("current", "target")
    }
    rng = np.random.default_rng(3)
    agreed = dict.fromkeys(sims, 0)
    changing = 0
    for decision in range(150):
        st = sims["current"].state
        changing += bool(st.lane[0, 0] != st.target_lane[0, 0])
        theirs = sorted(hw.action_type.get_available_actions())
        for lane, sim in sims.items():
            agreed[lane] += _available(sim) == theirs
        action = int(rng.integers(0, 5))
        _, _, hw_terminated, _, _ = hw.step(action)
        results = {lane: sim.step(np.array([[TO_OVERTAKE[action]]])) for lane, sim in sims.items()}
        for lane, sim in sims.items():
            _assert_same(hw, sim, f"{lane}, after decision {decision} (action {action})")
        assert results["current"].action_applied == results["target"].action_applied
        if hw_terminated:
            break
    decisions = decision + 1
    assert changing > 10, "few decisions fell within a lane change: the test tests little"
    assert agreed["current"] == decisions
    assert agreed["target"] < decisions


def test_the_highway_presets_mask_as_highway_env_and_records_of_before_replay_as_they_were():
    for preset in ("highway-fast", "highway"):
        assert make_config(preset).highway_scene.action_mask_lane == "current"
    assert make_config("min2018").highway_scene.action_mask_lane == "target"
    recorded = as_json(make_config("highway-fast"))
    del recorded["highway_scene"]["action_mask_lane"]  # a record from before issue 68
    assert as_recorded("highway-fast", {}, recorded).highway_scene.action_mask_lane == "target"


# highway-v0's 50 cars and 40 s episodes take 12-24 s here: slow (run with -m slow); the
# same code drives highway-fast in the default suite.
@pytest.mark.parametrize(("scene", "preset", "seed"), [
    ("highway-fast-v0", "highway-fast", 7),
    pytest.param("highway-v0", "highway", 8, marks=pytest.mark.slow),
])  # fmt: skip
def test_the_idm_ego_moves_as_highway_env_s_idm_vehicle(scene, preset, seed):
    """highway_scene.ego_driver=idm: the controlled car is highway-env's
    IDMVehicle.create_from(its car), whatever actions are sent; the action applied is the lane
    change it started, else FASTER / SLOWER / IDLE by the target speed nearest its speed."""
    from highway_env.vehicle.behavior import IDMVehicle

    hw = gym.make(scene).unwrapped
    hw.reset(seed=seed)
    car = hw.vehicle
    idm = IDMVehicle.create_from(car)
    hw.road.vehicles[hw.road.vehicles.index(car)] = idm
    hw.controlled_vehicles[0] = idm
    sim = _copied(hw, preset, {"highway_scene.ego_driver": "idm"})
    assert sim.state.idm_delta[0, 0] == idm.DELTA == 4.0
    lanes, speeds = sim.config.road.lane_count, np.array([20.0, 25.0, 30.0])
    index = int(np.abs(speeds - idm.speed).argmin())
    rng = np.random.default_rng(seed)
    applied = []
    for decision in range(40):
        action = int(rng.integers(0, 5))  # unread by either car
        target_before = idm.target_lane_index[2]
        _, hw_reward, hw_terminated, _, _ = hw.step(action)
        result = sim.step(np.array([[TO_OVERTAKE[action]]]))
        _assert_same(hw, sim, f"after decision {decision}")
        assert result.reward[0, 0] == pytest.approx(hw_reward, abs=1e-9)
        assert bool(result.terminated[0, 0]) == hw_terminated
        now = int(np.abs(speeds - idm.speed).argmin())
        # highway-env's lane ids grow to the right: a smaller id is a change to the left.
        if idm.target_lane_index[2] != target_before:
            wanted = "LANE_LEFT" if idm.target_lane_index[2] < target_before else "LANE_RIGHT"
        else:
            wanted = "FASTER" if now > index else "SLOWER" if now < index else "IDLE"
        index = now
        applied.append(int(result.action_applied[0, 0]))
        assert applied[-1] == TO_OVERTAKE[ACTION_LABELS.index(wanted)], f"decision {decision}"
        if hw_terminated:
            break
    assert lanes > 1 and len(set(applied)) > 1  # the car did more than keep going
    hw.close()


def test_the_idm_ego_is_refused_outside_the_highway_scenes():
    with pytest.raises(ValueError, match="highway_scene.ego_driver = 'idm' is not allowed"):
        make_config("min2018", {"highway_scene.ego_driver": "idm"})
    with pytest.raises(ValueError, match="expected one of"):
        make_config("highway-fast", {"highway_scene.ego_driver": "mobil"})


def test_the_ids_take_highway_env_s_config_and_refuse_an_unknown_key_by_name():
    env = gym.make("overtake/highway-fast-v0")
    obs, info = env.reset(seed=0)
    assert obs.shape == (5, 5) and env.action_space == gym.spaces.Discrete(5)
    decisions = 0
    while True:  # always IDLE: the car holds 25 m/s into slower traffic
        obs, _reward, terminated, truncated, info = env.step(1)
        decisions += 1
        if terminated or truncated:
            break
    assert decisions <= 30 and info["crashed"] == terminated
    env.close()
    wider = gym.make("overtake/highway-fast-v0", config={"lanes_count": 4, "vehicles_count": 30})
    config = wider.unwrapped.env.config
    assert config.road.lane_count == 4 and config.traffic.resolved_vehicle_count == 30
    wider.close()
    with pytest.raises(BadConfig, match="'lanes_cuont'; did you mean 'lanes_count'"):
        gym.make("overtake/highway-fast-v0", config={"lanes_cuont": 4})
    with pytest.raises(BadConfig, match="did you mean 'vehicles_count'"):
        overrides_from_config("highway-fast", {"observation": {"vehicle_count": 7}})
    overrides = overrides_from_config(
        "highway",
        {"simulation_frequency": 10, "policy_frequency": 2, "duration": 20,
         "observation": {"type": "Kinematics", "features_range": {"x": [-100, 100]}}},
    )  # fmt: skip
    assert overrides["episode.frames_per_decision"] == 5
    assert overrides["episode.max_decisions"] == 40
    assert overrides["kinematics.x_range_m"] == [-100, 100]
    with pytest.raises(BadConfig, match="OccupancyGrid"):
        overrides_from_config("highway", {"observation": {"type": "OccupancyGrid"}})


def test_the_ids_pass_gymnasium_s_checker_and_vectorise():
    from gymnasium.utils.env_checker import check_env

    for env_id in ("overtake/highway-fast-v0", "overtake/highway-v0"):
        env = gym.make(env_id)
        check_env(env.unwrapped, skip_render_check=True)
        env.close()
    vector = gym.make_vec("overtake/highway-fast-v0", num_envs=3)
    obs, _ = vector.reset(seed=1)
    assert obs.shape == (3, 5, 5)
    obs, _reward, *_, info = vector.step(np.array([1, 3, 0]))
    # The mask in highway-env's order: IDLE is always there.
    assert info["action_mask"].shape == (3, 5) and info["action_mask"][:, 1].all()
    vector.close()


def test_the_kinematics_table_is_highway_env_s():
    """The same cars in both simulators observe the same table, for highway-env's default
    features and for every feature, absolute, seeing behind."""
    features = ["presence", "x", "y", "vx", "vy", "heading", "cos_h", "sin_h", "cos_d",
                "sin_d", "long_off", "lat_off", "ang_off"]  # fmt: skip
    for observation, overrides in (
        ({"type": "Kinematics"}, {}),
        (
            {"type": "Kinematics", "features": features, "absolute": True, "see_behind": True,
             "vehicles_count": 8, "normalize": False},
            {"kinematics.features": features, "kinematics.absolute": True,
             "kinematics.see_behind": True, "kinematics.vehicles_count": 8,
             "kinematics.normalize": False},
        ),
    ):  # fmt: skip
        hw = gym.make("highway-fast-v0", config={"observation": observation}).unwrapped
        hw.reset(seed=7)
        for _ in range(3):
            hw.step(0)  # a lane change under way: headings and lateral offsets
        sim = _copied(hw, "highway-fast", overrides)
        np.testing.assert_allclose(
            sim.observe()["kinematics"][0, 0], hw.observation_type.observe(), atol=1e-5
        )
        hw.close()


def test_the_kinematics_table_is_a_sensor_of_every_preset():
    """On Min et al.'s road (5 lanes of 3.5 m, lane 0 the rightmost): the car's own row in
    absolute terms, a car 30 m ahead one lane to the right as its first neighbour, relative,
    in highway-env's axes (y grows to the right); a car 40 m behind only with see_behind."""
    from tests.support.scenes import Car, scripted_sim

    def table(**settings):
        overrides = {"kinematics.enabled": True, "kinematics.normalize": False, **settings}
        sim = scripted_sim(
            [Car(dx=30.0, lane=1, speed_kmh=54.0), Car(dx=-40.0, lane=2, speed_kmh=90.0)],
            ego_lane=2,
            ego_speed_kmh=72.0,
            overrides=overrides,
        )
        return sim.observe()["kinematics"][0, 0]

    width = 3.5
    front = table()
    # Own row: absolute x 0, y from the leftmost lane's centre (lane 2 of 5: two lanes in).
    np.testing.assert_allclose(front[0], [1, 0.0, 2 * width, 20.0, 0.0], atol=1e-4)
    np.testing.assert_allclose(front[1], [1, 30.0, width, -5.0, 0.0], atol=1e-4)
    assert not front[2:].any()  # the car behind is more than two car lengths back
    behind = table(**{"kinematics.see_behind": True})
    np.testing.assert_allclose(behind[2], [1, -40.0, 0.0, 5.0, 0.0], atol=1e-4)


def test_the_kernels_action_numbers_are_the_vocabulary_s():
    from overtake.protocol import vocabulary as v
    from overtake.server.sim.highway_scene import kernels

    assert (
        kernels.A_KEEP,
        kernels.A_FASTER,
        kernels.A_SLOWER,
        kernels.A_LEFT,
        kernels.A_RIGHT,
    ) == (
        v.KEEP,
        v.CRUISE_UP,
        v.CRUISE_DOWN,
        v.LANE_LEFT,
        v.LANE_RIGHT,
    )


def test_arenas_split_over_threads_step_as_in_one_block(monkeypatch):
    """The decision's blocks of arenas on several threads (from 64 arenas) give the very
    state one block gives: each arena is written by one thread only."""
    from overtake.server.sim.highway_scene import kernels as scene_kernels

    arenas, decisions = 64, 30
    rng = np.random.default_rng(3)
    actions = rng.integers(0, 5, size=(decisions, arenas, 1))

    def run(blocks) -> dict[str, np.ndarray]:
        monkeypatch.setattr(scene_kernels, "arena_blocks", blocks)
        sim = HighwaySim(make_config("highway-fast"), num_arenas=arenas)
        sim.reset(seeds=list(range(arenas)))
        for chosen in actions:
            sim.step(chosen)
        st = sim.state
        return {name: getattr(st, name).copy() for name in ("x_m", "y_m", "speed_mps", "crashed")}

    one = run(lambda count: [slice(0, count)])
    split = run(lambda count: [slice(0, 20), slice(20, 41), slice(41, count)])
    for name, value in one.items():
        np.testing.assert_array_equal(split[name], value, err_msg=name)
    # Not a trivial comparison: the arenas went their own ways.
    assert len({round(float(x), 6) for x in one["x_m"][:, 0]}) > arenas // 2
