"""Adding a sensor is its module and its section of the configuration (docs/development.md,
"To add something"): done here once with a speedometer, which the simulation then builds,
observes, describes in its spec, switches on and off with ``--set`` and with a trainer's
request, in process and in a server's group, with no other change."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from overtake.server.engine.env import HighwayVectorEnv
from overtake.server.service.groups import Group
from overtake.server.sim import SimConfig, make_config
from overtake.server.sim.config import apply_overrides
from overtake.server.sim.sensors.base import Scene, SensorConfig, SensorFacts, SensorSpace

QUIET = {"traffic.vehicle_count": 4, "episode.max_decisions": 20}


class Speedometer:
    """(1,) float32 per agent: its speed."""

    key = "speedometer"

    def space(self) -> SensorSpace:
        return SensorSpace.uniform((1,), np.float32, 0.0, 100.0)

    def facts(self) -> SensorFacts:
        return SensorFacts(columns=("speed_mps",))

    def observe(self, scene: Scene) -> np.ndarray:
        return scene.state.speed_mps[:, : scene.agents, None].astype(np.float32)


@dataclass(frozen=True, slots=True)
class SpeedometerConfig(SensorConfig):
    """The ``speedometer`` observation."""

    OBSERVATION: ClassVar[str] = "speedometer"

    enabled: bool = True

    def build(self, config: SimConfig) -> Speedometer:
        return Speedometer()


# The configuration with the new section (in the project: one field of SimConfig).
WithSpeedometer = dataclasses.make_dataclass(
    "WithSpeedometer",
    [("speedometer", SpeedometerConfig, field(default_factory=SpeedometerConfig))],
    bases=(SimConfig,),
    frozen=True,
    slots=True,
)


def with_speedometer(preset: str = "min2018") -> SimConfig:
    base = make_config(preset, QUIET)
    return WithSpeedometer(**{f.name: getattr(base, f.name) for f in dataclasses.fields(base)})


def test_a_new_sensor_is_observed_described_and_switched_like_the_others():
    config = with_speedometer()
    envs = HighwayVectorEnv(2, config=config)
    try:
        space = envs.single_observation_space["speedometer"]
        assert space.shape == (1,) and space.dtype == np.float32
        envs.reset(seed=1)
        obs, *_ = envs.step(np.zeros(2, np.int64))
        np.testing.assert_allclose(obs["speedometer"][:, 0], envs.sim.state.speed_mps[:, 0])
        spec = envs.behaviour_spec.observation("speedometer")
        assert spec.columns == ("speed_mps",)
    finally:
        envs.close()
    # --set reaches it by its section's name; a trainer's request by its observation's.
    assert not apply_overrides(config, {"speedometer.enabled": False}).speedometer.enabled
    lean = config.observing(("speedometer",))
    assert [s.enabled for s in lean.sensor_sections().values()].count(True) == 1
    group = Group.of_config(0, "srv", [0], lean, 1, seed=1)
    assert [o.name for o in group.spec.observations] == ["speedometer"]
