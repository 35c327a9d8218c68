"""The simulator's settings through time, in one place: every setting added or changed since
episode records were first kept (:data:`HISTORY`: its name, the issue that made the change, what
the simulator did before), and the papers' presets as they were before the authors' traffic
(:data:`BEFORE_AUTHORS_TRAFFIC`).

A record keeps the whole configuration its simulator resolved to. :func:`as_recorded` builds that
simulator again from today's code: the record's preset and overrides, then, where the
simulator changed since, the settings that undo the change (an added setting the record does
not name at its value from before; a preset's changed value at the record's); what still
differs is refused, naming it. The in-process engine and the server both build a replay's
simulator here (a trainer sends the record's configuration in its OpenRequest), so no client
holds the simulator's schema or its history.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from overtake.protocol.vocabulary import BEHAVIOUR_NAMES

from .config import ConfigError, PlainValue, SimConfig, Translated, as_json
from .presets import make_config


class _Marker:
    """A ``before`` that is not a value (named, for the history's repr)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return self.name


INERT: Any = _Marker("INERT")
"""An added setting that decided nothing before it existed (whatever it holds now)."""
FROM_RECORD: Any = _Marker("FROM_RECORD")
"""A preset's changed value: a replay takes the record's."""


@dataclass(frozen=True)
class SettingChange:
    """One setting added or changed since records were first kept."""

    name: str  # the dotted setting (or a whole section)
    since: int  # the issue that made the change
    before: Any = INERT
    """What makes the simulator what it was before: the value an added setting had in effect
    (:data:`INERT`: it decided nothing then), or :data:`FROM_RECORD` for an existing setting
    whose value in :attr:`presets` changed (the record holds the value of its day)."""
    presets: tuple[str, ...] = ()  # with FROM_RECORD: the presets whose value changed


_TRAFFIC_FIELDS_44 = (
    ("speed_steps_per_s", 0.0),
    ("speed_step_kmh", INERT),
    ("speed_step_up_prob", INERT),
    ("speed_step_down_prob", INERT),
    ("speed_walk_kmh", INERT),
    ("keeps_current_speed", False),
    ("random_lane_changes_when_slow", False),
)
_CHANGED_44 = {
    "min2018": (
        "ego.lane_change_check",
        "traffic.random.desired_speed_kmh",
        "traffic.random.speed_change_rate_per_s",
        "traffic.random.random_lane_change_rate_per_s",
        "traffic.keep_ahead_m",
    ),
    "ho2018": (
        "traffic.density_vehicle_counts",
        "traffic.steady.lane_change_threshold_mps2",
        "traffic.road_max.lane_change_threshold_mps2",
        "traffic.road_max.desired_speed_kmh",
        "traffic.lane_changer.desired_speed_kmh",
        "traffic.lane_changer.lane_change_threshold_mps2",
        "traffic.lane_change_duration_s",
        "ego.safety_gap_m",
        "ego.lane_change_clear_ahead_m",
        "ego.lane_change_clear_behind_m",
        "ego.lane_change_closing_time_s",
        "ego.lane_change_duration_s",
    ),
}

HISTORY: tuple[SettingChange, ...] = (
    # Issue 44, the authors' traffic: speed steps, entry zones and their own car-following.
    *(
        SettingChange(f"traffic.{name}.{field}", since=44, before=before)
        for name in BEHAVIOUR_NAMES
        for field, before in _TRAFFIC_FIELDS_44
    ),
    SettingChange("traffic.following", since=44, before="idm"),
    SettingChange("traffic.safety_gap_m", since=44),
    SettingChange("traffic.entry", since=44, before="comfortable"),
    SettingChange("traffic.entry_prob_per_frame", since=44),
    SettingChange("traffic.entry_offset_m", since=44),
    SettingChange("traffic.entry_zone_ahead_m", since=44),
    SettingChange("traffic.entry_zone_behind_m", since=44),
    SettingChange("traffic.entry_speed_ahead_kmh", since=44),
    SettingChange("traffic.entry_speed_behind_kmh", since=44),
    SettingChange("episode.max_distance_m", since=44, before=None),
    # The action mask carried driver assistance's refusals (with the lane-change check on).
    SettingChange("ego.mask_refusals", since=44, before=True),
    SettingChange("grid.covered_by", since=44, before="any_part"),
    *(
        SettingChange(name, since=44, before=FROM_RECORD, presets=(preset,))
        for preset, names in _CHANGED_44.items()
        for name in names
    ),
    # Issue 46: nothing watched a lane change once it had begun (the watch's brake and
    # response time then do nothing).
    SettingChange("ego.lane_change_watch", since=46, before=False),
    SettingChange("ego.watch_brake_mps2", since=46),
    SettingChange("ego.watch_response_s", since=46),
    # Issue 56: every preset counted a deliberate brake with a slower car ahead (Ho's now
    # counts the brakes his safety rule forces, as his code does).
    SettingChange("ego.emergency_brake_count", since=56, before="deliberate"),
    # Issue 57: highway-env's scene and its Kinematics observation, whole sections, off in
    # every preset of before.
    SettingChange("highway_scene", since=57),
    SettingChange("kinematics", since=57),
    # Issue 66: the action applied was the one chosen (a refused lane change keep); ho2018's
    # is now as his car drove it, and its skipped frames repeat that.
    SettingChange("ego.applied_as_driven", since=66, before=False),
    # Issue 67: the ego was driven by its meta-actions (highway-env's IDM ego is an option).
    SettingChange("highway_scene.ego_driver", since=67, before="meta_actions"),
    SettingChange("highway_scene.ego_idm_delta", since=67),
    # Issue 68: highway-env's scene masked lane changes from the lane the car was changing
    # into (highway-env, and its presets now, from the lane it is in).
    SettingChange("highway_scene.action_mask_lane", since=68, before="target"),
    # Issue 68: min2018's traffic came and went on a treadmill (entry "comfortable": a car out
    # of range recycled at once, the road full from the start); now by its authors' spawners.
    # Their settings decided nothing before (the treadmill reads none of them).
    SettingChange("traffic.entry", since=68, before=FROM_RECORD, presets=("min2018",)),
    *(
        SettingChange(f"traffic.{name}", since=68)
        for name in (
            "spawner_count",
            "spawner_step_s",
            "spawner_wait_s",
            "spawner_ahead_share",
            "spawner_clearance_m",
            "spawner_clearance_lanes",
        )
    ),
)
SETTINGS_EPOCH = max(change.since for change in HISTORY)
"""The last issue that changed the simulator's settings."""
_ADDED = {c.name: c for c in HISTORY if c.before is not FROM_RECORD}

# The presets as issue 32 left them, before the authors' traffic (issue 44), as overrides of
# today's: Min et al.'s on the treadmill, with blind lane changes, desired speeds redrawn in
# 40-65 km/h, random lane changes every 20 s, 150 m kept ahead and episodes of 1,000
# decisions; Ho's with IDM and MOBIL traffic entering where IDM finds a comfortable gap,
# "road_max" and "lane_changer" at a constant 100 km/h, the lane changer switching by MOBIL, a
# safety gap of 8 m and the side check of Min et al.'s preset. With them the tables kept in
# bench/results before issue 44 can be made again: tests/server/sim/test_golden.py holds them
# to the digests of then.
BEFORE_AUTHORS_TRAFFIC: dict[str, dict[str, PlainValue]] = {
    "min2018": {
        # The treadmill, as then (issue 68 brings the authors' spawners).
        "traffic.entry": "comfortable",
        "ego.lane_change_check": False,
        "traffic.random.speed_steps_per_s": 0.0,
        "traffic.random.speed_walk_kmh": None,
        "traffic.random.desired_speed_kmh": (40.0, 65.0),
        "traffic.random.speed_change_rate_per_s": 0.1,
        "traffic.random.random_lane_change_rate_per_s": 0.05,
        "traffic.keep_ahead_m": 150.0,
        "episode.max_distance_m": None,
    },
    "ho2018": {
        # Counted as any preset counted them then (issue 56 counts the brakes his rule forces).
        "ego.emergency_brake_count": "deliberate",
        # The action chosen applied, as then (issue 66 applies it as his car drove it).
        "ego.applied_as_driven": False,
        "traffic.density_vehicle_counts": (20, 40, 60),
        "traffic.entry": "comfortable",
        "traffic.following": "idm",
        "traffic.steady.keeps_current_speed": False,
        "traffic.steady.lane_change_threshold_mps2": 10.0,
        "traffic.road_max.lane_change_threshold_mps2": 10.0,
        "traffic.road_max.keeps_current_speed": False,
        "traffic.road_max.speed_steps_per_s": 0.0,
        "traffic.road_max.desired_speed_kmh": (100.0, 100.0),
        "traffic.lane_changer.keeps_current_speed": False,
        "traffic.lane_changer.speed_steps_per_s": 0.0,
        "traffic.lane_changer.desired_speed_kmh": (100.0, 100.0),
        "traffic.lane_changer.lane_change_threshold_mps2": 0.1,
        "ego.safety_gap_m": 8.0,
        "ego.lane_change_clear_ahead_m": 2.0,
        "ego.lane_change_clear_behind_m": 4.0,
        "ego.lane_change_closing_time_s": 1.0,
        "ego.lane_change_duration_s": 0.24,
        "traffic.lane_change_duration_s": 0.24,
        "traffic.safety_gap_m": 3.5,
        "traffic.lane_changer.random_lane_change_rate_per_s": 0.0,
        "traffic.lane_changer.random_lane_changes_when_slow": False,
        "grid.covered_by": "any_part",
    },
}


def flat(config: Any, prefix: str = "") -> dict[str, Any]:
    """A nested configuration as dotted names to values (lists for tuples, as JSON has it)."""
    if not isinstance(config, dict):
        return {prefix: list(config) if isinstance(config, tuple) else config}
    found: dict[str, Any] = {}
    for key, value in config.items():
        found.update(flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return found


def undo_overrides(recorded: Mapping[str, Any], now: Mapping[str, Any]) -> dict[str, Any]:
    """The overrides that turn the simulator a record's preset and overrides give today
    (``now``) into the one the record was made on (``recorded``), where only the simulator has
    changed since (:data:`HISTORY`): the settings added since, which the record does not name,
    at their values from before, then the preset's settings whose value changed since at the
    record's. Any other difference stays, for :func:`unexplained_differences` to report."""
    flat_recorded, flat_now = flat(dict(recorded)), flat(dict(now))
    preset = recorded.get("preset")
    undo: dict[str, Any] = {}
    for change in HISTORY:
        name = change.name
        if name not in flat_now:
            continue
        if change.before is FROM_RECORD:
            if (
                preset in change.presets
                and preset == now.get("preset")
                and name in flat_recorded
                and flat_recorded[name] != flat_now[name]
            ):
                undo[name] = flat_recorded[name]
        elif (
            change.before is not INERT
            and name not in flat_recorded
            and flat_now[name] != change.before
        ):
            undo[name] = change.before
    return undo


def unexplained_differences(recorded: Mapping[str, Any], now: Mapping[str, Any]) -> list[str]:
    """:func:`config_differences`, less the settings added since the record (which
    :func:`undo_overrides` has set to what they were, or which do nothing then)."""
    return [
        text
        for text in config_differences(dict(recorded), dict(now))
        if not (text.split(":", 1)[0] in _ADDED and "absent from the record" in text)
    ]


def config_differences(recorded: Any, now: Any, prefix: str = "") -> list[str]:
    """The dotted names where two configurations (nested dicts) differ, with both values."""
    if isinstance(recorded, dict) and isinstance(now, dict):
        found = []
        for key in sorted(set(recorded) | set(now), key=str):
            name = f"{prefix}.{key}" if prefix else str(key)
            if key not in now:
                found.append(f"{name}: {recorded[key]!r} in the record, absent now")
            elif key not in recorded:
                found.append(f"{name}: absent from the record, {now[key]!r} now")
            else:
                found += config_differences(recorded[key], now[key], name)
        return found
    return [] if recorded == now else [f"{prefix}: {recorded!r} in the record, {now!r} now"]


SHOWN_DIFFERENCES = 8


def snapshot_differences(then: Mapping[str, Any], now: Mapping[str, Any]) -> list[str]:
    """Where the simulator a snapshot was taken of (``then``, its configuration) differs
    from the one it is restored into (``now``), less the settings added since that change
    nothing here: a setting :data:`HISTORY` says was added, absent from ``then``, that
    decided nothing before (:data:`INERT`) or holds now what was in effect before. So a run
    stopped by one version of the code resumes exactly on a later one that only added
    settings; a later one that changed what the arenas do is refused."""
    flat_now = flat(dict(now))
    unchanged = {
        change.name
        for change in HISTORY
        if change.before is INERT
        or (change.before is not FROM_RECORD and flat_now.get(change.name) == change.before)
    }
    return [
        text
        for text in config_differences(dict(then), dict(now))
        if not ("absent from the record" in text and text.split(":", 1)[0] in unchanged)
    ]


def _sensors_as_recorded(config: SimConfig, recorded: Mapping[str, Any]) -> SimConfig:
    """``config`` with the sensors off that are off in ``recorded``: a trainer asks for the
    observations it reads (protocol 1.10, :meth:`SimConfig.observing`), so a record's sensors
    may be off that no override names. A sensor on in the record and off here stays a
    difference."""
    on = [
        section.OBSERVATION
        for name, section in config.sensor_sections().items()
        if section.enabled and _recorded_on(recorded.get(name))
    ]
    return config.observing(tuple(on))


# The ego vector's fields as an override names them (a trainer asks for them by a request's
# field since protocol 1.11; a record of before names them here, if at all).
EGO_FIELDS_SETTING = "ego_vector.fields"


def _ego_fields_as_recorded(
    config: SimConfig, overrides: Mapping[str, PlainValue], recorded: Mapping[str, Any]
) -> SimConfig:
    """``config`` with the record's ego fields where no override names them: a trainer asks
    for the ego fields it reads (protocol 1.11, :meth:`SimConfig.reading_ego_fields`), so a
    record's may differ from its preset's that no override names."""
    section = recorded.get("ego_vector")
    fields = section.get("fields") if isinstance(section, dict) else None
    if (
        not config.ego_vector.enabled
        or EGO_FIELDS_SETTING in overrides
        or not isinstance(fields, list)
        or tuple(fields) == config.ego_vector.fields
    ):
        return config
    return config.reading_ego_fields(tuple(fields))


def _recorded_on(section: Any) -> bool:
    # A section the record lacks (a sensor added since) is as the preset has it.
    return not isinstance(section, dict) or section.get("enabled", True) is not False


def as_recorded(
    preset: str, overrides: Mapping[str, PlainValue], recorded: Mapping[str, Any]
) -> SimConfig:
    """The simulator an episode record was made on (``recorded``: the configuration its header
    keeps; a replay that asks "what if" puts its changes in both), from ``preset`` with
    ``overrides`` (the record's) and the settings that undo what changed since
    (:func:`undo_overrides`). :class:`ConfigError` where it would still differ from the
    record, naming the differences."""
    now = make_config(preset, overrides)
    undo = undo_overrides(recorded, as_json(now))
    config = _sensors_as_recorded(
        _ego_fields_as_recorded(
            make_config(preset, {**overrides, **undo}) if undo else now, overrides, recorded
        ),
        recorded,
    )
    differences = sorted(
        unexplained_differences(recorded, as_json(config)),
        key=lambda text: not text.startswith("preset:"),  # the preset's name first
    )
    if differences:
        shown = "; ".join(differences[:SHOWN_DIFFERENCES])
        more = len(differences) - SHOWN_DIFFERENCES
        raise ConfigError(
            f"preset {preset} with the record's overrides resolves to another simulator than "
            f"the record's: {shown}" + (f" (and {more} more)" if more > 0 else "")
        )
    return config


def requested_config(
    preset: str,
    overrides: Mapping[str, PlainValue],
    recorded: Mapping[str, Any] | None = None,
    observations: Sequence[str] = (),
    ego_fields: Sequence[str] = (),
    translated: Translated | None = None,
) -> SimConfig:
    """The simulator a trainer asks for, in process or of a server: ``preset`` with
    ``translated``'s settings (a configuration in another simulator's words,
    :mod:`.translations`) and ``overrides`` over them, or with ``recorded`` (an episode
    record's configuration) the one that record was made on (:func:`as_recorded`); its ego
    vector holding ``ego_fields`` where it names some
    (:meth:`SimConfig.reading_ego_fields`), with only the sensors of ``observations`` on where
    it names some (:meth:`SimConfig.observing`). :class:`ConfigError` where it cannot be
    built, said in the words ``translated`` was given in."""
    try:
        if translated is not None:
            overrides = {**translated.overrides, **overrides}
        named = overrides.get(EGO_FIELDS_SETTING)
        if ego_fields and isinstance(named, (list, tuple)) and tuple(named) != tuple(ego_fields):
            raise ConfigError(
                f"{EGO_FIELDS_SETTING} = {list(named)} is set, and the trainer asks for the ego "
                f"fields {list(ego_fields)}: one or the other"
            )
        if recorded is None:
            config = make_config(preset, overrides)
        else:
            config = as_recorded(preset, overrides, recorded)
        return config.reading_ego_fields(tuple(ego_fields)).observing(tuple(observations))
    except ConfigError as error:
        if translated is None:
            raise
        raise ConfigError(translated.in_users_words(str(error))) from None
