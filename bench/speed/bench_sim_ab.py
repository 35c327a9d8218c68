"""A/B of two versions of the simulator: its CPU cost per decision, measured side by side.

On a shared 2-vCPU VM the same code's throughput drifts by 10-30% between runs, so a change
worth a few per cent cannot be seen by comparing two runs of ``bench.speed.bench_sim``. Two ways of
comparing the working tree's simulator with another git revision's (checked out in a temporary
worktree and put first on its processes' PYTHONPATH):

``--mode time`` (the default): two worker processes, one per side, each holding the same
environment (one arena through ``gymnasium.make``, then a batch through
``gymnasium.make_vec``, exactly as ``bench.speed.bench_sim`` builds them) with the same seed. The
benchmark asks them in turn, order flipped every round, to drive a short chunk of random
decisions; each reports the CPU seconds of its own process for it. Where the two versions
behave alike, both sides run the very same episodes (the simulator is deterministic), so each
round's pair of chunks did the same work, half a second apart: the drift of the machine falls
on both alike (where they behave differently, the report says so, and the chunks are the same
decisions of different episodes). It prints, per arena count, the median over rounds of the
working tree's CPU seconds per arena-decision divided by the baseline's (below 1: the working
tree is faster) and the middle half of those ratios.

``--mode instructions``: the CPU instructions a decision takes, counted by valgrind's
callgrind (the same code, inputs and environment give nearly the same count, whatever else the
machine does). Each side runs the same random decisions twice, D and 2D of them, in a child
under callgrind; the difference divided by D is the instructions per decision, free of
start-up and import costs.

    .venv/bin/python -m bench.speed.bench_sim_ab --baseline REV [--rounds 40]
    .venv/bin/python -m bench.speed.bench_sim_ab --baseline REV --mode instructions
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import tyro

from bench.harness import write_report
from bench.speed.bench_sim import PRESET

ROOT = Path(__file__).resolve().parents[2]
SIDES = ("baseline", "working tree")


@dataclass(frozen=True)
class SimABConfig:
    baseline: str
    """The git revision whose simulator is compared with the working tree's."""
    mode: Literal["time", "instructions"] = "time"
    """time: CPU seconds of paired chunks in two workers; instructions: callgrind's counts."""
    rounds: int = 40
    """time mode: chunks per side and arena count; the order flips every round."""
    single_chunk: int = 200
    """time mode: decisions of one arena per chunk."""
    batch_arenas: int = 64
    batch_chunk: int = 4
    """time mode: vector steps of the batch per chunk."""
    warmup: int = 2
    """time mode: untimed chunks per side before the rounds."""
    instruction_decisions: int = 60
    """instructions mode: D, the decisions of one arena counted (the child runs D and 2D)."""
    instruction_batch_steps: int = 6
    """instructions mode: D for the batch, in vector steps."""
    preset: str = PRESET
    """The preset both sides run, with its default sensors (``gymnasium.make`` of
    overtake/Highway-v0)."""
    seed: int = 0
    json: Path | None = None


def _side_env(path: str | None) -> dict[str, str]:
    """The environment of a process measuring a side: the baseline's overtake first on its
    path, or the working tree's as installed."""
    env = dict(os.environ)
    if path is not None:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (path, env.get("PYTHONPATH")) if p)
    return env


# --- time mode: two workers, paired chunks ----------------------------------------------------

# A worker: builds one environment as bench_sim does, then drives as many random decisions as
# each line on stdin asks and answers with one JSON line: its CPU seconds and the arena-
# decisions that advanced (a vector env's autoreset steps advance none).
_WORKER = """
import json, sys, time
from bench.speed.bench_sim import ENV_ID, pin_threads
pin_threads(1)
import gymnasium, numpy as np
import overtake.client, overtake.server
arenas, seed, preset = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
rng = np.random.default_rng(seed)
if arenas == 1:
    env = gymnasium.make(ENV_ID, preset=preset)
    env.reset(seed=seed)
    def drive(steps):
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(int(rng.integers(5)))
            if terminated or truncated:
                env.reset()
        return steps
else:
    env = gymnasium.make_vec(ENV_ID, num_envs=arenas, vectorization_mode="vector_entry_point",
                             preset=preset)
    env.reset(seed=seed)
    autoreset = np.zeros(arenas, dtype=bool)
    def drive(steps):
        global autoreset
        advanced = 0
        for _ in range(steps):
            _, _, terminated, truncated, _ = env.step(rng.integers(5, size=arenas))
            advanced += arenas - int(autoreset.sum())
            autoreset = terminated | truncated
        return advanced
print(json.dumps({"source": overtake.server.__file__}), flush=True)
for line in sys.stdin:
    steps = int(line)
    start = time.process_time()
    advanced = drive(steps)
    print(json.dumps({"cpu_s": time.process_time() - start, "decisions": advanced}),
          flush=True)
"""


