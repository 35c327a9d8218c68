"""How much road every view shows around the followed car: the road view's window (metres,
more ahead than behind, as a driver looks; at 950 px wide a car is about 35 px long), shared
by the spectator's roads (:mod:`.world_view`) and a training run's (:mod:`.training_layout`)."""

from __future__ import annotations

ROAD_BEHIND_M = 40.0
ROAD_AHEAD_M = 80.0
