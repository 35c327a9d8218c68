"""Driver assistance: what the controlled car does beneath the agent's decisions.

Min et al.'s agents act at the level of a driver-assistance system (DAS): adaptive cruise
control holds the cruise target (the IDM of :mod:`.traffic.car_following`, with the car's own
parameters), autonomous emergency braking takes over when the time to collision gets short,
lane keeping holds the lane, and a lane change, once asked for, is a smooth lateral move.
Warnings (:class:`DriverWarnings`, the authors' code's left, right and forward warnings) say
when a lane change to a side, or more speed, is dangerous now; with ``ego.lane_change_check``
driver assistance also refuses a lane change against a side warning. :class:`EgoConfig` holds
the car's body and all of these parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Literal

import numpy as np

from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP

from . import kernels
from .ahead import CarsAhead, cars_ahead
from .lane_watch import LaneChangeWatch
from .units import KMH
from .validation import check, check_flag, check_range

if TYPE_CHECKING:
    from .state import SimState
    from .traffic.car_following import Following
    from .vehicles import VehicleKinds


@dataclass(frozen=True, slots=True)
class EgoConfig:
    """The controlled car: DAS functions (adaptive cruise, lane keeping, AEB) under the actions."""

    cruise_min_kmh: float = 40.0
    cruise_max_kmh: float = 80.0
    cruise_step_kmh: float = 5.0
    # What the cruise actions move (Min et al. §II.C): "current" sets the target to the current
    # speed plus or minus the step (keep: the current speed), so the car stays as slow as a car
    # ahead made it until the agent accelerates; "remembered" moves a target that is kept
    # between decisions, so the car returns to it by itself.
    cruise_mode: Literal["current", "remembered"] = "current"
    initial_speed_kmh: float = 60.0
    length_m: float = 4.5
    width_m: float = 1.8
    # Adaptive cruise control: a speed controller that closes the gap to the cruise target with
    # this time constant (within max_accel_mps2 and comfort_decel_mps2), limited by an IDM's
    # distance keeping to the car ahead with these parameters (chosen here: the paper's cruise
    # control reaches v + 5 km/h about as fast as the car can accelerate).
    cruise_time_constant_s: float = 0.5
    time_headway_s: float = 1.2
    min_gap_m: float = 2.0
    max_accel_mps2: float = 2.0
    comfort_decel_mps2: float = 3.0
    # Autonomous emergency braking: full braking when the time to collision falls below this.
    aeb_time_to_collision_s: float = 1.5
    aeb_decel_mps2: float = 8.0
    # Ho's emergency brake (2018, §6.2: "a brake applied" with the car in front slower by 20
    # km/h or more), counted as ``emergency_brake_count`` says: "deliberate" counts a decision
    # in which some frame braked at least emergency_decel_mps2 with the car ahead slower by at
    # least emergency_speed_diff_kmh (a reading of the thesis); "forced" counts, frame by frame,
    # the safety rule of speed steps taking the car ahead's speed when that car is slower by
    # more than emergency_speed_diff_kmh (his code's hard_brake_count, car.py: the brake his
    # car is forced into; speed_control "speed_steps" only).
    emergency_brake_count: Literal["deliberate", "forced"] = "deliberate"
    emergency_decel_mps2: float = 1.0
    emergency_speed_diff_kmh: float = 20.0
    lane_change_duration_s: float = 2.0
    # A side warning: a vehicle in the lane on that side, or moving into it, from
    # lane_change_clear_behind_m behind the rear bumper to lane_change_clear_ahead_m ahead of
    # the front bumper, each window growing by the speed at which a car there closes in times
    # lane_change_closing_time_s (a car 10 m/s faster behind needs 10 m more); or no lane there.
    lane_change_clear_ahead_m: float = 2.0
    lane_change_clear_behind_m: float = 4.0
    lane_change_closing_time_s: float = 1.0
    # The forward warning: a car ahead, no faster than the agent, closer than this many seconds
    # at the current speed, plus min_gap_m (the "two-second rule"; chosen here: the authors'
    # code warns when its cruise control follows a car ahead, and gives no distance).
    forward_warning_time_s: float = 2.0
    # True (Min et al.'s code, VehicleAgent.cs: a change starts only with that side's warning
    # off; their README's "Side warning: No lane change"): driver assistance refuses to start
    # a lane change against a side warning, and the car keeps its lane (the action applied is
    # keep). False: the car starts it and may collide. Either way acting against a warning
    # costs the reward's "warning" term.
    lane_change_check: bool = True
    # Whether the action mask marks the lane changes the check would refuse (True), or only
    # those that cannot be done at all: no lane there, or a change under way (False: Min et
    # al.'s agent chooses among all five actions and its car refuses; a mask that carried the
    # side warnings would tell a camera-only network of the cars beside it).
    mask_refusals: bool = False
    # Driver assistance that watches a lane change through (:mod:`.lane_watch`, issue 46;
    # chosen here, the shield's option, off in the papers' presets, whose code has none): a
    # change starts, goes on past the lane marking, or turns back, by whether each car in the
    # target lane or moving into it could stop closing in, reacting after watch_response_s
    # and braking at watch_brake_mps2 (UN R79's 0.4 s and 3 m/s^2), with min_gap_m left; and
    # a car ahead that closing in on would take more than comfort_decel_mps2 is met by as hard
    # a brake as it needs (to aeb_decel_mps2).
    lane_change_watch: bool = False
    watch_response_s: float = 0.4
    watch_brake_mps2: float = 3.0
    # How the agents' speed is controlled: "cruise" (Min et al.: the actions move a cruise
    # target that adaptive cruise control and emergency braking hold, above), or "speed_steps"
    # (Ho 2018, §4 and his code): accelerate and decelerate change the speed by
    # speed_step_kmh in every physics frame, keep holds it, within cruise_min_kmh and
    # cruise_max_kmh; the frames between decisions follow ``skipped_frames``; and a safety
    # rule stands in for cruise control: with a vehicle ahead closer than safety_gap_m the
    # car cannot accelerate, and if that vehicle is slower it takes its speed at once (an
    # emergency brake where the difference is large).
    speed_control: Literal["cruise", "speed_steps"] = "cruise"
    speed_step_kmh: float = 1.0
    # What the frames after a decision's first do (speed_steps): "table3" as Ho's thesis
    # (Table 3): accelerate -> accelerate, decelerate -> accelerate, left / right / keep ->
    # keep; "repeat" as his code: the decision's speed action again (a lane change: keep).
    skipped_frames: Literal["table3", "repeat"] = "table3"
    safety_gap_m: float = 8.0
    # The action applied as the car drove it (speed_steps only; Ho's code,
    # players/deep_traffic_player.py, where car.move returns what the car did and the player
    # writes it over the agent's action): in the decision's first frame, with a vehicle ahead
    # within safety_gap_m, accelerate is applied as keep, and accelerate, keep or a lane
    # change (the car still changes lanes) as decelerate where that vehicle is slower (the
    # safety rule takes its speed); the skipped frames then repeat that speed action, not
    # the one chosen (his action_cache). False: the action applied is the one chosen, a
    # refused lane change keep.
    applied_as_driven: bool = False

    def __post_init__(self) -> None:
        check_range("ego.cruise_min_kmh", self.cruise_min_kmh, 0.0, 300.0)
        check_range("ego.cruise_max_kmh", self.cruise_max_kmh, self.cruise_min_kmh, 300.0)
        check_range("ego.cruise_step_kmh", self.cruise_step_kmh, 0.0, 50.0, low_open=True)
        check_range(
            "ego.initial_speed_kmh",
            self.initial_speed_kmh,
            self.cruise_min_kmh,
            self.cruise_max_kmh,
        )
        check_range("ego.length_m", self.length_m, 2.0, 20.0)
        check_range("ego.width_m", self.width_m, 1.0, 4.0)
        check_range("ego.cruise_time_constant_s", self.cruise_time_constant_s, 0.05, 10.0)
        check_range("ego.time_headway_s", self.time_headway_s, 0.1, 5.0)
        check_range("ego.min_gap_m", self.min_gap_m, 0.5, 20.0)
        check_range("ego.max_accel_mps2", self.max_accel_mps2, 0.1, 10.0)
        check_range("ego.comfort_decel_mps2", self.comfort_decel_mps2, 0.1, 10.0)
        check_range("ego.aeb_time_to_collision_s", self.aeb_time_to_collision_s, 0.0, 10.0)
        check_range("ego.aeb_decel_mps2", self.aeb_decel_mps2, 0.1, 15.0)
        check_range("ego.emergency_decel_mps2", self.emergency_decel_mps2, 0.1, 15.0)
        check_range("ego.emergency_speed_diff_kmh", self.emergency_speed_diff_kmh, 0.0, 300.0)
        check_range("ego.lane_change_duration_s", self.lane_change_duration_s, 0.01, 10.0)
        check_range("ego.lane_change_clear_ahead_m", self.lane_change_clear_ahead_m, 0.0, 100.0)
        check_range("ego.lane_change_clear_behind_m", self.lane_change_clear_behind_m, 0.0, 100.0)
        check_range("ego.lane_change_closing_time_s", self.lane_change_closing_time_s, 0.0, 10.0)
        check_range("ego.forward_warning_time_s", self.forward_warning_time_s, 0.0, 10.0)
        check(
            self.cruise_mode in ("current", "remembered"),
            "ego.cruise_mode",
            self.cruise_mode,
            "current or remembered",
        )
        check_flag("ego.lane_change_check", self.lane_change_check)
        check_flag("ego.mask_refusals", self.mask_refusals)
        check_flag("ego.lane_change_watch", self.lane_change_watch)
        check_range("ego.watch_response_s", self.watch_response_s, 0.0, 5.0)
        check_range("ego.watch_brake_mps2", self.watch_brake_mps2, 0.5, 15.0)
        check(
            self.speed_control in ("cruise", "speed_steps"),
            "ego.speed_control",
            self.speed_control,
            "cruise or speed_steps",
        )
        check_range("ego.speed_step_kmh", self.speed_step_kmh, 0.0, 50.0, low_open=True)
        # The watch's fail-safe lowers the acceleration cruise control gives; speed steps set
        # the speed itself, so the brake would silently do nothing.
        check(
            not (self.lane_change_watch and self.speed_control == "speed_steps"),
            "ego.lane_change_watch",
            self.lane_change_watch,
            "off with ego.speed_control = speed_steps (its fail-safe brakes through cruise "
            "control)",
        )
        check(
            self.skipped_frames in ("table3", "repeat"),
            "ego.skipped_frames",
            self.skipped_frames,
            "table3 or repeat",
        )
        check_range("ego.safety_gap_m", self.safety_gap_m, 0.0, 100.0)
        check(
            self.emergency_brake_count == "deliberate"
            or (self.emergency_brake_count == "forced" and self.speed_control == "speed_steps"),
            "ego.emergency_brake_count",
            self.emergency_brake_count,
            "deliberate, or forced with ego.speed_control = speed_steps (the brake its safety "
            "rule forces)",
        )
        check_flag("ego.applied_as_driven", self.applied_as_driven)
        check(
            not self.applied_as_driven or self.speed_control == "speed_steps",
            "ego.applied_as_driven",
            self.applied_as_driven,
            "off unless ego.speed_control = speed_steps (it reads that control's safety rule)",
        )


class CruiseControl:
    """The agents' cruise targets (``desired_speed_mps`` of their columns), within limits.

    Each frame an agent accelerates towards its target (``(target - speed) / time constant``,
    between ``-comfort_decel_mps2`` and ``max_accel_mps2``), and no more than the IDM's
    distance keeping to the car ahead allows (the IDM without its free-road term): in the
    physics frame's compiled loop, :func:`.traffic.kernels.follow_and_accelerate`, with these
    parameters."""

    def __init__(self, ego: EgoConfig, agents: int) -> None:
        self.min_mps = ego.cruise_min_kmh * KMH
        self.max_mps = ego.cruise_max_kmh * KMH
        self.from_current_speed = ego.cruise_mode == "current"
        self.time_constant_s = ego.cruise_time_constant_s
        self.max_accel_mps2 = ego.max_accel_mps2
        self.comfort_decel_mps2 = ego.comfort_decel_mps2
        self.agents = agents

    def adjust(self, st: SimState, change_mps: np.ndarray) -> None:
        """Set each agent's target to its current speed plus ``change_mps`` (A, N) ("current"
        mode), or move the kept target by it ("remembered"); clipped to the cruise range."""
        n = self.agents
        cruise = st.desired_speed_mps[:, :n]
        if self.from_current_speed:
            np.add(st.speed_mps[:, :n], change_mps, out=cruise)
        else:
            cruise += change_mps
        np.minimum(np.maximum(cruise, self.min_mps, out=cruise), self.max_mps, out=cruise)


class SpeedSteps:
    """Ho's speed control (``ego.speed_control = "speed_steps"``): each frame the agent's speed
    moves one step up, down or not at all, as its decision says for that frame, and the safety
    rule of his simulator keeps it behind the vehicle ahead. The speed it gives replaces the
    one cruise control and the IDM work out (still computed: MOBIL reads the agents'
    accelerations)."""

    # The speed command of each action (keep, accelerate, decelerate, left, right) in the
    # decision's first frame, and in the frames after it under each ``skipped_frames`` rule.
    FIRST: ClassVar[np.ndarray] = np.array([0, 1, -1, 0, 0], dtype=np.int64)
    SKIPPED: ClassVar[dict[str, np.ndarray]] = {
        "table3": np.array([0, 1, 1, 0, 0], dtype=np.int64),
        "repeat": np.array([0, 1, -1, 0, 0], dtype=np.int64),
    }

    def __init__(self, ego: EgoConfig, agents: int) -> None:
        self.step_mps = ego.speed_step_kmh * KMH
        self.min_mps = ego.cruise_min_kmh * KMH
        self.max_mps = ego.cruise_max_kmh * KMH
        self.safety_gap_m = ego.safety_gap_m
        self.skipped = self.SKIPPED[ego.skipped_frames]
        self.agents = agents

    def commands(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(A, N) speed commands (-1, 0, +1) of the decision's first frame and of the others."""
        return self.FIRST[actions], self.skipped[actions]

    def as_driven(self, st: SimState, following: Following, applied: np.ndarray) -> None:
        """Rewrite the (A, N) actions ``applied`` as the car drove them in this frame
        (``ego.applied_as_driven``, Ho's ``players/deep_traffic_player.py``): with a vehicle
        ahead within the safety gap, accelerate is keep; with that vehicle slower, accelerate,
        keep and a lane change are decelerate (his ``car.move``: an action the safety rule
        does not allow becomes the first it allows, keep before decelerate). Before the
        frame's speeds are integrated (the rule's own test, :func:`.kernels.speed_steps`)."""
        n = self.agents
        near = following.has_leader[:, :n] & (following.gap_m[:, :n] < self.safety_gap_m)
        slower = near & (following.leader_speed_mps[:, :n] < st.speed_mps[:, :n])
        applied[near & (applied == CRUISE_UP)] = KEEP
        applied[slower] = CRUISE_DOWN

    def speeds(
        self,
        st: SimState,
        following: Following,
        command: np.ndarray,
        more_than_mps: float,
        new_speed: np.ndarray,
        forced: np.ndarray,
    ) -> None:
        """The agents' speeds at the end of this frame, given its commands (A, N), into the
        agent columns of ``new_speed`` (A, V); ``forced`` (A, N) marks those the safety rule set
        to a car ahead slower by more than ``more_than_mps`` this frame (Ho's
        ``hard_brake_count``, ``car.py``). One compiled loop (:func:`.kernels.speed_steps`)."""
        kernels.speed_steps(
            st.speed_mps, following.has_leader, following.gap_m, following.leader_speed_mps,
            command, self.step_mps, self.min_mps, self.max_mps, self.safety_gap_m,
            more_than_mps, new_speed, forced,
        )  # fmt: skip


