"""What the table says of the episodes: means and spreads, per seed, the order of rows against
the seed spread, and the learning curves."""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

from overtake.protocol.vocabulary import METRIC_FIELDS, WATCH_METRICS

from .catalogue import CURVE_METRICS, EPISODE_METRICS


def episode_statistics(episodes: Sequence[dict[str, float]]) -> dict[str, Any]:
    """Mean and spread (standard deviation) over ``episodes`` of every metric and of each
    episode's collisions per 1,000 decisions; the pooled collision rate and the count."""
    table = {
        name: np.array([episode[name] for episode in episodes], dtype=float)
        for name in METRIC_FIELDS
    }
    table["collisions_per_1000_decisions"] = (
        1000.0 * table["collisions"] / np.maximum(table["decisions"], 1.0)
    )
    # What safety did, where it ran (the shield's overrides, the lane changes driver assistance
    # turned back): per episode and per km driven.
    km = np.maximum(table["distance_m"], 1.0) / 1000.0
    for name in ("shield_overrides", *WATCH_METRICS):
        if episodes and all(name in episode for episode in episodes):
            table[name] = np.array([e[name] for e in episodes], float)
            table[f"{name}_per_km"] = table[name] / km
    stats: dict[str, Any] = {
        name: {"mean": float(values.mean()), "std": float(values.std())}
        for name, values in table.items()
    }
    stats["pooled_collisions_per_1000_decisions"] = float(
        1000.0 * table["collisions"].sum() / max(table["decisions"].sum(), 1.0)
    )
    stats["episodes"] = len(episodes)
    return stats


def seed_statistics(per_seed: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Each metric's per-seed means and their spread over the seeds."""
    return {
        name: {
            "means": [s[name]["mean"] for s in per_seed],
            "std": float(np.std([s[name]["mean"] for s in per_seed])),
        }
        for name in EPISODE_METRICS
    }


def seed_order(rows: Sequence[dict[str, Any]], metric: str = "avg_speed_kmh") -> list[dict]:
    """The order of the rows trained from several seeds, judged against the seed spread: for
    every pair, the row with the higher mean of its seeds' means, and whether the order holds
    beyond the spread, that is every seed of the higher row above every seed of the lower (the
    test a table of a few seeds can bear: with two seeds a confidence interval from their
    means would span tens of km/h)."""
    several = sorted(
        (row for row in rows if len(row["runs"]) > 1),
        key=lambda row: -float(np.mean(row["seeds"][metric]["means"])),
    )
    order = []
    for i, high in enumerate(several):
        for low in several[i + 1 :]:
            highs, lows = high["seeds"][metric]["means"], low["seeds"][metric]["means"]
            order.append(
                {
                    "higher": high["label"],
                    "lower": low["label"],
                    "difference": float(np.mean(highs) - np.mean(lows)),
                    "beyond_seed_spread": min(highs) > max(lows),
                }
            )
    return order


def learning_curves(
    episodes_by_run: dict[str, list[dict[str, Any]]], total_steps: int, bins: int
) -> dict[str, Any]:
    """A row's learning curves: per bin of ``total_steps / bins`` steps, the mean of the
    training episodes that ended in it (over all the row's runs), and the lowest and highest
    of the runs' own means. Empty bins are None."""
    edges = np.linspace(0, total_steps, bins + 1)
    curves: dict[str, Any] = {"bin_end_step": [round(float(e)) for e in edges[1:]]}
    for metric, _ in CURVE_METRICS:
        pooled: list[float | None] = []
        low: list[float | None] = []
        high: list[float | None] = []
        for lo, hi in itertools.pairwise(edges):
            chosen = {
                run: [e[metric] for e in episodes if lo < e["step"] <= hi]
                for run, episodes in episodes_by_run.items()
            }
            values = [v for vs in chosen.values() for v in vs]
            means = [float(np.mean(vs)) for vs in chosen.values() if vs]
            pooled.append(float(np.mean(values)) if values else None)
            low.append(min(means) if means else None)
            high.append(max(means) if means else None)
        curves[metric] = {"mean": pooled, "run_min": low, "run_max": high}
    return curves
