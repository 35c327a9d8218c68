"""The contract's vocabulary: the names both sides of the wire must agree on, defined once.

The simulator reads them from here, and so do clients, trainers and the Rerun views; nothing
else of the project spells them out. Pure Python: importing this module loads nothing but the
standard library, so the simulation core can read it and stay free of msgpack, Zenoh and
Gymnasium.

What a preset chooses for itself (its reward terms, its observation names and shapes) is not
listed here: it travels in each arena's :class:`~overtake.protocol.messages.BehaviourSpec`.
"""

from __future__ import annotations

from typing import Literal, get_args

# Min et al.'s five DAS-level actions, in the order of the discrete action index.
ACTION_NAMES: tuple[str, ...] = ("keep", "cruise_up", "cruise_down", "lane_left", "lane_right")
ACTION_COUNT = len(ACTION_NAMES)
KEEP, CRUISE_UP, CRUISE_DOWN, LANE_LEFT, LANE_RIGHT = range(ACTION_COUNT)
# The same five actions as highway-env's DiscreteMetaAction names them, in overtake's order
# (highway-env numbers them 0 LANE_LEFT, 1 IDLE, 2 LANE_RIGHT, 3 FASTER, 4 SLOWER): what
# highway-env's scenes (presets highway-fast, highway) call them in their behaviour spec's
# action_names, and so in recordings and tables.
HIGHWAY_ENV_ACTION_NAMES: tuple[str, ...] = ("IDLE", "FASTER", "SLOWER", "LANE_LEFT", "LANE_RIGHT")
# What a car does when its trainer sent no action in time: adaptive cruise and lane keeping.
DEFAULT_ACTION = KEEP

# Every field the ego vector observation ("ego") can hold. A preset picks which, in which
# order (``ego_vector.fields`` of its configuration, which every spec's ``config_json``
# carries): speeds in m/s, distances in m, lanes counted from the right, warnings 0 or 1.
EGO_FIELDS: tuple[str, ...] = (
    "speed_mps",
    "cruise_target_mps",
    "lane_index",
    "lane_count",
    "lane_change_progress",
    "lane_change_direction",
    "left_warning",
    "right_warning",
    "forward_warning",
    "ahead_distance_m",
    "ahead_speed_mps",
)

# The papers' episode metrics, the columns of every Steps' ``metrics`` and of info["metrics"],
# and the traffic cars on the road on average over the episode (what a density label means).
METRIC_FIELDS: tuple[str, ...] = (
    "avg_speed_kmh",
    "lane_changes",
    "overtakes",
    "collisions",
    "emergency_brakes",
    "distance_m",
    "return",
    "decisions",
    "traffic_cars",
)
# The metrics that count events, which a vector environment also reports after every step as
# the episode's counts so far (``info["episode_counts"]``): the decision whose count rose had
# one (an episode record marks it, a replay shows it).
EPISODE_COUNTS: tuple[str, ...] = ("collisions", "emergency_brakes")
assert set(EPISODE_COUNTS) <= set(METRIC_FIELDS)

# The keys of every overtake environment's ``info`` (the single, vector and PettingZoo faces
# alike, in process or remote; overtake.envs.faces.StepInfo builds it): the action mask,
# the action applied, the reward's terms, the episode's event counts so far, the episode's
# metrics (where it ended), whether the action was late, and whether the server was lost.
INFO_KEYS: tuple[str, ...] = (
    "action_mask",
    "action_applied",
    "reward_terms",
    "episode_counts",
    "metrics",
    "late",
    "server_restarted",
)

# Traffic densities, the words a preset's ``traffic.density`` takes (each preset says how many
# cars each brings: ``traffic.density_vehicle_counts``, in this order); what every command's
# --traffic and every experiment's densities are spelled in.
Density = Literal["light", "medium", "heavy"]
DENSITIES: tuple[Density, ...] = get_args(Density)
# Driver assistance that watches a lane change through (the shield's option,
# overtake.server.sim.lane_watch): the setting that turns it on, and the metrics a simulator
# with it reports after METRIC_FIELDS (an episode's lane changes turned back).
WATCH_SETTING = "ego.lane_change_watch"
WATCH_METRICS: tuple[str, ...] = ("lane_change_aborts",)
# The simulator settings a scenario names by its own options (--traffic, --max-decisions).
DENSITY_SETTING = "traffic.density"
# Who drives the agents' cars in highway-env's scenes (overtake.server.sim.highway_scene): their
# meta-actions, or (EGO_DRIVER_IDM) the scene's own IDM + MOBIL car, --policy idm's driver; and
# the presets that are those scenes.
EGO_DRIVER_SETTING = "highway_scene.ego_driver"
EGO_DRIVER_IDM = "idm"
HIGHWAY_SCENE_PRESETS: tuple[str, ...] = ("highway-fast", "highway")
HIGHWAY_SCENE_SETTING = "highway_scene.enabled"
EPISODE_LENGTH_SETTING = "episode.max_decisions"
# The preset a simulator runs where nobody names one (Min et al. 2018, the paper overtake began
# with): every environment's, command's and configuration's default, on both sides of the wire.
DEFAULT_PRESET = "min2018"
# Configurations written in another simulator's words, which the simulator translates into its
# own settings where a trainer asks for it by name (OpenRequest.translation, protocol 1.11):
# highway-env's ``config`` dict, on its scenes (HIGHWAY_SCENE_PRESETS).
HIGHWAY_ENV_TRANSLATION = "highway-env"
TRANSLATIONS: tuple[str, ...] = (HIGHWAY_ENV_TRANSLATION,)
# highway-env's keys that its face reads itself (overtake.envs.highway_env_like), not the
# simulator: the viewer's framing of render()'s picture and the keys that change nothing here
# (top level), and the action subset (config["action"]'s). The server's translation takes
# them as known and leaves them alone, so a typo is matched against every key highway-env has.
HIGHWAY_ENV_FACE_KEYS: tuple[str, ...] = (
    "screen_width",
    "screen_height",
    "scaling",
    "centering_position",
    "show_trajectories",
    "render_agent",
    "offscreen_rendering",
    "manual_control",
    "real_time_rendering",
    "neighbour_vehicles_connected_lanes",
)
HIGHWAY_ENV_FACE_ACTION_KEYS: tuple[str, ...] = ("longitudinal", "lateral")

# Traffic driver types: Ho's three (2018, Table 5), and Min et al.'s cars that act at random
# (2018, §IV.A). A vehicle's ``kind`` in world frames indexes this tuple, and a kind equal to
# its length marks an agent's car.
BEHAVIOUR_NAMES: tuple[str, ...] = ("steady", "road_max", "lane_changer", "random")
AGENT_KIND = len(BEHAVIOUR_NAMES)
# How every view draws the vehicles (the in-process render and Rerun's road alike), RGB: one
# colour per behaviour in the order of BEHAVIOUR_NAMES (steady blue, road-max green,
# lane-changer orange, random purple), and the agents' cars red.
BEHAVIOUR_COLOURS: tuple[tuple[int, int, int], ...] = (
    (80, 120, 255),
    (40, 200, 120),
    (240, 170, 30),
    (200, 120, 230),
)
AGENT_COLOUR: tuple[int, int, int] = (230, 40, 40)
