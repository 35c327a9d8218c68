"""World frames in Rerun: what a spectator, or a server logging directly, shows of an arena.

Per arena, under ``world/<server>/arena<id>``:

- ``road/lanes/{edges,marks}``, ``road/cars``, ``road/agent<i>/lidar/{hits,rays}``: the road
  from above, drawn the way a driver reads a map: centred on the followed car (agent 0, or
  the first agent on the road) and moving with it, forward to the right and the driver's left
  *up*. Drawing
  coordinates are metres: x ahead of the followed car, y = minus the distance from the road's
  right edge (Rerun draws +y downward, so the road's left, +y in the simulator, must be
  negated to come out on top). Every car is a box of its own size, traffic coloured by
  behaviour, agents red and labelled; LIDAR rays leave each agent at angle 2*pi*k/R from the
  car's heading (a car changing lanes turns by a few degrees; its box is drawn straight);
- ``agent<i>/camera``: its camera image;
- ``agent<i>/speed_kmh``: speed (km/h);
- ``agent<i>/reward/total`` and ``agent<i>/reward/<term>``: the reward and each of its terms
  (frames of protocol 1.1 on);
- ``agent<i>/action/<name>``: the action applied, as a point at its index on the series of
  its name (a scatter with a legend, not a line).

Timelines: ``round`` (the group's decisions), ``sim_time``, and ``step`` when the arena's
trainer sends its step count (protocol 1.2): a recording of the road then opens on the same
timeline as the trainer's curves.

Traffic is coloured by its behaviour (:data:`~overtake.protocol.vocabulary.BEHAVIOUR_NAMES`).
Spectators (client) and servers draw the same view of the :class:`WorldFrame` s they share, and
lay each arena out as it first appears (:func:`arena_layout`).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from overtake.protocol.messages import WorldFrame
from overtake.protocol.vocabulary import ACTION_NAMES, BEHAVIOUR_COLOURS, BEHAVIOUR_NAMES
from overtake.protocol.vocabulary import AGENT_COLOUR as AGENT_RGB

from .road_window import ROAD_AHEAD_M, ROAD_BEHIND_M
from .training_layout import curves_layout, key_curves_layout

log = logging.getLogger("overtake.viz")

# The vocabulary's colours: one per behaviour, and the agents' red.
KIND_COLOURS = np.array(BEHAVIOUR_COLOURS, dtype=np.uint8)
assert len(KIND_COLOURS) == len(BEHAVIOUR_NAMES)
AGENT_COLOUR = np.array(AGENT_RGB, dtype=np.uint8)
# One colour per action, in the order of ACTION_NAMES, for the action scatter.
ACTION_COLOURS = np.array(
    [[200, 200, 200], [40, 200, 120], [240, 80, 60], [80, 160, 255], [240, 170, 30]],
    dtype=np.uint8,
)
assert len(ACTION_COLOURS) == len(ACTION_NAMES)
LANE_COLOUR = [200, 200, 200]
HALF_SIZE_M = (2.25, 0.9)  # the default car, for frames of peers before protocol 1.2
# Lane lines are drawn this far behind and ahead of the followed car: beyond the road view's
# window, which a wide, low view (an overview of many arenas) shows more of.
LINES_BEHIND_M = 150.0
LINES_AHEAD_M = 250.0
# Lane markings: dashes of DASH_M in every DASH_PERIOD_M, fixed to the road so they pass by.
DASH_PERIOD_M = 12.0
DASH_M = 6.0
LIDAR_HIT_COLOUR = [255, 128, 0]
# The cars of a collision, at the decision it happened: a colour no behaviour or agent has.
EVENT_COLOUR: tuple[int, int, int] = (0, 240, 255)
# An emergency brake's car and the car it braked for, at that decision.
BRAKE_COLOUR: tuple[int, int, int] = (255, 255, 255)
LIDAR_RAY_COLOUR = [255, 200, 120]


@functools.cache
def _ray_directions(rays: int) -> np.ndarray:
    angles = np.arange(rays) * (2.0 * np.pi / rays)
    return np.stack([np.cos(angles), np.sin(angles)], axis=1)


def lidar_hits(
    distances_m: np.ndarray,
    origin_m: np.ndarray | tuple[float, float] = (0.0, 0.0),
    heading_rad: float = 0.0,
) -> np.ndarray:
    """(R, 2) points, in road coordinates (x ahead, y left), where a LIDAR scan's R rays end:
    ray k at angle heading + 2*pi*k/R counter-clockwise from the road's direction,
    ``distances_m[k]`` from ``origin_m``."""
    directions = _ray_directions(distances_m.shape[0])
    if heading_rad:
        c, s = np.cos(heading_rad), np.sin(heading_rad)
        directions = directions @ np.array([[c, s], [-s, c]])
    return np.asarray(origin_m) + distances_m[:, None] * directions


def to_drawing(points_m: np.ndarray) -> np.ndarray:
    """Road coordinates (x ahead, y left) to Rerun's 2-D drawing, where +y points down: y is
    negated, so the driver's left comes out on top."""
    return points_m * np.array([1.0, -1.0])


