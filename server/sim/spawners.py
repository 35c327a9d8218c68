"""Min et al.'s way for traffic to come onto the road and leave it (``traffic.entry =
"spawners"``): nothing is recycled, and the population rises and falls.

Their Unity scene (``Unity_SDK/Assets/VehicleSimulator/``, read for the numbers, none of it
copied): eight spawners (``Scripts/Vehicle1_Manager.cs`` .. ``Vehicle8_Manager.cs``), each
owning an equal share of the slider's count of cars (the first ``count % 8`` one more). Every
fixed step (0.02 s, ``ProjectSettings/TimeManager.asset``) a spawner adds the step to its
clock, draws a wait of 2-7 whole seconds (``Random.Range(2, 8)``, integers) and, once its
clock is past that wait, tries once and starts its clock again. The first step whose clock
passes 2 s is the 101st (the clock is a 32-bit float: after 100 steps it reads 1.9999987), and
from then on each step passes with one chance in six (only a wait of 2 is below a clock under
3 s): a try every 106 steps on average, 2.12 s (standard deviation 0.11 s), 0.47 tries a
second per spawner, 3.8 for the eight (:func:`attempt_interval_cdf` works it out from the
settings). A try places a car 70% of the time ahead of the host, 30-89 m (whole metres,
``Random.Range(30, 90)``), else behind it, 30-59 m (``Random.Range(-30, -60)``: Unity swaps
the bounds keeping the first inclusive), in a lane drawn evenly (``Random.Range(1, 6)``), if
the spawner holds fewer than its share and no car's centre lies within 10 along the road and
10 across (``Scene.unity``'s margins for all eight) of the spot. A car more than 100 from the
host in a straight line destroys itself, as do two cars that touch
(``Scripts/TargetManagement.cs``, ``range_`` 100 in ``Prefabs/Target_*.prefab``); a reset
destroys every car (``Scripts/VehicleAgent.cs``, ``AgentReset``).

Here (``traffic.spawner_*``): lengths in metres as the rest of the preset reads theirs, the
margin across in lane widths (their 10 over lanes 7 apart: the own lane and the next ones),
every vehicle's centre counted for the margin (agents' too: theirs never stand within 30 m of
a spot); the cars that leave and the tries are worked out once a decision (0.4 s), after its
frames, each spawner trying at most once a decision; at a reset each spawner's first try is
at a uniformly drawn point of one wait (theirs keep their clocks through a reset). Each
spawner's draws come from its first slot's row of the decision's uniforms (:mod:`.randomness`),
so an arena's episode depends on its seed and actions alone.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .randomness import U_ANCHOR, U_BEHAVIOUR, U_LANE, U_OFFSET, U_SIDE, U_SPAWNER_WAIT, U_SPEED
from .spawner_kernels import attempt_interval_s, leave_and_spawn

if TYPE_CHECKING:
    from .overtakes import OvertakeTracker
    from .road import Road
    from .state import SimState
    from .traffic.config import TrafficConfig
    from .vehicles import VehicleKinds


def attempt_interval_cdf(traffic: TrafficConfig) -> np.ndarray:
    """(K,) the chance that a spawner's next try comes within k + 1 fixed steps of
    ``traffic.spawner_step_s``, to 1 at the last.

    Each step the spawner's clock grows by a step, accumulated as Unity does in a 32-bit
    float, and the step tries where the clock exceeds a wait drawn evenly among the whole
    seconds of ``traffic.spawner_wait_s`` (first included, last excluded)."""
    first_s, end_s = traffic.spawner_wait_s
    waits_s = np.arange(first_s, end_s, dtype=np.float32)
    step = np.float32(traffic.spawner_step_s)
    steps = int(np.ceil(waits_s[-1] / step)) + 2  # the clock passes the longest wait by then
    clock_s = np.cumsum(np.full(steps, step, dtype=np.float32), dtype=np.float32)
    passes = (clock_s[:, None] > waits_s[None, :]).mean(axis=1)
    # The chance that no step before passes, times this one's.
    none_before = np.concatenate(([1.0], np.cumprod(1.0 - passes)[:-1]))
    cdf = np.cumsum(none_before * passes)
    last = int(np.argmax(passes >= 1.0))
    cdf = cdf[: last + 1]
    cdf[-1] = 1.0
    return cdf


def spawner_shares(count: int, spawners: int) -> np.ndarray:
    """(spawners,) how many cars each spawner keeps at most: an equal share of ``count``, the
    first ``count % spawners`` one more (their ``sliderval % 8 > k``)."""
    share, extra = divmod(count, spawners)
    return share + (np.arange(spawners) < extra).astype(np.int64)


class Spawners:
    """Min et al.'s spawners for every arena at once, in one compiled loop
    (:mod:`.spawner_kernels`); traffic slots are the spawners' in order, each its share."""

    def __init__(
        self,
        traffic: TrafficConfig,
        kinds: VehicleKinds,
        road: Road,
        agents: int,
        decision_period_s: float,
        tracker: OvertakeTracker,
    ) -> None:
        self.kinds = kinds
        self.agents = agents
        self.tracker = tracker
        self.decision_period_s = decision_period_s
        self.count = traffic.spawner_count
        self.keep_ahead_m = traffic.keep_ahead_m
        self.keep_behind_m = traffic.keep_behind_m
        self.slots = spawner_shares(traffic.resolved_vehicle_count, self.count)
        self.first = np.concatenate(([0], np.cumsum(self.slots)[:-1])).astype(np.int64)
        self.interval_cdf = attempt_interval_cdf(traffic)
        self.step_s = traffic.spawner_step_s
        self.ahead_share = traffic.spawner_ahead_share
        self.ahead_window_m = np.array(traffic.spawn_ahead_m, dtype=np.float64)
        self.behind_window_m = np.array(traffic.spawn_behind_m, dtype=np.float64)
        self.clearance_m = traffic.spawner_clearance_m
        self.clearance_across_m = traffic.spawner_clearance_lanes * road.lane_width_m
        self._lane_centre_y = road.centre_y(np.arange(road.lane_count))

    @property
    def mean_interval_s(self) -> float:
        """The spawners' mean time between tries (2.12 s with the authors' settings)."""
        steps = np.arange(1, self.interval_cdf.size + 1)
        chances = np.diff(self.interval_cdf, prepend=0.0)
        return float((steps * chances).sum() * self.step_s)

    def first_waits(self, rng: np.random.Generator) -> np.ndarray:
        """(S,) a new episode's time until each spawner's first try: a uniform point of one
        wait, drawn from ``rng`` (two draws a spawner, whether or not it holds slots)."""
        draws = rng.random((self.count, 2))
        return np.array(
            [
                fraction * attempt_interval_s(self.interval_cdf, self.step_s, uniform)
                for fraction, uniform in draws
            ]
        )

    def step(self, st: SimState, uniforms: np.ndarray) -> None:
        """This decision's departures and tries in every arena of ``st`` (uniforms: the
        decision's (A, V, UNIFORMS_PER_VEHICLE))."""
        spawned = np.zeros(st.active.shape, dtype=bool)
        k = self.kinds
        if leave_and_spawn(
            st.x_m, st.lane, st.target_lane, st.change_progress, st.y_m, st.speed_mps,
            st.desired_speed_mps, st.own_speed_mps, st.accel_mps2, st.kind, st.active,
            st.spawner_wait_s, self.agents, self.keep_ahead_m, self.keep_behind_m,
            k.half_length, k.half_width, uniforms, U_SIDE, U_ANCHOR, U_LANE, U_OFFSET,
            U_BEHAVIOUR, U_SPEED, U_SPAWNER_WAIT, self.decision_period_s, self.first,
            self.slots, self.interval_cdf, self.step_s, self.ahead_share, self.ahead_window_m,
            self.behind_window_m, self.clearance_m, self.clearance_across_m,
            self._lane_centre_y, k.behaviour_cdf, k.speed_lo, k.speed_hi, spawned,
        ):  # fmt: skip
            self.tracker.start(st, spawned)
