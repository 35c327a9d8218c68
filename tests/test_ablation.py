"""Min et al.'s sensor ablation: each row of Table III sees the other cars only through its
own sensors (the warnings and the car ahead ride with the LIDAR, as in the authors' vector)."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.trainers.network import INPUT_SENSORS, LATEST_SENSORS
from overtake.trainers.train import TrainConfig

from conftest import Car, scripted_sim

# A car just ahead in the agent's lane and one beside it on the left: both warnings fire and
# the car ahead has a distance and a speed ...
CROWDED = (Car(dx=12.0, lane=2, speed_kmh=40.0), Car(dx=0.0, lane=3, speed_kmh=60.0))
# ... and the same two cars far behind, out of every sensor's reach and every warning's.
AWAY = (Car(dx=-90.0, lane=2, speed_kmh=40.0), Car(dx=-95.0, lane=3, speed_kmh=60.0))


def observed(inputs: str, cars: tuple[Car, ...]) -> dict[str, np.ndarray]:
    """What a network of ``inputs`` reads, with the traffic ``cars``."""
    overrides = TrainConfig(preset="min2018", inputs=inputs).overrides()
    obs = scripted_sim(cars, ego_lane=2, overrides=overrides).observe()
    return {k: obs[k][0, 0] for k in (*INPUT_SENSORS[inputs], *LATEST_SENSORS[inputs])}


@pytest.mark.parametrize("inputs", ["camera", "lidar", "both"])
def test_other_cars_reach_a_row_only_through_its_own_sensors(inputs):
    crowded, away = observed(inputs, CROWDED), observed(inputs, AWAY)
    sensors = INPUT_SENSORS[inputs]
    # The row's own sensors see the cars move ...
    assert all(not np.array_equal(crowded[k], away[k]) for k in sensors)
    # ... and whatever else it reads is unchanged, unless it rides with the LIDAR.
    for name in set(crowded) - set(sensors):
        if "lidar" in sensors:
            continue
        assert np.array_equal(crowded[name], away[name]), (inputs, name)


def test_the_warnings_ride_with_the_lidar():
    """The LIDAR rows do read the warnings and the car ahead (and the camera row would, with
    the preset's own ego vector: the test above is not vacuous)."""
    assert not np.array_equal(observed("lidar", CROWDED)["ego"], observed("lidar", AWAY)["ego"])
    crowded, away = (
        scripted_sim(cars, ego_lane=2).observe()["ego"][0, 0] for cars in (CROWDED, AWAY)
    )
    assert not np.array_equal(crowded, away)
    assert observed("camera", CROWDED)["ego"].shape == (1,)  # the car's own speed
