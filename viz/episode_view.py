"""One recorded episode in Rerun, the way a trainer's recording shows its car: the road from
above with the car in it, what the car's camera and LIDAR saw, its speed, the Q-values when a
network drove, the action, the reward and its terms; and each event (a collision, an
emergency brake, the safety shield overriding the network) as a line of the event log at the
decision it happened, with the cars of a collision (and of an emergency brake) coloured on the
road at that moment.

Every episode has a timeline of its own, ``episode <n>`` (positions: decisions, from 0), and
all log to the same entities: choosing an episode's timeline in the viewer shows that episode,
in one layout. ``overtake-replay`` and ``overtake-eval --record`` record this way.

Entities: ``world/episode/arena0/road/...`` (the road, as :mod:`.world_view` draws it),
``episode/car/...`` (:class:`~.car_view.CarView`), ``episode/events`` (text log).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

# The road's entities: a world frame's, of an arena 0 on a "server" named episode.
ROAD_SERVER = "episode"
ROAD = f"/world/{ROAD_SERVER}/arena0/road"
CAR = "episode/car"
EVENTS = "episode/events"


def timeline(episode: int) -> str:
    """The name of episode ``episode``'s timeline."""
    return f"episode {episode}"


def episode_blueprint(
    episodes: Sequence[int],
    road_width_m: float | None,
    title: str = "episode",
    show_q_values: bool = True,
) -> Any:
    """The layout of an episode recording, opening on the first episode's timeline;
    ``road_width_m``: the road's width where the road is recorded (in process); ``show_q_values``:
    whether the driver says its Q-values (a network does; a rule, or recorded actions played
    alone, do not: no empty plot for them)."""
    import rerun.blueprint as rrb

    from .training_layout import car_layout

    events = rrb.TextLogView(origin=f"/{EVENTS}", name=f"{title}: events")
    return rrb.Blueprint(
        car_layout(
            title,
            (ROAD, road_width_m) if road_width_m is not None else None,
            root=f"/{CAR}",
            below=(events,),
            show_q_values=show_q_values,
        ),
        rrb.TimePanel(timeline=timeline(episodes[0]) if episodes else None, state="expanded"),
        collapse_panels=True,
    )