@dataclass(frozen=True)
class ArenaShape:
    """What an arena's layout needs to know, read from its first frame."""

    server: str
    arena: int
    lane_count: int
    lane_width_m: float
    lidar_range_m: float | None  # None: no LIDAR
    camera: bool

    @property
    def root(self) -> str:
        return f"/world/{self.server}/arena{self.arena}"

    def as_values(self, rr: Any) -> Any:
        return rr.AnyValues(
            server=[self.server],
            arena=[self.arena],
            lane_count=[self.lane_count],
            lane_width_m=[self.lane_width_m],
            lidar_range_m=[-1.0 if self.lidar_range_m is None else self.lidar_range_m],
            camera=[self.camera],
        )

    @classmethod
    def from_values(cls, values: dict[str, Any]) -> ArenaShape:
        """The shape :meth:`as_values` logged, from its columns' first values."""
        lidar = float(values["lidar_range_m"])
        return cls(
            server=str(values["server"]),
            arena=int(values["arena"]),
            lane_count=int(values["lane_count"]),
            lane_width_m=float(values["lane_width_m"]),
            lidar_range_m=None if lidar < 0 else lidar,
            camera=bool(values["camera"]),
        )

    @classmethod
    def of(cls, frame: WorldFrame) -> ArenaShape:
        lidar = frame.observations.get("lidar")
        return cls(
            server=frame.server,
            arena=frame.arena,
            lane_count=frame.lane_count,
            lane_width_m=frame.lane_width_m,
            # A scan of rays that hit nothing reads the range: the longest reading is the best
            # estimate the frame gives (it is not part of the frame).
            lidar_range_m=float(np.max(lidar)) if lidar is not None and lidar.size else None,
            camera="camera" in frame.observations,
        )


def road_view(shape: ArenaShape, name: str) -> Any:
    """The road around the followed car, every car and the agents' LIDAR."""
    import rerun.blueprint as rrb

    road_width = shape.lane_count * shape.lane_width_m
    return rrb.Spatial2DView(
        origin=f"{shape.root}/road",
        name=name,
        visual_bounds=rrb.VisualBounds2D(
            x_range=[-ROAD_BEHIND_M, ROAD_AHEAD_M], y_range=[-road_width - 1.0, 1.0]
        ),
    )


