"""Layouts of what trainers record (:mod:`overtake.trainers.run.visual` logs it): the curves of
one or several runs, a plot per quantity with every run a line in each, and each run's first car.

Entity paths: ``training/episode/<metric>/<run>``, ``training/learning/<name>/<run>`` and
``trainer/<run>/env0/...``.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any

from .road_window import ROAD_AHEAD_M, ROAD_BEHIND_M

# What a car's view can show of its observations (car_view logs both where they are there).
CAR_PICTURES = ("camera", "lidar")

# Plots of the episodes and of learning, one per quantity (title, the series in it): a run
# keeps its colour in every plot, so one plot holding two quantities could not tell them apart.
EPISODE_PLOTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("episode return", ("return",)),
    ("average speed (km/h)", ("avg_speed_kmh",)),
    ("lane changes per episode", ("lane_changes",)),
    ("overtakes per episode", ("overtakes",)),
    ("collisions per episode", ("collisions",)),
    ("emergency brakes per episode", ("emergency_brakes",)),
    ("distance per episode (m)", ("distance_m",)),
)
# The few a comparison at a glance needs (the "compare" tab of a joined recording).
KEY_PLOTS: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("episode return", "episode", ("return",)),
    ("average speed (km/h)", "episode", ("avg_speed_kmh",)),
    ("collisions per episode", "episode", ("collisions",)),
    ("loss", "learning", ("loss",)),
)
LEARNING_PLOTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("loss", ("loss",)),
    ("mean Q of the actions taken", ("q_taken",)),
    ("epsilon", ("epsilon",)),
    ("steps per second", ("steps_per_s",)),
)


def _plot(title: str, section: str, series: tuple[str, ...]) -> Any:
    import rerun.blueprint as rrb

    return rrb.TimeSeriesView(
        origin=f"/training/{section}",
        contents=[f"/training/{section}/{name}/**" for name in series],
        name=title,
    )


def curves_layout(runs: Sequence[str]) -> Any:
    """Episodes and learning, a plot per quantity; every run a line in each (one step axis)."""
    import rerun.blueprint as rrb

    return rrb.Horizontal(
        rrb.Vertical(
            *(_plot(title, "episode", series) for title, series in EPISODE_PLOTS),
            name="episodes",
        ),
        rrb.Vertical(
            *(_plot(title, "learning", series) for title, series in LEARNING_PLOTS),
            name="learning",
        ),
        name=f"training: {', '.join(runs)}",
    )


def key_curves_layout() -> Any:
    """The plots of :data:`KEY_PLOTS` in a row, every run a line in each."""
    import rerun.blueprint as rrb

    return rrb.Horizontal(*(_plot(title, section, series) for title, section, series in KEY_PLOTS))


def car_layout(
    run: str,
    road: tuple[str, float] | None = None,
    root: str | None = None,
    below: Sequence[Any] = (),
    show_q_values: bool = True,
    pictures: Collection[str] = CAR_PICTURES,
    show_speed: bool = True,
) -> Any:
    """What run ``run``'s first environment sees and does; with ``road`` (the entity path of
    its road and the road's width in metres: an in-process run's), the road from above on
    top, the way a spectator's recording shows a server's arenas. ``root``: the car's
    entities (default: the run's first environment's); ``below``: more views under the
    rest (an episode's events); ``show_q_values``: whether a network's Q-values are there to show
    (not where a rule drove, or recorded actions are played without their network);
    ``pictures``: which of the camera and the LIDAR the car has (no empty panel for one it
    lacks); ``show_speed``: whether its speed is known (an ego vector with the speed)."""
    import rerun.blueprint as rrb

    car_root = root or f"/trainer/{run}/env0"
    plots = [
        *(
            [rrb.TimeSeriesView(origin=f"{car_root}/speed_kmh", name=f"{run}: speed (km/h)")]
            if show_speed
            else []
        ),
        *(
            [rrb.TimeSeriesView(origin=f"{car_root}/q", name=f"{run}: Q-values")]
            if show_q_values
            else []
        ),
        rrb.TimeSeriesView(origin=f"{car_root}/reward", name=f"{run}: reward and its terms"),
        rrb.TimeSeriesView(origin=f"{car_root}/action", name=f"{run}: action"),
    ]
    road_view = []
    if road is not None:
        origin, width_m = road
        road_view.append(
            rrb.Spatial2DView(
                origin=origin,
                name=f"{run}: road ({'env 0' if root is None else 'the car'} at 0 m, left up)",
                visual_bounds=rrb.VisualBounds2D(
                    x_range=[-ROAD_BEHIND_M, ROAD_AHEAD_M], y_range=[-width_m - 1.0, 1.0]
                ),
            )
        )
    seen = [
        rrb.Spatial2DView(origin=f"{car_root}/{picture}", name=f"{run}: {title}")
        for picture, title in (("camera", "camera"), ("lidar", "LIDAR (m, left up)"))
        if picture in pictures
    ]
    pictures_row = [rrb.Horizontal(*seen)] if seen else []
    return rrb.Vertical(
        *road_view,
        *pictures_row,
        *plots,
        *below,
        row_shares=[
            *([2] * len(road_view)),
            *([3] * len(pictures_row)),
            *([1] * (len(plots) + len(below))),
        ],
        name=f"{run}: env 0",
    )


def training_blueprint(
    runs: str | Sequence[str],
    extra_tabs: Sequence[Any] = (),
    road: tuple[str, float] | None = None,
    pictures: Collection[str] = CAR_PICTURES,
    show_speed: bool = True,
) -> Any:
    """One run's layout, or several runs' side by side: the curves (every run in each plot),
    then each run's car view, as tabs. ``extra_tabs`` (for example the road's) follow; ``road``,
    ``pictures``, ``show_speed``: one run's road and what its car has (:func:`car_layout`)."""
    import rerun.blueprint as rrb

    names = [runs] if isinstance(runs, str) else list(runs)
    return rrb.Blueprint(
        rrb.Tabs(
            curves_layout(names),
            rrb.Horizontal(*(car_layout(run) for run in names), name="cars")
            if len(names) > 1
            else car_layout(names[0], road, pictures=pictures, show_speed=show_speed),
            *extra_tabs,
        ),
        rrb.TimePanel(timeline="step", state="collapsed"),
        collapse_panels=True,
    )
