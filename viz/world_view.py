"""World frames in Rerun: what a spectator, or a server logging directly, shows of an arena.

Per arena, under ``world/<server>/arena<id>``, on the ``round`` (decision) and ``sim_time``
timelines:

- ``road/lanes``: lane lines around the cars (x along the road, y from the right edge, metres);
- ``cars``: every vehicle as a box, traffic coloured by behaviour, agents in red and labelled;
- ``agent<i>/lidar/hits`` and ``agent<i>/lidar/rays``: each agent's LIDAR, drawn from its car
  (rays at angle 2*pi*k/R from the road's direction; a car changing lanes is turned by a few
  degrees, which the drawing ignores);
- ``agent<i>/camera``: its camera image;
- ``agent<i>/speed_kmh``, ``agent<i>/reward``, ``agent<i>/action``: scalars;
- ``agent<i>/reward_terms/<term>``: each term of the reward (frames of protocol 1.1 on).

Traffic is coloured by its behaviour (:data:`~overtake.protocol.vocabulary.BEHAVIOUR_NAMES`).
Spectators (client) and servers draw the same view of the :class:`WorldFrame` s they share.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from overtake.protocol.messages import WorldFrame
from overtake.protocol.vocabulary import BEHAVIOUR_NAMES

# One colour per behaviour, in the order of BEHAVIOUR_NAMES: steady blue, road-max green,
# lane-changer orange, random purple.
KIND_COLOURS = np.array(
    [[80, 120, 255], [40, 200, 120], [240, 170, 30], [200, 120, 230]], dtype=np.uint8
)
assert len(KIND_COLOURS) == len(BEHAVIOUR_NAMES)
AGENT_COLOUR = np.array([230, 40, 40], dtype=np.uint8)
HALF_SIZE_M = (2.25, 0.9)  # the default car (4.5 m x 1.8 m); frames do not carry sizes
LANE_LINE_SPAN_M = 120.0  # lane lines drawn this far either side of the cars


@functools.cache
def _ray_directions(rays: int) -> np.ndarray:
    angles = np.arange(rays) * (2.0 * np.pi / rays)
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def lidar_hits(
    distances_m: np.ndarray, origin_m: np.ndarray | tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """(R, 2) points where a LIDAR scan's R rays end: ray k at angle 2*pi*k/R counter-clockwise
    from the x axis (the road's direction), ``distances_m[k]`` from ``origin_m``."""
    return np.asarray(origin_m) + distances_m[:, None] * _ray_directions(distances_m.shape[0])


def _top_down(server: str, arena: int, name: str) -> Any:
    import rerun.blueprint as rrb

    root = f"/world/{server}/arena{arena}"
    return rrb.Spatial2DView(
        origin=root,
        name=name,
        contents=[f"{root}/road/**", f"{root}/cars", f"{root}/agent*/lidar/**"],
    )


def _arena_layout(server: str, arena: int, name: str | None = None) -> Any:
    """One arena: the road from above, and agent 0's camera and scalars beside it."""
    import rerun.blueprint as rrb

    root = f"/world/{server}/arena{arena}"
    return rrb.Horizontal(
        _top_down(server, arena, "top-down"),
        rrb.Vertical(
            rrb.Spatial2DView(origin=f"{root}/agent0/camera", name="agent 0 camera"),
            rrb.TimeSeriesView(
                origin=f"{root}/agent0",
                name="agent 0",
                contents=[
                    f"{root}/agent0/speed_kmh",
                    f"{root}/agent0/reward",
                    f"{root}/agent0/action",
                    f"{root}/agent0/reward_terms/**",
                ],
            ),
            row_shares=[2, 1],
        ),
        column_shares=[2, 1],
        name=name,
    )


def world_blueprint(server: str, arena: int) -> Any:
    """A spectator's layout of one arena."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        _arena_layout(server, arena), rrb.TimePanel(timeline="round"), collapse_panels=True
    )


def server_blueprint(server: str, arenas: list[int]) -> Any:
    """A server's layout: every arena from above in a grid, then a tab per arena."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Tabs(
            rrb.Grid(
                *(_top_down(server, arena, f"arena {arena}") for arena in arenas), name="all arenas"
            ),
            *(_arena_layout(server, arena, f"arena {arena}") for arena in arenas),
        ),
        rrb.TimePanel(timeline="round"),
        collapse_panels=True,
    )


class WorldRecording:
    """Logs :class:`WorldFrame` s to a RecordingStream; ``rays`` draws every LIDAR ray too."""

    def __init__(self, stream: Any, rays: bool = True) -> None:
        import rerun as rr

        self.rr, self.stream, self.rays = rr, stream, rays

    def log(self, frame: WorldFrame) -> None:
        rr, stream = self.rr, self.stream
        root = f"world/{frame.server}/arena{frame.arena}"
        stream.set_time("round", sequence=frame.round)
        stream.set_time("sim_time", duration=frame.sim_time_s)
        n = frame.agent_active.shape[0]
        active = np.flatnonzero(frame.active)
        agents = active[active < n]
        x, y = frame.x_m[active], frame.y_m[active]
        is_agent = frame.kind[active] == frame.agent_kind
        colours = np.where(
            is_agent[:, None],
            AGENT_COLOUR,
            KIND_COLOURS[np.clip(frame.kind[active], 0, len(KIND_COLOURS) - 1)],
        )
        labels = [f"agent {i}" if i < n else "" for i in active]
        stream.log(
            f"{root}/cars",
            rr.Boxes2D(
                centers=np.stack([x, y], axis=1),
                half_sizes=[HALF_SIZE_M],
                colors=colours,
                labels=labels,
            ),
        )
        low, high = (
            (x.min() - LANE_LINE_SPAN_M, x.max() + LANE_LINE_SPAN_M)
            if x.size
            else (-LANE_LINE_SPAN_M, LANE_LINE_SPAN_M)
        )
        edges = np.arange(frame.lane_count + 1) * frame.lane_width_m
        stream.log(
            f"{root}/road/lanes",
            rr.LineStrips2D(
                [[[low, e], [high, e]] for e in edges], colors=[[200, 200, 200]], radii=[0.05]
            ),
        )
        lidar = frame.observations.get("lidar")
        camera = frame.observations.get("camera")
        for i in agents:
            base = f"{root}/agent{i}"
            origin = np.array([frame.x_m[i], frame.y_m[i]])
            if lidar is not None:
                hits = lidar_hits(lidar[i], origin)
                stream.log(
                    f"{base}/lidar/hits", rr.Points2D(hits, radii=[0.25], colors=[[255, 128, 0]])
                )
                if self.rays:
                    strips = np.stack([np.broadcast_to(origin, hits.shape), hits], axis=1)
                    stream.log(
                        f"{base}/lidar/rays",
                        rr.LineStrips2D(strips, radii=[0.02], colors=[[255, 200, 120]]),
                    )
            if camera is not None:
                stream.log(f"{base}/camera", rr.Image(camera[i]))
            speed_mps = float(frame.speed_mps[i])
            stream.log(f"{base}/speed_kmh", rr.Scalars(speed_mps * 3.6))
            stream.log(f"{base}/reward", rr.Scalars(float(frame.reward[i])))
            stream.log(f"{base}/action", rr.Scalars(float(frame.action_applied[i])))
            if frame.reward_terms is not None:
                for name, value in zip(frame.reward_term_names, frame.reward_terms[i], strict=True):
                    stream.log(f"{base}/reward_terms/{name}", rr.Scalars(float(value)))
