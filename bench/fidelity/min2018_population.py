"""min2018's traffic population over an episode: the authors' spawners against the treadmill.

    .venv/bin/python -m bench.fidelity.min2018_population [--episodes 20] [--json PATH]

Issue 68 gave min2018 its authors' spawners (``traffic.entry = "spawners"``): the road starts
empty, eight spawners bring cars on their own timing up to the density's count, and cars leave
beyond 100 m or when they touch. Before, a treadmill (``"comfortable"``) kept the count on the
road from the first decision. For each density and each way, the rule driver drives
``episodes`` whole episodes in process (seeds ``seed`` on, the same for both ways); after every
decision of each episode the traffic cars on the road are counted from the arena's world frame.
It reports, per density and way: the population's mean over the episodes' decisions and its
percentiles, its mean at given times after the reset (the rise), the share of decisions at the
count, the cars that left by touching another (a car gone from the road within 100 m of the
host) per episode, and the driver's speed and collisions.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bench.harness import write_report

DENSITIES = ("light", "medium", "heavy")
ENTRIES = ("comfortable", "spawners")  # the treadmill before issue 68, the authors' since
# Times after a reset (s) at which the population's mean is reported: its rise.
RISE_AT_S = (0.4, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 120.0)
DECISION_S = 0.4


@dataclass(frozen=True)
class PopulationConfig:
    episodes: int = 20
    """whole episodes (2,600 m) per density and way, driven side by side"""
    seed: int = 1000
    """the first episode's seed (the existing min2018 reference rows use 1000 on)"""
    json: Path | None = None
    """write every figure here"""


class PopulationWatcher:
    """Counts each environment's traffic cars after every decision of its first episode, and
    the cars that left within 100 m of the host (by touching another)."""

    def __init__(self, envs: Any, episodes: int) -> None:
        self.road = envs.simulator.road
        self.episodes = episodes
        self.counts: list[list[int]] = [[] for _ in range(episodes)]
        self.touched = np.zeros(episodes, dtype=np.int64)
        self.done = np.zeros(episodes, dtype=bool)
        self.active: list[np.ndarray] = []

    def _frames(self) -> list[Any]:
        return [self.road.world_frame(i) for i in range(self.episodes)]

    def started(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.active = [frame.active.copy() for frame in self._frames()]

    def stepped(self, step: Any) -> None:
        ended = step.terminated | step.truncated
        for i, frame in enumerate(self._frames()):
            if self.done[i]:
                continue
            host_x, host_y = frame.x_m[0], frame.y_m[0]
            gone = self.active[i] & ~frame.active
            gone[0] = False
            near = np.hypot(frame.x_m - host_x, frame.y_m - host_y) <= 100.0
            self.touched[i] += int((gone & near).sum())
            self.counts[i].append(int(frame.active[1:].sum()))
            self.active[i] = frame.active.copy()
            self.done[i] = bool(ended[i])


def measure(density: str, entry: str, config: PopulationConfig) -> dict[str, Any]:
    """One density and way: the population's figures and the driver's."""
    from overtake.client.episodes.runner import baseline_policy, run_episodes
    from overtake.client.episodes.scenario import Where

    overrides = {"traffic.density": density, "traffic.entry": entry}
    envs = Where().open("min2018", overrides, config.episodes)
    try:
        count = envs.sim_config["traffic"]["density_vehicle_counts"][DENSITIES.index(density)]
        policy = baseline_policy("rule", envs.behaviour_spec, config.seed, config.episodes)
        watcher = PopulationWatcher(envs, config.episodes)
        started = time.perf_counter()
        rows, decisions, _ = run_episodes(
            envs, policy, config.episodes, config.seed, watchers=[watcher]
        )
        elapsed_s = time.perf_counter() - started
    finally:
        envs.close()
    every = np.concatenate([np.asarray(c, dtype=np.float64) for c in watcher.counts])
    rise = {}
    for at_s in RISE_AT_S:
        index = round(at_s / DECISION_S) - 1
        present = [c[index] for c in watcher.counts if len(c) > index]
        rise[f"{at_s:g}"] = float(np.mean(present)) if present else None
    p10, p50, p90 = np.percentile(every, [10, 50, 90])
    return {
        "count": count,
        "episodes": len(rows),
        "decisions": int(every.size),
        "mean": float(every.mean()),
        "metric_traffic_cars": float(np.mean([row["traffic_cars"] for row in rows])),
        "min": float(every.min()),
        "p10": float(p10),
        "p50": float(p50),
        "p90": float(p90),
        "max": float(every.max()),
        "at_count_share": float((every >= count).mean()),
        "rise": rise,
        "touched_per_episode": float(watcher.touched.mean()),
        "speed_kmh": float(np.mean([row["avg_speed_kmh"] for row in rows])),
        "speed_kmh_std": float(np.std([row["avg_speed_kmh"] for row in rows])),
        "collisions": int(sum(row["collisions"] for row in rows)),
        "decisions_per_s": decisions / elapsed_s,
    }


def table(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    lines = [
        "| density (count) | traffic | cars on the road: mean (10th / 50th / 90th pct, min-max) "
        "| at the count | left by touching / episode | rule driver km/h | collisions |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for density, ways in results.items():
        for entry, r in ways.items():
            lines.append(
                f"| {density} ({r['count']}) | {entry} | {r['mean']:.1f} ({r['p10']:.0f} / "
                f"{r['p50']:.0f} / {r['p90']:.0f}, {r['min']:.0f}-{r['max']:.0f}) | "
                f"{100 * r['at_count_share']:.0f}% | {r['touched_per_episode']:.2f} | "
                f"{r['speed_kmh']:.1f} ± {r['speed_kmh_std']:.1f} | {r['collisions']} |"
            )
    lines += [
        "",
        "| density | traffic | " + " | ".join(f"{t:g} s" for t in RISE_AT_S) + " |",
        "|---|---|" + "---:|" * len(RISE_AT_S),
    ]
    for density, ways in results.items():
        for entry, r in ways.items():
            cells = [
                "-" if r["rise"][f"{t:g}"] is None else f"{r['rise'][f'{t:g}']:.1f}"
                for t in RISE_AT_S
            ]
            lines.append(f"| {density} | {entry} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(config: PopulationConfig) -> dict[str, Any]:
    from overtake.client.provenance import git_commit

    results = {
        density: {entry: measure(density, entry, config) for entry in ENTRIES}
        for density in DENSITIES
    }
    report = {
        "config": {k: str(v) for k, v in dataclasses.asdict(config).items()},
        "command": " ".join(["python -m bench.fidelity.min2018_population", *sys.argv[1:]]),
        "commit": git_commit(),
        "results": results,
    }
    print(table(results))
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    import tyro

    main(tyro.cli(PopulationConfig))