class Worker:
    """A process holding one side's environment, driving chunks on request."""

    def __init__(self, path: str | None, arenas: int, seed: int, preset: str) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _WORKER, str(arenas), str(seed), preset],
            env=_side_env(path),
            cwd=ROOT,
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        self.source = Path(self._answer()["source"]).resolve()
        # The measured code must be the side's: the baseline's worktree, or this checkout.
        expected = Path(path).resolve().parent if path is not None else ROOT
        if not self.source.is_relative_to(expected):
            self.close()
            raise RuntimeError(f"the worker meant for {expected} loaded {self.source}")

    def _answer(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"a worker exited with {self.proc.wait()}")
        return json.loads(line)

    def chunk(self, steps: int) -> dict[str, Any]:
        assert self.proc.stdin is not None
        self.proc.stdin.write(f"{steps}\n")
        self.proc.stdin.flush()
        return self._answer()

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def time_paired(config: SimABConfig, baseline_path: str) -> dict[str, Any]:
    """Per arena count: each round's CPU seconds of both sides for the same chunk."""
    cases = {
        "1": (1, config.single_chunk),
        str(config.batch_arenas): (config.batch_arenas, config.batch_chunk),
    }
    results: dict[str, Any] = {}
    for key, (arenas, steps) in cases.items():
        workers = {
            side: Worker(
                baseline_path if side == "baseline" else None, arenas, config.seed, config.preset
            )
            for side in SIDES
        }
        try:
            for _ in range(config.warmup):
                for worker in workers.values():
                    worker.chunk(steps)
            chunks: dict[str, list[dict[str, Any]]] = {side: [] for side in SIDES}
            for index in range(config.rounds):
                for side in SIDES if index % 2 == 0 else SIDES[::-1]:
                    chunks[side].append(workers[side].chunk(steps))
        finally:
            for worker in workers.values():
                worker.close()
        # Per arena-decision advanced: two versions that behave differently may spend a
        # different number of a batch's steps on autoresets.
        same_work = all(
            old["decisions"] == new["decisions"]
            for old, new in zip(chunks["baseline"], chunks["working tree"], strict=True)
        )
        ratios = sorted(
            (new["cpu_s"] / new["decisions"]) / (old["cpu_s"] / old["decisions"])
            for old, new in zip(chunks["baseline"], chunks["working tree"], strict=True)
        )
        quartiles = statistics.quantiles(ratios, n=4)
        per_decision_us = {
            side: 1e6
            * sum(c["cpu_s"] for c in chunks[side])
            / sum(c["decisions"] for c in chunks[side])
            for side in SIDES
        }
        results[key] = {
            "median_ratio": statistics.median(ratios),
            "quartiles": [quartiles[0], quartiles[2]],
            "slower_rounds": sum(r > 1.0 for r in ratios),
            "rounds": len(ratios),
            "same_episodes": same_work,
            "cpu_us_per_arena_decision": per_decision_us,
            "chunks": chunks,
        }
        print(
            f"{key} arena(s): working tree / baseline CPU time = "
            f"{results[key]['median_ratio']:.3f} (median of {len(ratios)} paired chunks; middle "
            f"half {quartiles[0]:.3f} to {quartiles[2]:.3f}; working tree slower in "
            f"{results[key]['slower_rounds']}); CPU per arena-decision "
            f"{per_decision_us['baseline']:.0f} vs {per_decision_us['working tree']:.0f} us"
            f"{'' if same_work else ' (the two behave differently: not the same episodes)'}",
            flush=True,
        )
    return results


# --- instructions mode ------------------------------------------------------------------------

# What an instructions-mode child runs: ``steps`` random decisions of ``arenas`` arenas, made
# exactly as bench_sim makes them (no warm-up: start-up costs cancel in the difference).
_COUNTED_CHILD = """
import sys
from bench.speed.bench_sim import measure_overtake_batch, measure_overtake_single, pin_threads
pin_threads(1)
arenas, steps, seed = map(int, sys.argv[1:4])
preset = sys.argv[4]
if arenas == 1:
    measure_overtake_single(steps, 0, seed, preset)
else:
    measure_overtake_batch(arenas, arenas * steps, 0, seed, preset)
"""


def _instructions(path: str | None, arenas: int, steps: int, seed: int, preset: str) -> int:
    """Instructions callgrind counts for a child running ``steps`` steps of ``arenas``."""
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
                preset,
            ],
            env=_side_env(path),
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
            once = _instructions(path, arenas, steps, config.seed, config.preset)
            twice = _instructions(path, arenas, 2 * steps, config.seed, config.preset)
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
    from bench.harness import baseline_checkout

    with baseline_checkout(config.baseline) as path:
        if config.mode == "instructions":
            result = count_instructions(config, str(path))
        else:
            result = time_paired(config, str(path))
    report = {
        "config": {**config.__dict__, "json": None if config.json is None else str(config.json)},
        "result": result,
    }
    write_report(config.json, report)
    return report


def cli() -> None:
    main(tyro.cli(SimABConfig, description=__doc__))


if __name__ == "__main__":
    cli()
