"""Min et al.'s sensor ablation: each row of Table III sees the other cars only through its
own sensors (the warnings and the car ahead ride with the LIDAR, as in the authors' vector)."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.client.episodes.scenario import Scenario
from overtake.trainers.learning.network import INPUT_SENSORS, LATEST_SENSORS
from overtake.trainers.train import TrainConfig

from tests.support.scenes import Car, scripted_sim

# A car just ahead in the agent's lane and one beside it on the left: both warnings fire and
# the car ahead has a distance and a speed ...
CROWDED = (Car(dx=12.0, lane=2, speed_kmh=40.0), Car(dx=0.0, lane=3, speed_kmh=60.0))
# ... and the same two cars far behind, out of every sensor's reach and every warning's.
AWAY = (Car(dx=-90.0, lane=2, speed_kmh=40.0), Car(dx=-95.0, lane=3, speed_kmh=60.0))


def asked(inputs: str) -> dict:
    """What a trainer of ``inputs`` asks of the simulator: its overrides and ego fields."""
    config = TrainConfig(inputs=inputs, scenario=Scenario(preset="min2018"))
    return {"overrides": config.overrides(), "ego_fields": config.ego_fields}


def observed(inputs: str, cars: tuple[Car, ...]) -> dict[str, np.ndarray]:
    """What a network of ``inputs`` reads, with the traffic ``cars``."""
    obs = scripted_sim(cars, ego_lane=2, **asked(inputs)).observe()
    return {k: obs[k][0, 0] for k in (*INPUT_SENSORS[inputs], *LATEST_SENSORS[inputs])}


# The ego vector's fields that tell of other cars (the authors' code's scalars, which ride
# with the LIDAR); the car's own speed is the rest.
OTHER_CARS = (
    "left_warning",
    "right_warning",
    "forward_warning",
    "ahead_distance_m",
    "ahead_speed_mps",
)


@pytest.mark.parametrize("inputs", ["camera", "lidar", "both"])
def test_other_cars_reach_a_row_only_through_its_own_sensors(inputs):
    crowded, away = observed(inputs, CROWDED), observed(inputs, AWAY)
    sensors = INPUT_SENSORS[inputs]
    fields = scripted_sim((), **asked(inputs)).config.ego_vector.fields
    # The row's own sensors see the cars move ...
    assert all(not np.array_equal(crowded[k], away[k]) for k in sensors)
    # ... and of whatever else it reads, only the ego vector's scalars of other cars change,
    # and only where they ride with the LIDAR: the car's own speed never does.
    for name in set(crowded) - set(sensors):
        assert name == "ego", (inputs, name)
        for column, field in enumerate(fields):
            same = crowded[name][column] == away[name][column]
            if field in OTHER_CARS:
                assert "lidar" in sensors, (inputs, field)
            else:
                assert same, (inputs, field)
    if "lidar" in sensors:
        changed = [f for i, f in enumerate(fields) if crowded["ego"][i] != away["ego"][i]]
        assert changed and set(changed) <= set(OTHER_CARS), changed


def test_the_warnings_ride_with_the_lidar():
    """The LIDAR rows do read the warnings and the car ahead (and the camera row would, with
    the preset's own ego vector: the test above is not vacuous)."""
    assert not np.array_equal(observed("lidar", CROWDED)["ego"], observed("lidar", AWAY)["ego"])
    crowded, away = (
        scripted_sim(cars, ego_lane=2).observe()["ego"][0, 0] for cars in (CROWDED, AWAY)
    )
    assert not np.array_equal(crowded, away)
    assert observed("camera", CROWDED)["ego"].shape == (1,)  # the car's own speed


def scene(inputs: str, cars: tuple[Car, ...], **extra):
    trainer = asked(inputs)
    return scripted_sim(
        cars,
        ego_lane=2,
        overrides={**trainer["overrides"], **extra},
        ego_fields=trainer["ego_fields"],
    )


@pytest.mark.parametrize("inputs", ["camera", "lidar", "both"])
def test_the_mask_a_row_acts_on_tells_nothing_of_the_cars_and_the_car_refuses_for_it(inputs):
    """The authors' DAS refuses a lane change under a side warning; the action mask each row
    chooses with is the same with a car beside and one ahead as with none near (it marks only
    what cannot be done at all), so no row learns of the car beside from it: the camera row
    acts without the warning and its car refuses."""
    crowded, away = scene(inputs, CROWDED), scene(inputs, AWAY)
    np.testing.assert_array_equal(crowded.action_mask(), away.action_mask())
    assert crowded.action_mask()[0, 0].tolist() == [1, 1, 1, 1, 1]
    # Left, into the car beside: refused by the car, for every row; right, clear: taken.
    assert crowded.step(np.array([[3]])).action_applied[0, 0] == 0
    assert crowded.state.target_lane[0, 0] == 2
    assert scene(inputs, CROWDED).step(np.array([[4]])).action_applied[0, 0] == 4


def test_a_mask_with_the_refusals_would_carry_the_car_beside():
    """The test above is not vacuous: with ego.mask_refusals the mask would tell."""
    crowded = scene("camera", CROWDED, **{"ego.mask_refusals": True})
    away = scene("camera", AWAY, **{"ego.mask_refusals": True})
    assert crowded.action_mask()[0, 0, 3] == 0 and away.action_mask()[0, 0, 3] == 1
