"""Traffic models: the drivers around the agents.

- :mod:`.config`: how many cars, which driver types (Ho's three behaviours) and their manners;
- :mod:`.car_following`: the IDM every car follows its leader with (agents' cruise control too);
- :mod:`.lane_changes`: MOBIL, traffic's lane-change decisions;
- :mod:`.manoeuvres`: random changes of a driver's desired speed.

Where traffic appears and disappears (the treadmill around the agents) is
:mod:`overtake.server.sim.spawning`.
"""

from .config import DENSITIES, BehaviourConfig, Density, TrafficConfig

__all__ = ["DENSITIES", "BehaviourConfig", "Density", "TrafficConfig"]
