"""A/B of two versions of the simulator: simulated seconds per CPU second, measured in turns.

On a shared 2-vCPU VM the same code's throughput drifts by 10-30% between runs, so a change
worth a few per cent cannot be seen by comparing two runs of ``bench.bench_sim``. Here short
child processes measure the working tree's simulator and another git revision's (checked out in
a temporary worktree and put first on that child's PYTHONPATH) in alternating turns, the order
flipped every round, so that both see the same drift. Each child times one arena
(``gymnasium.make``) and a batch of arenas (``gymnasium.make_vec``) exactly as
``bench.bench_sim`` does, with the same seeds and random actions.

    .venv/bin/python -m bench.bench_sim_ab --baseline REV [--rounds 6]

It prints, per arena count, the median over rounds of the working tree's simulated seconds per
CPU second divided by the baseline's (above 1: the working tree is faster) and its spread.

When even paired timings drown in the machine's noise, ``--mode instructions`` counts the CPU
instructions a decision takes instead, with valgrind's callgrind (deterministic: the same code,
inputs and environment give the same count, whatever else the machine does). Each side runs
the same random decisions twice, D and 2D of them, in a child under callgrind; the difference
divided by D is the instructions per decision, free of start-up and import costs.

    .venv/bin/python -m bench.bench_sim_ab --baseline REV --mode instructions
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

ROOT = Path(__file__).resolve().parents[1]
SIDES = ("baseline", "working tree")


@dataclass(frozen=True)
class SimABConfig:
    baseline: str
    """The git revision whose simulator is compared with the working tree's."""
    rounds: int = 6
    """Turns per side; the order of the two sides flips every round."""
    single_decisions: int = 1500
    """Timed decisions of one arena per turn."""
    batch_arenas: int = 64
    batch_arena_decisions: int = 16000
    """Timed arena-decisions of the batch per turn."""
    seed: int = 0
    mode: Literal["time", "instructions"] = "time"
    """time: CPU-time throughput in alternating turns; instructions: callgrind's counts."""
    instruction_decisions: int = 60
    """instructions mode: D, the decisions of one arena counted (the child runs D and 2D)."""
    instruction_batch_steps: int = 6
    """instructions mode: D for the batch, in vector steps."""
    json: Path | None = None


def measure_child(config: SimABConfig) -> dict[str, Any]:
    """In a child process: both measurements of whichever overtake is first on the path, and
    where that overtake's simulator was loaded from."""
    from bench.bench_sim import measure_overtake_batch, measure_overtake_single, pin_threads

    pin_threads(1)
    single, _ = measure_overtake_single(config.single_decisions, 100, config.seed)
    batch = measure_overtake_batch(
        config.batch_arenas, config.batch_arena_decisions, 20, config.seed
    )
    import overtake.server

    return {
        "source": str(Path(overtake.server.__file__).resolve().parent),
        "sim_s_per_cpu_s": {
            "1": single.sim_seconds_per_cpu_second,
            str(config.batch_arenas): batch.sim_seconds_per_cpu_second,
        },
    }


def _turn(config: SimABConfig, path: str | None) -> dict[str, float]:
    env = dict(os.environ)
    if path is not None:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (path, env.get("PYTHONPATH")) if p)
    argv = [
        sys.executable,
        "-m",
        "bench.bench_sim_ab",
        "--baseline",
        config.baseline,
        "--single-decisions",
        str(config.single_decisions),
        "--batch-arenas",
        str(config.batch_arenas),
        "--batch-arena-decisions",
        str(config.batch_arena_decisions),
        "--seed",
        str(config.seed),
    ]
    done = subprocess.run(
        argv,
        env={**env, "OVERTAKE_SIM_AB_CHILD": "1"},
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
        timeout=600,
    )
    result = json.loads(done.stdout.strip().splitlines()[-1])
    # The measured code must be the side's: the baseline's worktree, or this checkout.
    expected = Path(path).resolve() if path is not None else ROOT
    if not Path(result["source"]).is_relative_to(expected.parent if path else expected):
        raise RuntimeError(f"the turn meant for {expected} measured {result['source']}")
    return result["sim_s_per_cpu_s"]


# What an instructions-mode child runs: ``steps`` random decisions of ``arenas`` arenas, made
# exactly as bench_sim makes them (no warm-up: start-up costs cancel in the difference).
_COUNTED_CHILD = """
import sys
from bench.bench_sim import measure_overtake_batch, measure_overtake_single, pin_threads
pin_threads(1)
arenas, steps, seed = map(int, sys.argv[1:4])
if arenas == 1:
    measure_overtake_single(steps, 0, seed)
else:
    measure_overtake_batch(arenas, arenas * steps, 0, seed)
"""


