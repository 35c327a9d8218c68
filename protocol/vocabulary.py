"""The contract's vocabulary: the names both sides of the wire must agree on, defined once.

The simulator reads them from here, and so do clients, trainers and the Rerun views; nothing
else of the project spells them out. Pure Python: importing this module loads nothing but the
standard library, so the simulation core can read it and stay free of msgpack, Zenoh and
Gymnasium.

What a preset chooses for itself (its reward terms, its observation names and shapes) is not
listed here: it travels in each arena's :class:`~overtake.protocol.messages.BehaviourSpec`.
"""

from __future__ import annotations

# Min et al.'s five DAS-level actions, in the order of the discrete action index.
ACTION_NAMES: tuple[str, ...] = ("keep", "cruise_up", "cruise_down", "lane_left", "lane_right")
ACTION_COUNT = len(ACTION_NAMES)
KEEP, CRUISE_UP, CRUISE_DOWN, LANE_LEFT, LANE_RIGHT = range(ACTION_COUNT)
# What a car does when its trainer sent no action in time: adaptive cruise and lane keeping.
DEFAULT_ACTION = KEEP

# The ego vector observation ("ego"), field by field: the agent's own state (m/s, lanes).
EGO_FIELDS: tuple[str, ...] = (
    "speed_mps",
    "cruise_target_mps",
    "lane_index",
    "lane_count",
    "lane_change_progress",
    "lane_change_direction",
)
EGO_SPEED = EGO_FIELDS.index("speed_mps")
EGO_CRUISE_TARGET = EGO_FIELDS.index("cruise_target_mps")

# The papers' episode metrics, the columns of every Steps' ``metrics`` and of info["metrics"].
METRIC_FIELDS: tuple[str, ...] = (
    "avg_speed_kmh",
    "lane_changes",
    "overtakes",
    "collisions",
    "emergency_brakes",
    "distance_m",
    "return",
    "decisions",
)

# Traffic driver types (Ho 2018, Table 5); a vehicle's ``kind`` in world frames indexes this
# tuple, and a kind equal to its length marks an agent's car.
BEHAVIOUR_NAMES: tuple[str, ...] = ("steady", "road_max", "lane_changer")
AGENT_KIND = len(BEHAVIOUR_NAMES)
