"""Several agents on one road: they see each other, and a crash between them ends both."""

import numpy as np

from overtake.server.sim import HighwaySim, make_config


def _two_agents_in_lane_one(gap_m: float) -> HighwaySim:
    sim = HighwaySim(make_config(overrides={"traffic.vehicle_count": 0}), agents_per_arena=2)
    sim.reset(seeds=[0])
    st = sim.state
    st.lane[0, :2] = st.target_lane[0, :2] = 1
    st.y_m[0, :2] = 1.5 * sim.road.lane_width_m
    st.x_m[0, :2] = [0.0, gap_m]
    st.speed_mps[0, :2] = 20.0
    return sim


def test_agents_see_each_other_with_lidar_and_camera():
    sim = _two_agents_in_lane_one(gap_m=30.0)
    obs = sim.observe()
    assert obs["lidar"].shape == (1, 2, 360)
    half_length = sim.config.ego.length_m / 2
    # From its centre, agent 0 sees agent 1's rear straight ahead (ray 0); agent 1 sees agent
    # 0's front straight behind (ray 180).
    np.testing.assert_allclose(obs["lidar"][0, 0, 0], 30.0 - half_length, atol=1e-4)
    np.testing.assert_allclose(obs["lidar"][0, 1, 180], 30.0 - half_length, atol=1e-4)
    image = obs["camera"][0, 0]
    centre = image[:, image.shape[1] // 2]
    assert (centre == 20).any(), "agent 1 is drawn in agent 0's camera"


def test_agents_crashing_into_each_other_are_both_terminated():
    sim = _two_agents_in_lane_one(gap_m=5.0)
    sim.state.speed_mps[0, 0] = 30.0  # closing at 10 m/s from 0.5 m: no brake can stop it
    sim.state.speed_mps[0, 1] = 20.0
    sim.state.desired_speed_mps[0, 1] = 20.0
    result = sim.step(np.zeros((1, 2), dtype=np.int64))
    assert result.terminated[0].tolist() == [True, True]
    assert (result.reward_terms["collision"][0] == sim.config.reward.collision).all()
