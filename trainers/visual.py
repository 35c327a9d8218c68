"""What a trainer shows in Rerun, on the ``step`` timeline (environment steps):

- ``trainer/<run>/episode/<metric>``: every episode's return and the papers' metrics (average
  speed, lane changes, overtakes, collisions, emergency brakes, ...), as the episode ends;
- ``trainer/<run>/learning/<name>``: loss, epsilon, the mean Q of the actions taken in the
  updates, and steps per second, once per log line (``--log-every``).

Both are logged at most once per episode or log line, so recording costs the training loop
nothing measurable.
"""

from __future__ import annotations

from typing import Any

LEARNING_SERIES = ("loss", "epsilon", "q_taken", "steps_per_s")


def training_blueprint(run: str) -> Any:
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.TimeSeriesView(origin=f"/trainer/{run}/episode", name=f"{run}: episodes"),
            rrb.TimeSeriesView(origin=f"/trainer/{run}/learning", name=f"{run}: learning")),
        rrb.TimePanel(timeline="step"), collapse_panels=True)


class TrainingRecording:
    """Logs one training run's episodes and learning statistics to a RecordingStream."""

    def __init__(self, stream: Any, run: str) -> None:
        import rerun as rr

        self.rr, self.stream, self.root = rr, stream, f"trainer/{run}"

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
