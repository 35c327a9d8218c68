"""What a trainer shows in Rerun, on the ``step`` timeline (environment steps):

- ``trainer/<run>/episode/<metric>``: every episode's return and the papers' metrics (average
  speed, lane changes, overtakes, collisions, emergency brakes, ...), as the episode ends;
- ``trainer/<run>/learning/<name>``: loss, epsilon, the mean Q of the actions taken in the
  updates, and steps per second, once per log line (``--log-every``);
- ``trainer/<run>/env0/...``: what the first environment's car sees and does, every
  ``--record-every`` steps: its camera frame, its LIDAR hits around the car (metres, x ahead,
  y to the left), speed, the action taken, the Q-value of every action and of the chosen one,
  the reward and each reward term.

Summaries are logged at most once per episode or log line; the car's view is decimated, and
with the default decimation the training loop loses nothing measurable (``bench/RESULTS.md``,
``python -m bench.bench_recording``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from overtake.protocol import ACTION_NAMES
from overtake.viz.world_view import lidar_hits

LEARNING_SERIES = ("loss", "epsilon", "q_taken", "steps_per_s")


def training_blueprint(run: str) -> Any:
    import rerun.blueprint as rrb

    root = f"/trainer/{run}"
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.TimeSeriesView(origin=f"{root}/episode", name=f"{run}: episodes"),
                rrb.TimeSeriesView(origin=f"{root}/learning", name=f"{run}: learning"),
            ),
            rrb.Vertical(
                rrb.Horizontal(
                    rrb.Spatial2DView(origin=f"{root}/env0/camera", name="env 0 camera"),
                    rrb.Spatial2DView(origin=f"{root}/env0/lidar", name="env 0 LIDAR"),
                ),
                rrb.TimeSeriesView(origin=f"{root}/env0/q", name="env 0 Q-values"),
                rrb.TimeSeriesView(
                    origin=f"{root}/env0",
                    name="env 0",
                    contents=[
                        f"{root}/env0/speed_kmh",
                        f"{root}/env0/action",
                        f"{root}/env0/reward",
                        f"{root}/env0/reward_terms/**",
                    ],
                ),
            ),
        ),
        rrb.TimePanel(timeline="step"),
        collapse_panels=True,
    )


class TrainingRecording:
    """Logs one training run's episodes and learning statistics to a RecordingStream."""

    def __init__(self, stream: Any, run: str) -> None:
        import rerun as rr

        self.rr, self.stream, self.root = rr, stream, f"trainer/{run}"
        self._series_named = False

    def episode(self, step: int, metrics: dict[str, float]) -> None:
        rr = self.rr
        self.stream.set_time("step", sequence=step)
        for name, value in metrics.items():
            self.stream.log(f"{self.root}/episode/{name}", rr.Scalars(float(value)))

    def learning(self, step: int, entry: dict[str, Any]) -> None:
        rr = self.rr
        self.stream.set_time("step", sequence=step)
        for name in LEARNING_SERIES:
            value = entry.get(name)
            if value is not None:
                self.stream.log(f"{self.root}/learning/{name}", rr.Scalars(float(value)))

    def car_view(
        self,
        step: int,
        obs: dict[str, np.ndarray],
        action: int,
        q: np.ndarray,
        reward: float,
        terms: dict[str, float],
    ) -> None:
        """One environment's latest frame (``obs`` unbatched: ``lidar`` (R,) metres, ``camera``
        (H, W[, 3]) uint8, ``ego`` with speed in m/s first), the action it took, the Q-values
        of every action, and the reward it got for it with each term."""
        rr, stream, base = self.rr, self.stream, f"{self.root}/env0"
        if not self._series_named:
            for name in ACTION_NAMES:
                stream.log(f"{base}/q/{name}", rr.SeriesLines(names=name), static=True)
            self._series_named = True
        stream.set_time("step", sequence=step)
        lidar = obs.get("lidar")
        if lidar is not None:
            stream.log(
                f"{base}/lidar/hits",
                rr.Points2D(lidar_hits(lidar), radii=[0.25], colors=[[255, 128, 0]]),
            )
            stream.log(
                f"{base}/lidar/car",
                rr.Boxes2D(centers=[[0.0, 0.0]], half_sizes=[[2.25, 0.9]], colors=[[230, 40, 40]]),
            )
        camera = obs.get("camera")
        if camera is not None:
            stream.log(f"{base}/camera", rr.Image(camera))
        ego = obs.get("ego")
        if ego is not None:
            stream.log(f"{base}/speed_kmh", rr.Scalars(float(ego[0]) * 3.6))
        stream.log(f"{base}/action", rr.Scalars(float(action)))
        for name, value in zip(ACTION_NAMES, q):
            stream.log(f"{base}/q/{name}", rr.Scalars(float(value)))
        stream.log(f"{base}/q_chosen", rr.Scalars(float(q[action])))
        stream.log(f"{base}/reward", rr.Scalars(float(reward)))
        for name, value in terms.items():
            stream.log(f"{base}/reward_terms/{name}", rr.Scalars(float(value)))