def arena_layout(shape: ArenaShape, name: str | None = None) -> Any:
    """One arena: the road from above on top; below, agent 0's camera, its LIDAR (the same
    road, zoomed out to the LIDAR's range) and its plots, one per unit."""
    import rerun.blueprint as rrb

    root, agent = shape.root, f"{shape.root}/agent0"
    title = name or f"arena {shape.arena}"
    below: list[Any] = []
    if shape.camera:
        below.append(rrb.Spatial2DView(origin=f"{agent}/camera", name="agent 0: camera"))
    if shape.lidar_range_m is not None:
        reach = shape.lidar_range_m
        below.append(
            rrb.Spatial2DView(
                origin=f"{root}/road",
                contents=[
                    f"{root}/road/lanes/**",
                    f"{root}/road/cars",
                    f"{root}/road/agent0/lidar/**",
                ],
                name=f"agent 0: LIDAR ({reach:.0f} m)",
                visual_bounds=rrb.VisualBounds2D(x_range=[-reach, reach], y_range=[-reach, reach]),
            )
        )
    below.append(
        rrb.Vertical(
            rrb.TimeSeriesView(origin=f"{agent}/speed_kmh", name="agent 0: speed (km/h)"),
            rrb.TimeSeriesView(origin=f"{agent}/reward", name="agent 0: reward and its terms"),
            rrb.TimeSeriesView(origin=f"{agent}/action", name="agent 0: action"),
        )
    )
    return rrb.Vertical(
        road_view(shape, f"{title}: road (agent 0 at 0 m, left up)"),
        rrb.Horizontal(*below),
        row_shares=[1, 2],
        name=title,
    )


def world_blueprint(
    shapes: list[ArenaShape], timeline: str = "round", with_training: bool = False
) -> Any:
    """A layout of ``shapes``' arenas: one arena fills the window; several get an overview tab
    (every road, one above the other) and a tab each.

    ``with_training`` (a recording shared with trainers, ``--recording-id``): the overview
    also holds the key training plots and a "training" tab every plot, every run that shares
    the recording a line in each. A live viewer shows the layout it received last, and the
    roads' (sent as arenas open, after the trainers have started) then shows everything."""
    import rerun.blueprint as rrb

    roads = [road_view(s, f"{s.server} arena {s.arena}") for s in shapes]
    arenas = [arena_layout(s, f"{s.server} arena {s.arena}") for s in shapes]
    if with_training:
        root: Any = rrb.Tabs(
            rrb.Vertical(
                *roads, key_curves_layout(), row_shares=[1] * len(roads) + [2], name="compare"
            ),
            curves_layout(["every run"]),
            *arenas,
        )
    elif len(shapes) == 1:
        root = arena_layout(shapes[0])
    else:
        root = rrb.Tabs(rrb.Vertical(*roads, name="all roads"), *arenas)
    return rrb.Blueprint(
        root, rrb.TimePanel(timeline=timeline, state="collapsed"), collapse_panels=True
    )


# The blueprint lays out the arenas that appeared last, this many: a server that runs for days
# sees trainers come and go, and a tab per arena beyond a few dozen would be of no use anyway.
BLUEPRINT_ARENAS = 16