class EmergencyBraking:
    """Autonomous emergency braking: an agent closing in on its leader brakes at
    ``decel_mps2`` once the gap is under ``time_to_collision_s`` of closing (applied in the
    physics frame's compiled loop, :func:`.traffic.kernels.follow_and_accelerate`)."""

    def __init__(self, ego: EgoConfig, agents: int) -> None:
        self.time_to_collision_s = ego.aeb_time_to_collision_s
        self.decel_mps2 = ego.aeb_decel_mps2
        self.agents = agents


class LaneChangeAssist:
    """Starts the agents' lane changes, and says which it would start now.

    A change needs a lane on that side and no change under way; with ``ego.lane_change_check``
    also a clear side (:meth:`side_clear`), and of two agents cleared into the same gap at the
    same decision only the lower-numbered one goes; with ``ego.lane_change_watch`` also a
    target lane the watch's rule finds safe (:mod:`.lane_watch`).
    """

    def __init__(self, ego: EgoConfig, kinds: VehicleKinds, lane_count: int, agents: int) -> None:
        self.ego = ego
        self.kinds = kinds
        self.lane_count = lane_count
        self.agents = agents
        self.watch = LaneChangeWatch(ego, kinds, agents) if ego.lane_change_watch else None

    def possible_lanes(self, st: SimState) -> tuple[np.ndarray, np.ndarray]:
        """(A, N) bool each, left and right: a lane there."""
        lane = st.lane[:, : self.agents]
        return lane < self.lane_count - 1, lane > 0

    def possible(self, st: SimState) -> tuple[np.ndarray, np.ndarray]:
        """(A, N) bool each, left and right: a lane there and no change under way."""
        n = self.agents
        left, right = self.possible_lanes(st)
        idle = st.target_lane[:, :n] == st.lane[:, :n]
        return idle & left, idle & right

    def allowed(self, st: SimState) -> tuple[np.ndarray, np.ndarray]:
        """(A, N) bool each, left and right: a change that would start now if asked for."""
        left, right = self.possible(st)
        if self.ego.lane_change_check:
            clear = self.side_clear(st)
            left &= clear[..., 1]
            right &= clear[..., 0]
        if self.watch is not None:
            left &= self._watch_allows(st, left, 1)
            right &= self._watch_allows(st, right, -1)
        return left, right

    def _watch_allows(self, st: SimState, asked: np.ndarray, side: int) -> np.ndarray:
        """(A, N): where the watch would let a change to ``side`` (+1 left) start now."""
        assert self.watch is not None
        n = self.agents
        if not asked.any():
            return asked
        saved = st.target_lane[:, :n].copy()
        st.target_lane[:, :n] += np.where(asked, side, 0)
        try:
            return ~self.watch.unsafe(st)
        finally:
            st.target_lane[:, :n] = saved

    def start(self, st: SimState, want_left: np.ndarray, want_right: np.ndarray) -> np.ndarray:
        """Start the asked-for changes (A, N) that are allowed; returns which started."""
        n = self.agents
        left, right = self.possible(st)
        go_left = want_left & left
        go_right = want_right & right
        if self.ego.lane_change_check and (go_left | go_right).any():
            clear = self.side_clear(st)
            go_left &= clear[..., 1]
            go_right &= clear[..., 0]
            if n > 1:
                self._one_agent_per_gap(st, go_left, go_right)
        started = go_left | go_right
        st.target_lane[:, :n] += go_left.astype(np.int64) - go_right
        if self.watch is not None and started.any():
            started = self.watch.refuse_unsafe_starts(st, started)
        st.change_progress[:, :n] = np.where(started, 0.0, st.change_progress[:, :n])
        return started

    def side_clear(self, st: SimState) -> np.ndarray:
        """(A, N, 2) bool: whether the lane to each agent's right [0] and left [1] is clear for
        starting a lane change: no other vehicle in it, or moving into it, from
        ``lane_change_clear_behind_m`` behind the agent's rear bumper to
        ``lane_change_clear_ahead_m`` ahead of its front bumper, each window growing by the
        speed at which a car there closes in times ``lane_change_closing_time_s``. A lane that
        does not exist counts as clear here; :meth:`possible` refuses it anyway. A compiled loop
        (:func:`.kernels.side_clear`)."""
        ego = self.ego
        return kernels.side_clear(
            st.x_m,
            st.speed_mps,
            self.kinds.half_length[st.kind],
            st.active,
            st.lane,
            st.target_lane,
            self.agents,
            ego.lane_change_clear_ahead_m,
            ego.lane_change_clear_behind_m,
            ego.lane_change_closing_time_s,
        )

    def _one_agent_per_gap(self, st: SimState, go_left: np.ndarray, go_right: np.ndarray) -> None:
        """Agents cleared into the same lane at the same decision, near each other (from
        opposite sides), would meet there: the lower-numbered agent goes, the other keeps its
        lane. Changes ``go_left``/``go_right`` (A, N) in place."""
        n, ego = self.agents, self.ego
        started = go_left | go_right
        if not (started.sum(axis=1) > 1).any():
            return
        target = st.lane[:, :n] + go_left.astype(np.int64) - go_right
        half = self.kinds.half_length[st.kind[:, :n]]
        dx = np.abs(st.x_m[:, None, :n] - st.x_m[:, :n, None]) - half[:, None, :] - half[:, :, None]
        window = max(ego.lane_change_clear_ahead_m, ego.lane_change_clear_behind_m)
        lower = np.tri(n, k=-1, dtype=bool)  # [i, j]: j < i
        conflict = (
            lower
            & (dx < window)
            & started[:, None, :]
            & started[:, :, None]
            & (target[:, None, :] == target[:, :, None])
        )
        yields = conflict.any(axis=2)
        go_left &= ~yields
        go_right &= ~yields


