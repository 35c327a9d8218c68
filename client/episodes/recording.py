"""Episodes into Rerun as they are driven (``overtake-eval --record``, ``overtake-replay``): a
watcher of :func:`~overtake.client.episodes.runner.run_episodes` that logs each environment's first
episode on a timeline of its own, laid out as :mod:`overtake.viz.episode_view` says.

At decision ``d`` of an episode the recording holds what the car saw when it decided (camera,
LIDAR, ego vector), the action sent, the network's Q-values (where the policy says them:
``last_q``), the reward and its terms that the decision earned, the road after the decision (in
process: a remote simulator's road is its server's to record), and the decision's events.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from overtake.client.episodes.records import EventCounts
from overtake.client.episodes.runner import VectorStep
from overtake.envs.faces import VectorFace
from overtake.viz.car_view import CarView
from overtake.viz.episode_view import CAR, EVENTS, ROAD_SERVER, episode_blueprint, timeline
from overtake.viz.recording import (
    APPLICATION_ID,
    Recording,
    RecordingConfig,
    close_recording,
    open_recording,
)
from overtake.viz.world_view import BRAKE_COLOUR, EVENT_COLOUR, WorldRecording

# Cars closer than this (m, beyond touching) to a car that collided are drawn as its partners.
TOUCH_MARGIN_M = 0.5
EVENT_TEXT = {
    "collisions": ("ERROR", "collision"),
    "emergency_brakes": ("WARN", "emergency brake"),
}


def touching(frame: Any, agent: int = 0, margin_m: float = TOUCH_MARGIN_M) -> np.ndarray:
    """The vehicles of a world frame touching agent ``agent`` (boxes within ``margin_m``),
    the agent among them; where none does (a collision is judged over the decision's frames)
    the agent and the car nearest it."""
    active = np.flatnonzero(frame.active)
    others = active[active != agent]
    if frame.half_length_m is None or frame.half_width_m is None or others.size == 0:
        return np.array([agent])
    dx = np.abs(frame.x_m[others] - frame.x_m[agent])
    dy = np.abs(frame.y_m[others] - frame.y_m[agent])
    reach_x = frame.half_length_m[others] + frame.half_length_m[agent] + margin_m
    reach_y = frame.half_width_m[others] + frame.half_width_m[agent] + margin_m
    close = others[(dx <= reach_x) & (dy <= reach_y)]
    if close.size == 0:
        close = others[[int(np.argmin(np.hypot(dx, dy)))]]
    return np.concatenate([[agent], close])


def ahead_of(frame: Any, agent: int = 0) -> np.ndarray:
    """Agent ``agent`` and the nearest car ahead of it that shares a lane with it at least in
    part (less than a lane's width apart sideways: in its lane, or moving into or out of it
    as the agent or that car changes lanes, as car-following counts a leader), the car an
    emergency brake is for; the agent alone where there is none."""
    active = np.flatnonzero(frame.active)
    others = active[active != agent]
    if others.size == 0:
        return np.array([agent])
    dx = frame.x_m[others] - frame.x_m[agent]
    beside = np.abs(frame.y_m[others] - frame.y_m[agent]) < frame.lane_width_m
    ahead = others[(dx > 0) & beside]
    if ahead.size == 0:
        return np.array([agent])
    return np.array([agent, ahead[np.argmin(frame.x_m[ahead])]])


class EpisodeRecording:
    """Logs the first episode of each environment of a vector environment to ``stream``;
    ``labels[i]`` numbers environment ``i``'s episode (its timeline). ``envs``: the vector
    environment, whose simulator's road (in process) is drawn too; ``policy``: may say
    ``last_q`` (N, actions) and ``last_overridden`` (N,) after each call."""

    def __init__(
        self,
        stream: Any,
        labels: Sequence[int],
        envs: VectorFace,
        policy: Any = None,
        ego_fields: Sequence[str] = (),
        every: int = 1,
    ) -> None:
        """``every``: draw the car and the road at one decision in ``every`` (and at each
        decision with an event, and at each episode's last); the events are all logged."""
        import rerun as rr

        self.every = max(1, every)
        self.rr, self.stream, self.labels, self.policy = rr, stream, list(labels), policy
        # The actions as the preset names them (highway-env's names in its scenes).
        self.action_names = envs.behaviour_spec.action_names
        self.car = CarView(stream, CAR, ego_fields, self.action_names)
        self.world = envs.simulator.road
        self.road = (
            WorldRecording(stream, rays=False, lay_out=False, agent_series=False)
            if self.world is not None
            else None
        )
        n = len(self.labels)
        self.running = np.ones(n, dtype=bool)
        self.decisions = np.zeros(n, dtype=np.int64)
        self.counts = EventCounts(n)
        self.seen: dict[str, np.ndarray] = {}
        self.seen_mask: np.ndarray | None = None

    def started(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self._saw(obs, info)
        self.counts.reset()

    def _event(self, level: str, text: str) -> None:
        self.stream.log(EVENTS, self.rr.TextLog(text, level=level))

    def stepped(self, step: VectorStep) -> None:
        actions, info, reward = step.actions, step.info, step.reward
        q = getattr(self.policy, "last_q", None)
        overridden = getattr(self.policy, "last_overridden", None)
        rose = self.counts.rose(info)
        terms_of = info.get("reward_terms", {})
        for i in np.flatnonzero(self.running):
            decision = int(self.decisions[i])
            self.stream.reset_time()
            self.stream.set_time(timeline(self.labels[i]), sequence=decision)
            action = int(actions[i])
            happened = [name for name, now in rose.items() if now[i]]
            ends = bool(step.ended[i])
            drawn = decision % self.every == 0 or bool(happened) or ends
            if drawn:
                self.car.log(
                    {name: value[i] for name, value in self.seen.items()},
                    action,
                    None if q is None else np.asarray(q[i]),
                    float(reward[i]),
                    {name: float(value[i]) for name, value in terms_of.items()},
                )
            speed_kmh = None
            if drawn and self.road is not None and self.world is not None:
                frame = self.world.world_frame(int(i))
                # Every episode draws on the same road entities (its timeline tells them apart).
                frame = dataclasses.replace(frame, server=ROAD_SERVER, arena=0)
                highlight = {}
                if "emergency_brakes" in happened:
                    highlight[BRAKE_COLOUR] = ahead_of(frame)
                if "collisions" in happened:
                    highlight[EVENT_COLOUR] = touching(frame)
                self.road.log(frame, (timeline(self.labels[i]), decision), highlight)
                speed_kmh = float(frame.speed_mps[0]) * 3.6
            at = f"decision {decision}" + (
                f", {speed_kmh:.0f} km/h" if speed_kmh is not None else ""
            )
            for name in happened:
                level, what = EVENT_TEXT[name]
                self._event(level, f"{what} at {at}")
            if overridden is not None and overridden[i] and q is not None:
                allowed = True if self.seen_mask is None else self.seen_mask[i]
                greedy = int(np.argmax(np.where(allowed, q[i], -np.inf)))
                self._event(
                    "INFO",
                    f"the shield overrode {self.action_names[greedy]} with "
                    f"{self.action_names[action]} "
                    f"at {at}",
                )
            if ends:
                self._event("DEBUG", f"episode ends after {decision + 1} decisions")
        self.decisions += self.running
        self.running &= ~step.ended
        self._saw(step.obs, info)

    def _saw(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        """What the next decision is taken on (copies: the environment's arrays move on)."""
        self.seen = {name: np.array(value) for name, value in obs.items()}
        mask = info.get("action_mask")
        self.seen_mask = None if mask is None else np.array(mask, dtype=bool)


def open_episode_recording(
    config: RecordingConfig,
    default_rrd: Path,
    labels: Sequence[int],
    envs: VectorFace,
    policy: Any,
    title: str,
    every: int = 1,
) -> tuple[Recording | None, EpisodeRecording | None]:
    """A recording of the episodes ``labels`` (to ``default_rrd`` unless ``config`` says
    otherwise) and its watcher, drawing one decision in ``every`` (events always); (None,
    None) where ``config.sink`` is off. The layout has a Q-values plot where ``policy`` says
    them (has ``last_q``)."""
    spec = envs.behaviour_spec
    road_width_m = (
        spec.road.lane_count * spec.road.lane_width_m
        if envs.simulator.road is not None and spec.road is not None
        else None
    )
    layout = episode_blueprint(labels, road_width_m, title, show_q_values=hasattr(policy, "last_q"))
    recording = open_recording(APPLICATION_ID, config, default_rrd, layout)
    if recording is None:
        return None, None
    ego_fields = spec.observation("ego").columns if spec.has("ego") else ()
    return recording, EpisodeRecording(
        recording.stream, labels, envs, policy, ego_fields=ego_fields, every=every
    )


__all__ = ["EpisodeRecording", "close_recording", "open_episode_recording", "touching"]