def _instructions(path: str | None, arenas: int, steps: int, seed: int) -> int:
    """Instructions callgrind counts for a child running ``steps`` steps of ``arenas``."""
    env = dict(os.environ)
    if path is not None:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (path, env.get("PYTHONPATH")) if p)
    with tempfile.TemporaryDirectory() as tmp:
        done = subprocess.run(
            [
                "valgrind",
                "--tool=callgrind",
                f"--callgrind-out-file={tmp}/out",
                sys.executable,
                "-c",
                _COUNTED_CHILD,
                str(arenas),
                str(steps),
                str(seed),
            ],
            env=env,
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
            timeout=3600,
        )
    for line in done.stderr.splitlines():
        if "Collected :" in line:
            return int(line.rsplit(":", 1)[1].strip())
    raise RuntimeError(f"callgrind reported no count:\n{done.stderr[-2000:]}")


def count_instructions(config: SimABConfig, baseline_path: str) -> dict[str, Any]:
    """Instructions per decision (1 arena) and per arena-decision (the batch), both sides."""
    cases = {
        "1": (1, config.instruction_decisions),
        str(config.batch_arenas): (config.batch_arenas, config.instruction_batch_steps),
    }
    counts: dict[str, dict[str, float]] = {}
    for side, path in (("baseline", baseline_path), ("working tree", None)):
        counts[side] = {}
        for key, (arenas, steps) in cases.items():
            once = _instructions(path, arenas, steps, config.seed)
            twice = _instructions(path, arenas, 2 * steps, config.seed)
            counts[side][key] = (twice - once) / (steps * arenas)
            print(
                f"{side:>12}: {key} arena(s) {counts[side][key]:,.0f} instructions per "
                "arena-decision",
                flush=True,
            )
    summary = {
        key: {"ratio": counts["working tree"][key] / counts["baseline"][key]} for key in cases
    }
    for key, value in summary.items():
        print(f"{key} arena(s): working tree / baseline instructions = {value['ratio']:.4f}")
    return {"instructions_per_arena_decision": counts, "summary": summary}


def main(config: SimABConfig) -> dict[str, Any]:
    from bench.bench_server_ab import checkout

    if config.mode == "instructions":
        where = Path(tempfile.mkdtemp(prefix="overtake-sim-ab-"))
        try:
            result = count_instructions(config, str(checkout(config.baseline, where)))
        finally:
            subprocess.run(
                ["git", "worktree", "remove", "--force", str(where / "tree")], cwd=ROOT, check=False
            )
            shutil.rmtree(where, ignore_errors=True)
        report = {
            "config": {
                **config.__dict__,
                "json": None if config.json is None else str(config.json),
            },
            **result,
        }
        if config.json is not None:
            config.json.parent.mkdir(parents=True, exist_ok=True)
            config.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
        return report

    where = Path(tempfile.mkdtemp(prefix="overtake-sim-ab-"))
    turns: dict[str, list[dict[str, float]]] = {side: [] for side in SIDES}
    try:
        baseline_path = str(checkout(config.baseline, where))
        print(f"baseline {config.baseline} from {where / 'tree'}; working tree {ROOT}")
        for index in range(config.rounds):
            for side in SIDES if index % 2 == 0 else SIDES[::-1]:
                figures = _turn(config, baseline_path if side == "baseline" else None)
                turns[side].append(figures)
                print(
                    f"round {index + 1} {side:>12}: "
                    + ", ".join(f"{k} arena(s) {v:,.1f} sim s/CPU s" for k, v in figures.items()),
                    flush=True,
                )
    finally:
        subprocess.run(
            ["git", "worktree", "remove", "--force", str(where / "tree")], cwd=ROOT, check=False
        )
        shutil.rmtree(where, ignore_errors=True)
    summary = {}
    for arenas in turns["baseline"][0]:
        ratios = sorted(
            new[arenas] / old[arenas]
            for old, new in zip(turns["baseline"], turns["working tree"], strict=True)
        )
        summary[arenas] = {"median": statistics.median(ratios), "min": ratios[0], "max": ratios[-1]}
        print(
            f"{arenas} arena(s): working tree / baseline = {summary[arenas]['median']:.3f} "
            f"(median of {len(ratios)} rounds; {ratios[0]:.3f} to {ratios[-1]:.3f})"
        )
    report = {
        "config": {**config.__dict__, "json": None if config.json is None else str(config.json)},
        "turns": turns,
        "summary": summary,
    }
    if config.json is not None:
        config.json.parent.mkdir(parents=True, exist_ok=True)
        config.json.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    return report


def cli() -> None:
    config = tyro.cli(SimABConfig, description=__doc__)
    if os.environ.get("OVERTAKE_SIM_AB_CHILD"):
        print(json.dumps(measure_child(config)))
    else:
        main(config)


if __name__ == "__main__":
    cli()