class WorldRecording:
    """Logs :class:`WorldFrame` s to a RecordingStream; ``rays`` draws every LIDAR ray too.

    With ``lay_out`` it sends a layout (:func:`world_blueprint`) each time an arena appears,
    of the last :data:`BLUEPRINT_ARENAS` arenas, as the active and the default one: a live
    viewer shows it at once (an arrangement of the viewer's own is replaced when an arena
    opens; Rerun's "reset to default" brings the layout back at any time)."""

    def __init__(
        self,
        stream: Any,
        rays: bool = True,
        lay_out: bool = True,
        with_training: bool = False,
        agent_series: bool = True,
        action_names: Sequence[str] = ACTION_NAMES,
    ) -> None:
        """``with_training``: the layout also shows the trainers' plots (see
        :func:`world_blueprint`); for a recording shared with trainers. ``agent_series``:
        each agent's camera, speed, reward and action too (False: the road only, for a
        recording that shows its car's view on its own, :mod:`.car_view`). ``action_names``:
        the actions' names in index order where the arenas' spec is known (highway-env's in
        its scenes); a spectator's default is overtake's."""
        import rerun as rr

        self.action_names = tuple(action_names)

        self.rr, self.stream, self.rays, self.lay_out = rr, stream, rays, lay_out
        self.agent_series = agent_series
        self.with_training = with_training
        self.shapes: dict[tuple[str, int], ArenaShape] = {}
        self._seen: set[tuple[str, int]] = set()
        self._styled: set[str] = set()
        self._on_step = False

    def _arena_appears(self, frame: WorldFrame) -> None:
        shape = ArenaShape.of(frame)
        self.shapes[(shape.server, shape.arena)] = shape
        # What a layout needs, kept in the recording: a later one (overtake-layout) reads it.
        self.stream.log(f"{shape.root}/shape", shape.as_values(self.rr), static=True)
        while len(self.shapes) > BLUEPRINT_ARENAS:
            del self.shapes[next(iter(self.shapes))]
        if not self.lay_out:
            return
        try:
            self.stream.send_blueprint(
                world_blueprint(
                    list(self.shapes.values()),
                    "step" if self._on_step else "round",
                    with_training=self.with_training,
                ),
                # Active: a live viewer has made a layout of its own from the first data by
                # then, and would keep it over a default one.
                make_active=True,
                make_default=True,
            )
        except Exception:
            # Without it the viewer falls back to its own layout; the frames still go in.
            log.exception("could not send the recording's layout")

    def _style(self, base: str) -> None:
        """Series styles, logged once per agent (static): actions as coloured points."""
        rr, stream = self.rr, self.stream
        for index, name in enumerate(self.action_names):
            stream.log(
                f"{base}/action/{name}",
                rr.SeriesPoints(
                    names=name, colors=[ACTION_COLOURS[index]], markers="circle", marker_sizes=3.0
                ),
                static=True,
            )
        self._styled.add(base)

    def log(
        self,
        frame: WorldFrame,
        timeline: tuple[str, int] | None = None,
        highlight: dict[tuple[int, int, int], np.ndarray] | None = None,
    ) -> None:
        """Draw ``frame``; ``timeline`` (name, position): on that timeline alone instead of
        the frame's round, sim time and step (an episode replayed on a timeline of its own);
        ``highlight``: vehicles (indices into the frame's arrays) drawn in another colour
        than their own, by colour (:data:`EVENT_COLOUR`: the cars of a collision,
        :data:`BRAKE_COLOUR`: an emergency brake's car and the car it braked for)."""
        rr, stream = self.rr, self.stream
        root = f"world/{frame.server}/arena{frame.arena}"
        if frame.trainer_step >= 0 and not self._on_step:
            self._on_step = True
            self._seen.clear()  # lay out again, on the step timeline
        if (frame.server, frame.arena) not in self._seen:
            # Once per arena: one that left the layout (beyond BLUEPRINT_ARENAS) stays out.
            self._seen.add((frame.server, frame.arena))
            self._arena_appears(frame)
            self._lane_lines(root, frame)
        if timeline is not None:
            stream.reset_time()
            stream.set_time(timeline[0], sequence=timeline[1])
        else:
            stream.set_time("round", sequence=frame.round)
            stream.set_time("sim_time", duration=frame.sim_time_s)
            if frame.trainer_step >= 0:
                stream.set_time("step", sequence=frame.trainer_step)
        n = frame.agent_active.shape[0]
        active = np.flatnonzero(frame.active)
        agents = active[active < n]
        followed_x = float(frame.x_m[agents[0]]) if agents.size else 0.0
        origin = np.array([followed_x, 0.0])
        centres = to_drawing(np.stack([frame.x_m[active], frame.y_m[active]], axis=1) - origin)
        if frame.half_length_m is not None and frame.half_width_m is not None:
            half_sizes = np.stack([frame.half_length_m[active], frame.half_width_m[active]], axis=1)
        else:
            # One half-size for N centres would draw ONE box: repeat it per car.
            half_sizes = np.tile(np.array(HALF_SIZE_M), (active.size, 1))
        is_agent = frame.kind[active] == frame.agent_kind
        colours = np.where(
            is_agent[:, None],
            AGENT_COLOUR,
            KIND_COLOURS[np.clip(frame.kind[active], 0, len(KIND_COLOURS) - 1)],
        )
        for colour, vehicles in (highlight or {}).items():
            colours = np.where(
                np.isin(active, vehicles)[:, None], np.array(colour, dtype=np.uint8), colours
            )
        stream.log(
            f"{root}/road/cars",
            rr.Boxes2D(
                centers=centres,
                half_sizes=half_sizes,
                colors=colours,
                radii=[0.12],
                labels=[f"agent {i}" if i < n else "" for i in active],
                show_labels=True,
            ),
        )
        # The dashes (static, around x = 0) move back as the car moves on: they are the road's.
        stream.log(
            f"{root}/road/lanes/marks",
            rr.Transform3D(translation=[-(followed_x % DASH_PERIOD_M), 0.0, 0.0]),
        )
        lidar = frame.observations.get("lidar")
        camera = frame.observations.get("camera")
        for i in agents:
            base = f"{root}/agent{i}"
            if self.agent_series and base not in self._styled:
                self._style(base)
            car = np.array([frame.x_m[i], frame.y_m[i]]) - origin
            if lidar is not None:
                heading = (
                    float(frame.agent_heading_rad[i])
                    if frame.agent_heading_rad is not None
                    else 0.0
                )
                hits = to_drawing(lidar_hits(lidar[i], car, heading))
                stream.log(
                    f"{root}/road/agent{i}/lidar/hits",
                    rr.Points2D(hits, radii=[0.3], colors=[LIDAR_HIT_COLOUR]),
                )
                if self.rays:
                    start = np.broadcast_to(to_drawing(car), hits.shape)
                    stream.log(
                        f"{root}/road/agent{i}/lidar/rays",
                        rr.LineStrips2D(
                            np.stack([start, hits], axis=1),
                            radii=[0.03],
                            colors=[LIDAR_RAY_COLOUR],
                        ),
                    )
            if not self.agent_series:
                continue
            if camera is not None:
                stream.log(f"{base}/camera", rr.Image(camera[i]))
            stream.log(f"{base}/speed_kmh", rr.Scalars(float(frame.speed_mps[i]) * 3.6))
            stream.log(f"{base}/reward/total", rr.Scalars(float(frame.reward[i])))
            if frame.reward_terms is not None:
                for name, value in zip(frame.reward_term_names, frame.reward_terms[i], strict=True):
                    stream.log(f"{base}/reward/{name}", rr.Scalars(float(value)))
            applied = int(frame.action_applied[i])
            if 0 <= applied < len(self.action_names):
                name = self.action_names[applied]
                stream.log(f"{base}/action/{name}", rr.Scalars(float(applied)))

    def _lane_lines(self, root: str, frame: WorldFrame) -> None:
        """The road's edges as solid lines and the lines between lanes dashed, logged once
        per arena (static): the dashes are fixed to the road, and each frame only moves them
        (:meth:`log`, a translation) as the followed car drives on."""
        rr, stream = self.rr, self.stream
        low, high = -LINES_BEHIND_M, LINES_AHEAD_M
        width = frame.lane_count * frame.lane_width_m
        edges = [np.array([[low, 0.0], [high, 0.0]]), np.array([[low, -width], [high, -width]])]
        starts = np.arange(low - DASH_PERIOD_M, high + DASH_PERIOD_M, DASH_PERIOD_M)
        dashes = [
            np.array([[x, -k * frame.lane_width_m], [x + DASH_M, -k * frame.lane_width_m]])
            for k in range(1, frame.lane_count)
            for x in starts
        ]
        line = {"colors": [LANE_COLOUR], "radii": [0.08]}
        stream.log(f"{root}/road/lanes/edges", rr.LineStrips2D(edges, **line), static=True)
        if dashes:
            stream.log(f"{root}/road/lanes/marks", rr.LineStrips2D(dashes, **line), static=True)
