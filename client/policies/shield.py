"""A safety shield: before an action is taken, the actions the shield judges unsafe are masked.

The shield decides from what the car observes, its LIDAR and its own speed (the ego vector),
never the simulator's true state, so that it could run on a car. Its rule, fixed before any
run that measures it (issue 34) and not tuned on their results:

- **Lane changes** (Mirchevska et al., ITSC 2018: a learned lane-change policy behind a check
  of the gaps and relative speeds in the target lane; MOBIL's safety criterion, Treiber): a
  change to a side is unsafe where, in that lane, the nearest car ahead leaves a gap under
  ``min_gap_m + time_gap_s * v + horizon_s * c_ahead``, or the nearest car behind a gap under
  ``min_gap_m + time_gap_s * (v + c_behind) + horizon_s * c_behind``: a standstill gap, a time
  gap at the speed of whoever follows, and what the closing speed eats up while the change
  lasts (``horizon_s``, min2018's 2 s lane change).
- **Accelerating**: unsafe where the nearest car ahead in the car's own lane leaves a gap
  under ``min_gap_m + 2 * time_gap_s * v + horizon_s * c_own`` (a one-second time gap, and the
  closing over the horizon).
- Keeping the lane and slowing down are always allowed, so something always is.

``v`` is the car's speed (m/s, from the ego vector); a gap is bumper to return point along the
road (a LIDAR return's distance ahead or behind, less half the car's length); a region is a
lane's band of returns (lateral offset within half a lane width of that lane's centre, the
LIDAR being at the car's centre); ``c`` is how fast the gap in a region shrank between the
last two scans (the trainer stacks them; 0 where either scan saw nothing there, never
negative). Ho's and Fayjie et al.'s presets do not observe a LIDAR scan and the car's speed
(the grid, the camera and the LIDAR map): the shield refuses them, saying what it needs.

What the rule does not see: a car two lanes over that changes into the target lane at the same
time. Every collision left behind it in min2018-safe and the retired min2018-safe-both, before
issue 44, was of that kind (``overtake-collision-causes`` classifies a record's collisions;
bench/RESULTS.md). The shield's second half, ``--shield-watch`` (issue 46), is the simulator's
driver assistance watching each lane change through against every car in the target lane or
moving into it (:mod:`overtake.server.sim.lane_watch`): it sees the simulator's state, as the
car's own assistance would see its surroundings, and is a simulator setting
(``ego.lane_change_watch``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overtake.cli import UsageError
from overtake.protocol.messages import BehaviourSpec
from overtake.protocol.vocabulary import ACTION_COUNT, CRUISE_UP, LANE_LEFT, LANE_RIGHT

# The column the shield adds to each episode's row (and event to its record): how often it
# overrode the policy.
SHIELD_OVERRIDES = "shield_overrides"


@dataclass(frozen=True)
class ShieldRule:
    """The shield's thresholds (its rule is in the module's docstring)."""

    min_gap_m: float = 2.0
    time_gap_s: float = 0.5
    horizon_s: float = 2.0


class Shield:
    """The shield for an environment described by ``spec`` (see the module's docstring)."""

    def __init__(self, spec: BehaviourSpec, rule: ShieldRule = ShieldRule()) -> None:
        missing = []
        if not spec.has("lidar"):
            missing.append("a LIDAR scan (observation 'lidar')")
        if not spec.has("ego") or "speed_mps" not in spec.observation("ego").columns:
            missing.append("the car's speed (ego vector column 'speed_mps')")
        if spec.road is None or spec.car is None:
            missing.append("the road's lane width and the car's length (protocol 1.5's spec)")
        if missing:
            raise UsageError(
                f"the safety shield decides from a LIDAR scan and the car's speed; preset "
                f"{spec.preset}'s agents observe {', '.join(o.name for o in spec.observations)}"
                f", without {' and '.join(missing)}"
            )
        lidar = spec.observation("lidar")
        assert lidar.reach is not None and spec.road is not None and spec.car is not None
        self.rule = rule
        self.max_range_m = lidar.reach.range_m
        self.speed_column = spec.observation("ego").columns.index("speed_mps")
        self.period_s = spec.decision_period_s
        self.half_length_m = spec.car.length_m / 2
        self.lane_width_m = spec.road.lane_width_m
        angles = np.arange(lidar.shape[0]) * (2 * np.pi / lidar.shape[0])
        self._cos, self._sin = np.cos(angles), np.sin(angles)

    def _regions(self, scan: np.ndarray) -> dict[str, np.ndarray]:
        """(N,) nearest gaps (m; inf: nothing there) of one scan (N, rays) per region: own
        lane ahead, and each side's lane ahead and behind."""
        seen = scan < self.max_range_m - 1e-3
        x, y = scan * self._cos, scan * self._sin
        gap = np.abs(x) - self.half_length_m
        ahead = x >= 0.0
        half, w = 0.5 * self.lane_width_m, self.lane_width_m
        bands = {
            "own": np.abs(y) < half,
            "left": (y > half) & (y < half + w),
            "right": (y < -half) & (y > -half - w),
        }

        def nearest(where: np.ndarray) -> np.ndarray:
            return np.where(seen & where, gap, np.inf).min(axis=1)

        out = {"own_ahead": nearest(bands["own"] & ahead)}
        for side in ("left", "right"):
            out[f"{side}_ahead"] = nearest(bands[side] & ahead)
            out[f"{side}_behind"] = nearest(bands[side] & ~ahead)
        return out

    def mask(self, lidar: np.ndarray, ego: np.ndarray) -> np.ndarray:
        """(N, actions) int8, 1 where the shield allows the action: ``lidar`` the stacked
        scans (N, stack, rays), oldest first; ``ego`` the latest ego vectors (N, fields)."""
        lidar = np.asarray(lidar, dtype=np.float64)
        now = self._regions(lidar[:, -1])
        before = self._regions(lidar[:, -2]) if lidar.shape[1] > 1 else now
        closing = {}
        for name, gap in now.items():
            both = np.isfinite(gap) & np.isfinite(before[name])
            shrank = np.where(both, before[name], 0.0) - np.where(both, gap, 0.0)
            closing[name] = np.maximum(shrank / self.period_s, 0.0)
        rule = self.rule
        v = np.maximum(np.asarray(ego, dtype=np.float64)[:, self.speed_column], 0.0)
        allowed = np.ones((lidar.shape[0], ACTION_COUNT), dtype=np.int8)
        for side, action in (("left", LANE_LEFT), ("right", LANE_RIGHT)):
            c_ahead, c_behind = closing[f"{side}_ahead"], closing[f"{side}_behind"]
            unsafe = now[f"{side}_ahead"] < (
                rule.min_gap_m + rule.time_gap_s * v + rule.horizon_s * c_ahead
            )
            unsafe |= now[f"{side}_behind"] < (
                rule.min_gap_m + rule.time_gap_s * (v + c_behind) + rule.horizon_s * c_behind
            )
            allowed[unsafe, action] = 0
        too_close = now["own_ahead"] < (
            rule.min_gap_m + 2.0 * rule.time_gap_s * v + rule.horizon_s * closing["own_ahead"]
        )
        allowed[too_close, CRUISE_UP] = 0
        return allowed


def overridden(q: np.ndarray, env_mask: np.ndarray, shield_mask: np.ndarray) -> np.ndarray:
    """(N,) bool: where the network's greedy choice among the actions the environment allows
    is one the shield forbids (the shield overrode it)."""
    allowed = np.asarray(env_mask).astype(bool)
    greedy = np.where(allowed, q, -np.inf).argmax(axis=1)
    return np.asarray(shield_mask)[np.arange(len(greedy)), greedy] == 0


class ShieldedActing:
    """A shield in front of a greedy policy over ``num_envs`` environments: the mask it acts
    under, and per environment how often it overrode the policy in the episode under way
    (evaluation's ``shield_overrides`` column)."""

    def __init__(self, shield: Shield, num_envs: int) -> None:
        self.shield = shield
        self.overrides = np.zeros(num_envs, dtype=np.int64)
        self.last_overridden = np.zeros(num_envs, dtype=bool)

    def mask(
        self, stacked: dict[str, np.ndarray], env_mask: np.ndarray, starting: np.ndarray
    ) -> np.ndarray:
        """The environments' ``env_mask`` with the shield's, judged on the ``stacked`` frames
        (their ``lidar`` scans and latest ``ego``); the counts of episodes ``starting`` begin
        at 0."""
        self.overrides[np.asarray(starting, dtype=bool)] = 0
        return np.asarray(env_mask) & self.shield.mask(stacked["lidar"], stacked["ego"])

    def count(self, q: np.ndarray, env_mask: np.ndarray, mask: np.ndarray) -> None:
        """Note the decisions where the policy's greedy choice (``q``) was overridden
        (``last_overridden``: this decision's, per environment)."""
        self.last_overridden = overridden(q, env_mask, mask)
        self.overrides += self.last_overridden

    def episode_extras(self, env: int) -> dict[str, float]:
        return {SHIELD_OVERRIDES: float(self.overrides[env])}
