"""Tables for bench/RESULTS.md from training runs and their evaluations.

    .venv/bin/python -m bench.fidelity.learning_table --evals runs/results/eval/*.json \
        --runs runs/results/*/ --bin-steps 5000

- the evaluation table in the shape of Min et al.'s Table III, with the baselines' rows: mean ±
  spread over the evaluation episodes, and collisions per 1,000 decisions;
- learning curves: per run, the mean of the training episodes' metrics that ended in each bin
  of ``bin_steps`` environment steps (these episodes were driven epsilon-greedily).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class TableConfig:
    evals: tuple[Path, ...] = ()
    """overtake-eval --json-out files"""
    runs: tuple[Path, ...] = ()
    """overtake-train run directories"""
    bin_steps: int = 5_000


def evaluation_table(paths: tuple[Path, ...]) -> str:
    lines = [
        "| policy | run | training steps | avg speed km/h | lane changes | overtakes "
        "| collisions | emergency brakes | return | collisions / 1,000 decisions |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for path in paths:
        result = json.loads(path.read_text())
        s = result["summary"]
        name = result["name"]
        steps = name.rsplit("@", 1)[1] if "@" in name else "-"
        run = Path(result["checkpoint"]).parent.name if result["checkpoint"] else "-"

        def cell(metric: str, s: dict = s) -> str:
            return f"{s[metric]['mean']:.1f} ± {s[metric]['std']:.1f}"

        lines.append(
            f"| {name.rsplit('@', 1)[0]} | {run} | {steps} | {cell('avg_speed_kmh')} | "
            f"{cell('lane_changes')} | {cell('overtakes')} | {cell('collisions')} | "
            f"{cell('emergency_brakes')} | {cell('return')} | "
            f"{s['collisions_per_1000_decisions']:.2f} |"
        )
    return "\n".join(lines)


def learning_curves(runs: tuple[Path, ...], bin_steps: int) -> str:
    out = []
    for run in runs:
        records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        episodes = [r for r in records if r["kind"] == "episode"]
        if not episodes:
            continue
        last = max(r["step"] for r in episodes)
        out.append(
            f"{run.name}: steps | episodes | avg speed km/h | collisions / 1,000 "
            "decisions | lane changes / episode | return / episode"
        )
        for start in range(0, last + 1, bin_steps):
            chunk = [r for r in episodes if start < r["step"] <= start + bin_steps]
            if not chunk:
                continue
            decisions = sum(r["decisions"] for r in chunk)
            out.append(
                f"  {start:>6}-{start + bin_steps:<6} {len(chunk):>3} "
                f"{np.mean([r['avg_speed_kmh'] for r in chunk]):6.1f} "
                f"{1000 * sum(r['collisions'] for r in chunk) / decisions:6.2f} "
                f"{np.mean([r['lane_changes'] for r in chunk]):7.1f} "
                f"{np.mean([r['return'] for r in chunk]):7.1f}"
            )
    return "\n".join(out)


def main(config: TableConfig) -> None:
    if config.evals:
        print(evaluation_table(config.evals))
    if config.runs:
        print()
        print(learning_curves(config.runs, config.bin_steps))


if __name__ == "__main__":
    import tyro

    main(tyro.cli(TableConfig))
