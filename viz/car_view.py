"""What one car sees and does, in Rerun: its camera frame, its LIDAR hits around it, its speed,
the action it took, the Q-value of every action, the reward and each of its terms.

A trainer logs its first environment's car this way (``trainer/<run>/env0``, on the ``step``
timeline), and a recorded or replayed episode its car (``episode/car``, on the episode's own
timeline): the two recordings read alike. The caller sets the time; this logs the values.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from overtake.protocol.vocabulary import ACTION_NAMES

from .world_view import ACTION_COLOURS, LIDAR_HIT_COLOUR, lidar_hits, to_drawing

# The car drawn at the centre of its LIDAR map: the default car's half length and width (m).
CAR_HALF_SIZE_M = (2.25, 0.9)


class CarView:
    """Logs one car's view under ``base``; styles (names, colours) are logged once, static."""

    def __init__(
        self,
        stream: Any,
        base: str,
        ego_fields: Sequence[str] = (),
        action_names: Sequence[str] = ACTION_NAMES,
    ) -> None:
        """``ego_fields`` names the ego vector's fields in order: the speed is read from its
        ``speed_mps`` where it has one. ``action_names``: the actions' names in index order, as
        the behaviour spec says them (highway-env's in its scenes)."""
        import rerun as rr

        if len(action_names) != len(ACTION_NAMES):
            raise ValueError(f"expected {len(ACTION_NAMES)} action names, got {list(action_names)}")
        self.rr, self.stream, self.base = rr, stream, base
        self.action_names = tuple(action_names)
        self.speed_field = (
            list(ego_fields).index("speed_mps") if "speed_mps" in ego_fields else None
        )
        self._styled = False

    def _style(self) -> None:
        rr, stream, base = self.rr, self.stream, self.base
        for index, name in enumerate(self.action_names):
            # The colours of the action scatter: a Q-value's line and its action's points match.
            stream.log(
                f"{base}/q/{name}",
                rr.SeriesLines(names=name, colors=[ACTION_COLOURS[index]]),
                static=True,
            )
            stream.log(
                f"{base}/action/{name}",
                rr.SeriesPoints(
                    names=name, colors=[ACTION_COLOURS[index]], markers="circle", marker_sizes=3.0
                ),
                static=True,
            )
        stream.log(
            f"{base}/lidar/car",
            rr.Boxes2D(centers=[[0.0, 0.0]], half_sizes=[CAR_HALF_SIZE_M], colors=[[230, 40, 40]]),
            static=True,
        )
        self._styled = True

    def log(
        self,
        obs: dict[str, np.ndarray],
        action: int,
        q: np.ndarray | None,
        reward: float,
        terms: dict[str, float],
    ) -> None:
        """The car's latest frame (``obs`` unbatched: ``lidar`` (R,) metres, ``camera``
        (H, W[, 3]) uint8, ``ego`` the ego vector), the action it took, the Q-values of every
        action (None: no network drove) and the reward it got for it with each term."""
        rr, stream, base = self.rr, self.stream, self.base
        if not self._styled:
            self._style()
        lidar = obs.get("lidar")
        if lidar is not None:
            stream.log(
                f"{base}/lidar/hits",
                rr.Points2D(to_drawing(lidar_hits(lidar)), radii=[0.3], colors=[LIDAR_HIT_COLOUR]),
            )
        camera = obs.get("camera")
        if camera is not None:
            stream.log(f"{base}/camera", rr.Image(camera))
        ego = obs.get("ego")
        if ego is not None and self.speed_field is not None:
            stream.log(f"{base}/speed_kmh", rr.Scalars(float(ego[self.speed_field]) * 3.6))
        names = self.action_names
        if 0 <= action < len(names):
            stream.log(f"{base}/action/{names[action]}", rr.Scalars(float(action)))
        if q is not None:
            for name, value in zip(names, q, strict=True):
                stream.log(f"{base}/q/{name}", rr.Scalars(float(value)))
            if 0 <= action < len(names):
                stream.log(f"{base}/q_chosen", rr.Scalars(float(q[action])))
        stream.log(f"{base}/reward/total", rr.Scalars(float(reward)))
        for name, value in terms.items():
            stream.log(f"{base}/reward/{name}", rr.Scalars(float(value)))
