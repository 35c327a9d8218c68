"""Sensors: what the agents observe, each behind one small interface (:mod:`.base`).

- :mod:`.lidar`: Min et al.'s 360-ray LIDAR (``lidar``);
- :mod:`.camera`: a front camera rendered in software (``camera``);
- :mod:`.ego`: the agent's own state as numbers (``ego``).

Adding a sensor: a module here with its configuration (a :class:`.base.SensorConfig`) and the
sensor itself (``key``, ``space()``, ``observe(scene)``), a section of that configuration in
:class:`~overtake.server.sim.config.SimConfig`, and the presets that switch it on.
"""

from .base import ObserverViews, Scene, Sensor, SensorConfig, SensorFacts, SensorSpace

__all__ = ["ObserverViews", "Scene", "Sensor", "SensorConfig", "SensorFacts", "SensorSpace"]
