"""Baseline drivers that act only on what an agent observes: rule-based drivers and random.

They need no simulator: a trainer anywhere can run them against any overtake environment,
in-process or remote. All take batches (B, ...) so one call drives a whole vector env. There is
a rule-based driver per kind of observation (:class:`RuleDriver` for the LIDAR and ego vector
of min2018, :class:`GridRuleDriver` for Ho's occupancy grid, :class:`MapRuleDriver` for Fayjie
et al.'s LIDAR map); they choose lanes the same way (:func:`change_lanes`).

:class:`RuleDriver` is meant as a fair opponent for learned policies. It reads the LIDAR and
the ego vector, whose fields it is told (``ego_fields``, the preset's ``ego_vector.fields``):

- it accelerates (cruise up) whenever it is below the limit (``cruise_max_kmh``: its cruise
  target if the ego vector has one, else its speed), unless it has a forward warning; adaptive
  cruise control and emergency braking beneath it handle the car ahead;
- when its own lane is blocked (a car within ``blocked_ahead_m``) it changes to a neighbouring
  lane that offers at least ``better_by_m`` more free distance ahead, if its LIDAR shows that
  lane empty from ``gap_behind_m`` behind to ``gap_ahead_m`` ahead of the car's centre, it has
  no side warning there (if the ego vector has warnings) and the action mask allows the move;
  with both sides good it takes the one with more room, left on a tie (overtaking on the left).

Free distance in a lane is read from the LIDAR points in that lane's strip (``lane_width_m``
wide, centred on the lane), in the car's frame: x forward, y left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT


@dataclass(frozen=True, slots=True)
class RuleDriverConfig:
    """Thresholds of the rule-based driver (metres are along the road from the car's centre)."""

    cruise_max_kmh: float = 80.0
    lane_width_m: float = 3.5
    blocked_ahead_m: float = 40.0
    better_by_m: float = 15.0
    gap_ahead_m: float = 10.0
    gap_behind_m: float = 15.0


def change_lanes(
    action: np.ndarray,
    blocked: np.ndarray,
    own: np.ndarray,
    left: tuple[np.ndarray, np.ndarray],
    right: tuple[np.ndarray, np.ndarray],
    action_mask: np.ndarray,
    better_by_m: float,
) -> np.ndarray:
    """``action`` (B,) with a lane change where the own lane is ``blocked``: to a side whose
    (room, clear) pair is clear, that the mask allows and whose room beats the ``own`` lane's
    by ``better_by_m``; the side with more room, left on a tie. Every rule driver chooses its
    lane so."""
    room_left = np.where(left[1] & (action_mask[:, LANE_LEFT] > 0), left[0], -np.inf)
    room_right = np.where(right[1] & (action_mask[:, LANE_RIGHT] > 0), right[0], -np.inf)
    go_left = blocked & (room_left >= own + better_by_m) & (room_left >= room_right)
    go_right = blocked & ~go_left & (room_right >= own + better_by_m)
    action = np.where(go_right, LANE_RIGHT, action)
    return np.where(go_left, LANE_LEFT, action).astype(np.int64)


class RuleDriver:
    def __init__(
        self,
        config: RuleDriverConfig = RuleDriverConfig(),
        ray_count: int = 360,
        max_range_m: float = 80.0,
        *,
        ego_fields: tuple[str, ...],
    ) -> None:
        """``ego_fields``: the ego vector's columns, as the behaviour spec names them."""
        self.config = config
        self.max_range_m = max_range_m
        # The ego vector's columns the driver reads (None where the preset has no such field).
        target = "cruise_target_mps" if "cruise_target_mps" in ego_fields else "speed_mps"
        if target not in ego_fields:
            raise ValueError(
                f"the rule-based driver reads its speed or cruise target from the ego vector; "
                f"its fields are {list(ego_fields)}"
            )
        self._limit_column = ego_fields.index(target)

        def column(name: str) -> int | None:
            return ego_fields.index(name) if name in ego_fields else None

        self._left_warning = column("left_warning")
        self._right_warning = column("right_warning")
        self._forward_warning = column("forward_warning")
        angles = np.arange(ray_count) * (2.0 * np.pi / ray_count)
        self._cos, self._sin = np.cos(angles), np.sin(angles)

    def free_distance(self, lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per lane offset (right, own, left): free metres ahead and whether the side is clear.

        lidar: (B, R). Returns free (B, 3) and clear (B, 3) (beside the car, for a change).
        """
        cfg = self.config
        hit = lidar < self.max_range_m - 1e-3
        x = lidar * self._cos
        y = lidar * self._sin
        offsets = np.array([-1.0, 0.0, 1.0]) * cfg.lane_width_m
        in_lane = (np.abs(y[:, None, :] - offsets[None, :, None]) < cfg.lane_width_m / 2) & hit[
            :, None, :
        ]  # (B, 3, R)
        ahead = in_lane & (x[:, None, :] > 0.0)
        free = np.where(ahead, x[:, None, :], self.max_range_m).min(axis=-1)
        beside = in_lane & (x[:, None, :] > -cfg.gap_behind_m) & (x[:, None, :] < cfg.gap_ahead_m)
        return free, ~beside.any(axis=-1)

    def act(self, lidar: np.ndarray, ego: np.ndarray, action_mask: np.ndarray) -> np.ndarray:
        """Actions (B,) for observations lidar (B, R), ego (B, E) and action masks (B, 5)."""
        cfg = self.config
        lidar, ego = np.atleast_2d(lidar), np.atleast_2d(ego)
        action_mask = np.atleast_2d(action_mask)
        free, clear = self.free_distance(lidar)
        if self._right_warning is not None:
            clear[:, 0] &= ego[:, self._right_warning] < 0.5
        if self._left_warning is not None:
            clear[:, 2] &= ego[:, self._left_warning] < 0.5
        own = free[:, 1]
        speed_up = ego[:, self._limit_column] < cfg.cruise_max_kmh / 3.6 - 1e-3
        if self._forward_warning is not None:
            speed_up &= ego[:, self._forward_warning] < 0.5
        return change_lanes(
            np.where(speed_up, CRUISE_UP, KEEP),
            own < cfg.blocked_ahead_m,
            own,
            (free[:, 2], clear[:, 2]),
            (free[:, 0], clear[:, 0]),
            action_mask,
            cfg.better_by_m,
        )


@dataclass(frozen=True, slots=True)
class GridRuleDriverConfig:
    """Thresholds of the rule-based driver on an occupancy grid (metres from the car's centre
    along the road)."""

    half_length_m: float = 2.25
    blocked_ahead_m: float = 12.0
    better_by_m: float = 4.0
    clear_ahead_m: float = 4.0
    clear_behind_m: float = 6.0


class GridRuleDriver:
    """The rule-based driver for presets that observe Ho's occupancy grid (``grid``: rows from
    ``ahead_m`` ahead to ``behind_m`` behind, columns the lane to the left, its own, the lane to
    the right; 1 occupied, 0 free, anything else off the road) and no speed:

    - it accelerates in every decision (the simulator's safety rule keeps it behind the car
      ahead);
    - when a car in its own lane is within ``blocked_ahead_m`` of its front bumper, it changes
      to a neighbouring lane that is on the road, free from ``clear_behind_m`` behind its centre
      to ``clear_ahead_m`` ahead of its front, and offers at least ``better_by_m`` more free
      room ahead (the one with more room, left on a tie), if the action mask allows it.
    """

    def __init__(
        self,
        config: GridRuleDriverConfig = GridRuleDriverConfig(),
        ahead_m: float = 20.0,
        behind_m: float = 10.0,
        cells: int = 36,
    ) -> None:
        self.config = config
        cell_m = (ahead_m + behind_m) / cells
        top = ahead_m - cell_m * np.arange(cells)  # each row's far edge, m ahead of the centre
        bottom = top - cell_m
        front = config.half_length_m
        # Free room ahead of the front bumper if a row is the first occupied one ahead.
        self._room_if_first = np.where(bottom >= front, bottom - front, np.inf)
        self._room_max = ahead_m - front
        self._beside = (top > -config.clear_behind_m) & (bottom < front + config.clear_ahead_m)

    def act(self, grid: np.ndarray, action_mask: np.ndarray) -> np.ndarray:
        """Actions (B,) for grids (B, cells, 3) (the latest frame) and action masks (B, 5)."""
        cfg = self.config
        grid, action_mask = np.atleast_3d(grid), np.atleast_2d(action_mask)
        occupied = grid == 1
        room = np.where(occupied, self._room_if_first[None, :, None], np.inf).min(axis=1)
        room = np.minimum(room, self._room_max)  # (B, 3): left, own, right
        on_road = (grid == 0) | occupied
        clear = ~(occupied & self._beside[None, :, None]).any(axis=1) & on_road.all(axis=1)
        own = room[:, 1]
        return change_lanes(
            np.full(own.shape, CRUISE_UP),
            own < cfg.blocked_ahead_m,
            own,
            (room[:, 0], clear[:, 0]),
            (room[:, 2], clear[:, 2]),
            action_mask,
            cfg.better_by_m,
        )


@dataclass(frozen=True, slots=True)
class MapRuleDriverConfig:
    """Thresholds of the rule-based driver on a LIDAR map (metres ahead of the car's centre)."""

    lane_width_m: float = 3.5
    half_length_m: float = 2.25
    brake_within_m: float = 30.0
    accelerate_beyond_m: float = 37.0
    better_by_m: float = 15.0
    clear_ahead_m: float = 8.0


class MapRuleDriver:
    """The rule-based driver for presets that observe Fayjie et al.'s LIDAR map (``lidar_map``:
    rows from ``ahead_m`` ahead to ``behind_m`` behind, columns from ``half_width_m`` left to as
    far right, nonzero where the scan returned) and nothing of their own speed:

    - it reads the free room ahead of its front bumper in its lane's strip and in the strips
      of the lanes either side;
    - when its lane is blocked within ``brake_within_m``, it changes to a neighbouring lane
      with at least ``better_by_m`` more room whose strip is free for ``clear_ahead_m`` ahead of
      the front bumper (the map shows nothing behind), if the action mask allows it, left on a
      tie; otherwise it brakes;
    - with more than ``accelerate_beyond_m`` free it accelerates, in between it keeps going.
    """

    def __init__(
        self,
        config: MapRuleDriverConfig = MapRuleDriverConfig(),
        cells: int = 80,
        ahead_m: float = 40.0,
        behind_m: float = 0.0,
        half_width_m: float = 20.0,
    ) -> None:
        self.config = config
        row_m = (ahead_m + behind_m) / cells
        column_m = 2.0 * half_width_m / cells
        near = ahead_m - row_m * (np.arange(cells) + 1)  # each row's near edge, m ahead
        self._room_if_first = np.where(
            near >= config.half_length_m, near - config.half_length_m, np.inf
        )
        self._room_max = ahead_m - config.half_length_m
        left = half_width_m - column_m * (np.arange(cells) + 0.5)  # column centres, m left
        # (3, cells): the columns of the lane to the left, the own lane and the lane to the right.
        offsets = np.array([1.0, 0.0, -1.0])[:, None] * config.lane_width_m
        self._strips = np.abs(left[None, :] - offsets) < config.lane_width_m / 2

    def act(self, lidar_map: np.ndarray, action_mask: np.ndarray) -> np.ndarray:
        """Actions (B,) for maps (B, cells, cells) (the latest frame) and masks (B, 5)."""
        cfg = self.config
        hits = np.atleast_3d(lidar_map) > 0
        action_mask = np.atleast_2d(action_mask)
        in_strip = (hits[:, None, :, :] & self._strips[None, :, None, :]).any(axis=-1)
        room = np.where(in_strip, self._room_if_first[None, None, :], np.inf).min(axis=-1)
        room = np.minimum(room, self._room_max)  # (B, 3): left, own, right
        clear = room > cfg.clear_ahead_m
        own = room[:, 1]
        blocked = own < cfg.brake_within_m
        action = np.where(own > cfg.accelerate_beyond_m, CRUISE_UP, KEEP)
        return change_lanes(
            np.where(blocked, CRUISE_DOWN, action),
            blocked,
            own,
            (room[:, 0], clear[:, 0]),
            (room[:, 2], clear[:, 2]),
            action_mask,
            cfg.better_by_m,
        )


class RandomDriver:
    """Uniformly random among the actions the mask allows."""

    def __init__(self, seed: int | None = None) -> None:
        self.rng = np.random.default_rng(seed)

    def act(
        self, lidar: np.ndarray | None, ego: np.ndarray | None, action_mask: np.ndarray
    ) -> np.ndarray:
        """Actions (B,) for action masks (B, 5); the observations are not read (None will do)."""
        mask = np.atleast_2d(action_mask).astype(bool)
        scores = np.where(mask, self.rng.random(mask.shape), -1.0)
        return scores.argmax(axis=1).astype(np.int64)