class DriverWarnings:
    """The authors' code's warnings, per agent: left, right (a side warning: that lane is not
    clear for a lane change, or there is none) and forward (a car ahead, no faster than the
    agent, within ``forward_warning_time_s`` at the current speed, plus ``min_gap_m``)."""

    LEFT, RIGHT, FORWARD = range(3)

    def __init__(
        self, ego: EgoConfig, kinds: VehicleKinds, lane_changes: LaneChangeAssist, agents: int
    ) -> None:
        self.forward_time_s = ego.forward_warning_time_s
        self.min_gap_m = ego.min_gap_m
        self.kinds = kinds
        self.lane_changes = lane_changes
        self.agents = agents

    def cars_ahead(self, st: SimState) -> CarsAhead:
        """Each agent's car ahead (:class:`.ahead.CarsAhead`)."""
        return cars_ahead(st, self.kinds, self.agents)

    def compute(self, st: SimState, ahead: CarsAhead | None = None) -> np.ndarray:
        """(A, N, 3) bool: left, right and forward warnings now."""
        n = self.agents
        ahead = self.cars_ahead(st) if ahead is None else ahead
        possible_left, possible_right = self.lane_changes.possible_lanes(st)
        clear = self.lane_changes.side_clear(st)
        warnings = np.empty(clear.shape[:2] + (3,), dtype=bool)
        warnings[..., self.LEFT] = ~(possible_left & clear[..., 1])
        warnings[..., self.RIGHT] = ~(possible_right & clear[..., 0])
        speed = st.speed_mps[:, :n]
        warnings[..., self.FORWARD] = (
            ahead.present
            & (ahead.gap_m < self.forward_time_s * speed + self.min_gap_m)
            & (ahead.speed_mps <= speed)
        )
        return warnings
