"""The experiment's learning curves: curves.png (matplotlib) and curves.rrd (Rerun), one line
per row, from the training episodes' bins and, where the experiment plots it, the training
reward per window with its reference lines."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from overtake.viz.recording import RecordingConfig, close_recording, open_recording

from .catalogue import CURVE_METRICS

ROW_COLORS = (
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
)


def plot_curves(curves: dict[str, Any], title: str, path: Path) -> None:
    """curves.png: one panel per curve metric, one line per row (with the band between its
    runs' lowest and highest bin means where it has several)."""
    # The object-oriented API draws with the Agg canvas and touches no global pyplot state.
    from matplotlib.figure import Figure

    windowed = [row for row, curve in curves.items() if "window_reward" in curve]
    panels = len(CURVE_METRICS) + (1 if windowed else 0)
    figure = Figure(figsize=(7.0, 3.2 * panels), layout="constrained")
    axes = figure.subplots(panels, 1, sharex=True, squeeze=False)[:, 0]
    if windowed:
        ax = axes[-1]
        for row in windowed:
            window = curves[row]["window_reward"]
            ax.plot(window["window_end_step"], window["mean"], marker=".", label=row)
        for name, value in curves[windowed[0]].get("window_reference", {}).items():
            ax.axhline(value, linestyle="--", color="grey", label=f"{name}: {value:,.0f}")
        steps = curves[windowed[0]]["window_reward"]["window_end_step"]
        size = steps[0] if steps else 0
        ax.set_ylabel(f"reward per {size:,} steps")
        ax.legend(fontsize="small")
        ax.grid(alpha=0.3)
    for ax, (metric, label) in zip(axes, CURVE_METRICS):
        for row, curve in curves.items():
            steps = np.array(curve["bin_end_step"], dtype=float)
            mean = _floats(curve[metric]["mean"])
            # Bins no episode ended in are skipped, so that the line joins its neighbours.
            ok = ~np.isnan(mean)
            (line,) = ax.plot(steps[ok], mean[ok], marker=".", label=row)
            if curve["runs"] > 1:
                ax.fill_between(
                    steps[ok],
                    _floats(curve[metric]["run_min"])[ok],
                    _floats(curve[metric]["run_max"])[ok],
                    color=line.get_color(),
                    alpha=0.2,
                    linewidth=0,
                )
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("training steps")
    axes[-1].set_xlim(0, max(max(c["bin_end_step"]) for c in curves.values()))
    axes[0].legend(fontsize="small")
    axes[0].set_title(title, fontsize="medium")
    tmp = path.with_name(path.name + ".tmp")
    figure.savefig(tmp, format="png", dpi=100)
    os.replace(tmp, path)


def _floats(values: list[float | None]) -> np.ndarray:
    return np.array([math.nan if v is None else v for v in values], dtype=float)


# matplotlib's default cycle (tab10), so that curves.rrd and curves.png colour rows alike.


def record_curves(curves: dict[str, Any], experiment: str, path: Path) -> None:
    """curves.rrd: ``curves/<metric>/<row>`` on the ``step`` timeline, one entity per row."""
    import rerun as rr
    import rerun.blueprint as rrb

    metrics = list(CURVE_METRICS)
    if any("window_reward" in curve for curve in curves.values()):
        metrics.append(("window_reward", "reward per window of training steps"))
    # Without a range the viewer shows a narrow window around the time cursor; a learning curve
    # is read whole.
    whole_run = rrb.archetypes.TimeAxis(
        view_range=rr.TimeRange(
            start=rr.TimeRangeBoundary.infinite(), end=rr.TimeRangeBoundary.infinite()
        )
    )
    blueprint = rrb.Blueprint(
        rrb.Vertical(
            *(
                rrb.TimeSeriesView(origin=f"/curves/{metric}", name=label, axis_x=whole_run)
                for metric, label in metrics
            )
        ),
        rrb.TimePanel(timeline="step"),
        collapse_panels=True,
    )
    tmp = path.with_name(path.name + ".tmp")
    recording = open_recording(
        f"overtake-experiment {experiment}", RecordingConfig(sink="file", rrd=tmp), tmp, blueprint
    )
    assert recording is not None  # sink=file always opens one
    stream = recording.stream
    try:
        for index, (row, curve) in enumerate(curves.items()):
            color = ROW_COLORS[index % len(ROW_COLORS)]
            for metric, _ in metrics:
                if metric not in curve:
                    continue
                entity = f"curves/{metric}/{row}"
                # One colour per row in every plot, as in curves.png; the viewer's own pick
                # hashes the entity path and colours a row differently from plot to plot.
                stream.log(entity, rr.SeriesLines(names=row, colors=color), static=True)
                steps = curve[metric].get("window_end_step", curve["bin_end_step"])
                for step, value in zip(steps, curve[metric]["mean"]):
                    if value is not None:
                        stream.set_time("step", sequence=step)
                        stream.log(entity, rr.Scalars(value))
    finally:
        close_recording(recording)
    os.replace(tmp, path)
