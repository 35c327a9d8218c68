"""Learning throughput: training agent-steps per CPU-second and per wall-second, the runs of a
table trained as lone processes (a baseline revision's code and this one's) against the same
runs trained as members of one learner (``overtake-train --seeds`` / the experiments' member
batches), in one run, at most ``--jobs`` processes at once; and Stable-Baselines3's own DQN
with the same recipe on ``overtake/highway-fast-v0`` and on highway-env's ``highway-fast-v0``,
the highway-env user's alternative.

The table's runs (an update every decision where the recipe says so):

- ``ho2018``: Table 8's ten runs, the baseline network twice and the proposed network at the
  four learning rates twice each (TF RMSProp, batch 32, an update every decision);
- ``min2018-notebook``: Min et al.'s notebook recipe, Dueling DQN on camera and LIDAR, two seeds
  (Adam, an update every step);
- ``highway-fast``: SB3's documented recipe on highway-env's scene, ten seeds (MLP 256x256,
  Adam, an update every step).

Each run trains ``--steps`` environment steps, learning from ``--learning-starts``: the
updates are most of the work, as in the papers' runs. Each process's CPU time (user + system,
from ``wait4``) and the arm's wall time are measured; agent-steps per CPU-second is the
steps of every run over the CPU time of every process (start-up included: members pay it once
per batch). With ``--startup`` (the default) each arm's processes also run for one step, and
the steady state's figures subtract that start-up. Pause other work first: ratios on a busy
machine mislead.

    .venv/bin/python -m bench.speed.bench_learn [--tables ho2018 highway-fast min2018-notebook]
        [--steps 2000] [--jobs 2] [--baseline a6f9247] [--json PATH]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from bench.harness import ROOT, baseline_checkout, write_report

TABLES = ("ho2018", "highway-fast", "min2018-notebook")
ARMS = ("lone-baseline", "lone", "members")
# Also known: "members-bf16", members with --precision bf16 (not in the default arms: bf16
# is not the default until the learning curves are compared), and "members-baseline", members
# at the baseline revision (one that has members: an A/B of a change to them).


@dataclass(frozen=True)
class LearnBenchConfig:
    tables: tuple[str, ...] = TABLES
    """which tables' runs to train: ho2018, highway-fast, min2018-notebook"""
    steps: int = 2_000
    """environment steps each run trains (min2018-notebook: a quarter, its camera is slow)"""
    learning_starts: int = 400
    """steps before the first update"""
    jobs: int = 2
    """processes at once"""
    baseline: str = "a6f9247"
    """the revision whose lone processes are the baseline (issue 66's starting point)"""
    arms: tuple[str, ...] = ARMS
    """lone-baseline (the baseline revision, a process a run), lone (this code, a process a
    run), members (this code, the runs of one network as members, split over --jobs),
    members-bf16 (the same with --precision bf16), members-baseline (members at the baseline
    revision, which must have them)"""
    sb3: bool = True
    """also Stable-Baselines3's DQN on highway-fast (its recipe), on overtake's scene and on
    highway-env's, two seeds each (with the highway-fast table)"""
    sb3_steps: int = 1_000
    """steps of each SB3 run"""
    startup: bool = True
    """also run each arm's processes for one step (their start-up: Python, PyTorch, the
    compiled simulator, the run's files), and give the steady state's figures, start-up
    subtracted (what a paper's runs of millions of steps see)"""
    json: Path | None = None


def run_args(table: str, steps: int, learning_starts: int) -> list[list[str]]:
    """The table's runs as ``overtake-train`` arguments (without --run-dir), flags the
    baseline revision knows too."""
    common = [
        "--total-steps",
        str(steps),
        "--learning-starts",
        str(learning_starts),
        "--torch-threads",
        "1",
        "--no-progress",
        "--sink",
        "off",
        "--checkpoint-every",
        str(steps),
    ]
    if table == "ho2018":
        runs = [["--network", "baseline", "--seed", str(seed)] for seed in (0, 1)]
        runs += [
            ["--network", "proposed", "--learning-rate", str(rate), "--seed", str(seed)]
            for rate in (0.0001, 0.00025, 0.0005, 0.00075)
            for seed in (0, 1)
        ]
        return [["--preset", "ho2018", "--num-envs", "4", *run, *common] for run in runs]
    if table == "highway-fast":
        return [
            ["--preset", "highway-fast", "--num-envs", "1", "--seed", str(seed), *common]
            for seed in range(10)
        ]
    if table == "min2018-notebook":
        notebook = ["--preset", "min2018", "--recipe", "notebook", "--num-envs", "4"]
        quarter = [*common]
        quarter[1] = str(max(steps // 4, min(200, steps)))
        quarter[3] = str(max(learning_starts // 4, min(100, learning_starts)))
        quarter[10] = quarter[1]
        return [[*notebook, "--seed", str(seed), *quarter] for seed in (0, 1)]
    raise SystemExit(f"unknown table {table!r}: expected some of {', '.join(TABLES)}")


def _network(args: list[str]) -> str:
    return args[args.index("--network") + 1] if "--network" in args else "-"


def member_commands(runs: list[list[str]], jobs: int) -> list[list[str]]:
    """The runs as member batches: the runs of one network together, at most
    ceil(runs / jobs) to a process (as overtake-experiment splits them)."""
    per_batch = max(1, -(-len(runs) // jobs))
    groups: dict[str, list[list[str]]] = {}
    for run in runs:
        groups.setdefault(_network(run), []).append(run)
    commands = []
    for group in groups.values():
        count = -(-len(group) // per_batch)
        size = -(-len(group) // count)
        for i in range(0, len(group), size):
            members = [json.dumps(run) for run in group[i : i + size]]
            commands.append(
                [sys.executable, "-m", "overtake.trainers.member_batch", "--members", *members]
            )
    return sorted(commands, key=len, reverse=True)


def run_processes(
    commands: list[list[str]], jobs: int, env: dict[str, str], log_dir: Path
) -> dict[str, float]:
    """Run ``commands``, ``jobs`` at a time; their CPU seconds (user + system, each from
    wait4) and the wall seconds from the first start to the last end."""
    pending = list(enumerate(commands))
    running: dict[int, tuple[int, Any]] = {}
    cpu = 0.0
    start = time.perf_counter()
    while pending or running:
        while pending and len(running) < jobs:
            index, command = pending.pop(0)
            log = open(log_dir / f"process-{index}.log", "w")  # noqa: SIM115
            process = subprocess.Popen(
                command, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=log_dir
            )
            running[process.pid] = (index, log)
        pid, status, usage = os.wait4(-1, 0)
        if pid not in running:
            continue
        index, log = running.pop(pid)
        log.close()
        cpu += usage.ru_utime + usage.ru_stime
        if os.waitstatus_to_exitcode(status) != 0:
            tail = (log_dir / f"process-{index}.log").read_text()[-2000:]
            raise SystemExit(f"process {index} failed: {' '.join(commands[index])}\n{tail}")
    return {"cpu_s": cpu, "wall_s": time.perf_counter() - start}


def train_commands(arm: str, runs: list[list[str]], jobs: int, out: Path) -> list[list[str]]:
    with_dirs = [[*run, "--run-dir", str(out / f"run-{i}")] for i, run in enumerate(runs)]
    if arm == "members-bf16":
        with_dirs = [[*run, "--precision", "bf16"] for run in with_dirs]
    if arm.startswith("members"):
        return member_commands(with_dirs, jobs)
    return [[sys.executable, "-m", "overtake.trainers.train", *run] for run in with_dirs]


def measure_arm(
    arm: str, table: str, config: LearnBenchConfig, baseline_path: Path | None
) -> dict[str, Any]:
    runs = run_args(table, config.steps, config.learning_starts)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    if arm in ("lone-baseline", "members-baseline"):
        assert baseline_path is not None
        env["PYTHONPATH"] = f"{baseline_path}{os.pathsep}{env.get('PYTHONPATH', '')}"
    with tempfile.TemporaryDirectory(prefix=f"bench-learn-{arm}-") as tmp:
        out = Path(tmp)
        commands = train_commands(arm, runs, config.jobs, out)
        timing = run_processes(commands, config.jobs, env, out)
    steps = sum(int(run[run.index("--total-steps") + 1]) for run in runs)
    arm_figures = figures(len(runs), len(commands), steps, timing)
    if config.startup:
        # The same processes for one step each: what they spend before training.
        with tempfile.TemporaryDirectory(prefix=f"bench-learn-{arm}-startup-") as tmp:
            short = run_args(table, 1, 1)
            startup = run_processes(
                train_commands(arm, short, config.jobs, Path(tmp)), config.jobs, env, Path(tmp)
            )
        short_steps = sum(int(run[run.index("--total-steps") + 1]) for run in short)
        steady_cpu = timing["cpu_s"] - startup["cpu_s"]
        arm_figures["startup_cpu_s"] = startup["cpu_s"]
        arm_figures["steady_steps_per_cpu_s"] = (steps - short_steps) / steady_cpu
    return arm_figures


def figures(runs: int, processes: int, steps: int, timing: dict[str, float]) -> dict[str, Any]:
    """An arm's figures: agent-steps per CPU-second and per wall-second."""
    return {
        "runs": runs,
        "processes": processes,
        "steps": steps,
        **timing,
        "steps_per_cpu_s": steps / timing["cpu_s"],
        "steps_per_wall_s": steps / timing["wall_s"],
    }


def _ratio(arms: dict[str, Any], arm: str, key: str) -> float | None:
    if key not in arms[arm] or key not in arms["lone-baseline"]:
        return None
    return arms[arm][key] / arms["lone-baseline"][key]


SB3_SCRIPT = """
import sys, gymnasium as gym, torch
torch.set_num_threads(1)
import overtake.client, highway_env  # registers both scenes
from stable_baselines3 import DQN
from stable_baselines3.common.logger import configure
env_id, seed, steps, starts = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
env = gym.make(env_id)
model = DQN("MlpPolicy", env, policy_kwargs=dict(net_arch=[256, 256]), learning_rate=5e-4,
            buffer_size=15000, learning_starts=starts, batch_size=32, gamma=0.8, train_freq=1,
            gradient_steps=1, target_update_interval=50, exploration_fraction=0.1, seed=seed,
            device="cpu")
model.set_logger(configure(None, []))
model.learn(steps)
"""


def measure_sb3(env_id: str, config: LearnBenchConfig) -> dict[str, Any]:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    commands = [
        [sys.executable, "-c", SB3_SCRIPT, env_id, str(seed), str(config.sb3_steps), "200"]
        for seed in (0, 1)
    ]
    with tempfile.TemporaryDirectory(prefix="bench-learn-sb3-") as tmp:
        timing = run_processes(commands, config.jobs, env, Path(tmp))
    return figures(len(commands), len(commands), config.sb3_steps * len(commands), timing)


def warm_baseline(baseline_path: Path) -> None:
    """Compile the baseline revision's simulator kernels into its fresh checkout, untimed: the
    working tree's are cached already, and a cold compile (about 46 CPU-seconds for every
    preset's kernels here) counted in the baseline's arms only would flatter this code."""
    env = {
        **os.environ,
        "PYTHONPATH": f"{baseline_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}",
    }
    subprocess.run([sys.executable, "-m", "overtake.server.sim.warm"], env=env, check=True)


def main(config: LearnBenchConfig) -> dict[str, Any]:
    results: dict[str, dict[str, Any]] = {}
    with baseline_checkout(config.baseline) as baseline_path:
        if any(arm.endswith("-baseline") for arm in config.arms):
            warm_baseline(baseline_path)
        for table in config.tables:
            results[table] = {}
            for arm in config.arms:
                figures = measure_arm(arm, table, config, baseline_path)
                results[table][arm] = figures
                steady = (
                    f"; start-up {figures['startup_cpu_s']:.1f} CPU-s, steady state "
                    f"{figures['steady_steps_per_cpu_s']:.1f} per CPU-second"
                    if "startup_cpu_s" in figures
                    else ""
                )
                print(
                    f"{table:17s} {arm:14s} {figures['runs']:2d} runs in "
                    f"{figures['processes']:2d} processes: {figures['steps_per_cpu_s']:7.1f} "
                    f"steps per CPU-second, {figures['steps_per_wall_s']:7.1f} per wall-second"
                    f"{steady}",
                    flush=True,
                )
            if table == "highway-fast" and config.sb3:
                for name, env_id in (
                    ("sb3-overtake", "overtake/highway-fast-v0"),
                    ("sb3-highway-env", "highway-fast-v0"),
                ):
                    figures = measure_sb3(env_id, config)
                    results[table][name] = figures
                    print(
                        f"{table:17s} {name:14s} {figures['runs']:2d} runs: "
                        f"{figures['steps_per_cpu_s']:7.1f} steps per CPU-second, "
                        f"{figures['steps_per_wall_s']:7.1f} per wall-second",
                        flush=True,
                    )
    ratios = {
        table: {
            f"{arm}/lone-baseline": {
                "cpu": _ratio(arms, arm, "steps_per_cpu_s"),
                "wall": _ratio(arms, arm, "steps_per_wall_s"),
                "steady_cpu": _ratio(arms, arm, "steady_steps_per_cpu_s"),
            }
            for arm in arms
            if arm != "lone-baseline" and "lone-baseline" in arms
        }
        for table, arms in results.items()
    }
    for table, table_ratios in ratios.items():
        for name, ratio in table_ratios.items():
            steady = (
                f", {ratio['steady_cpu']:.2f}x in the steady state"
                if ratio["steady_cpu"] is not None
                else ""
            )
            print(
                f"{table:17s} {name:28s} {ratio['cpu']:.2f}x per CPU-second, "
                f"{ratio['wall']:.2f}x per wall-second{steady}"
            )
    report = {
        "config": {**config.__dict__, "json": None if config.json is None else str(config.json)},
        "root": str(ROOT),
        "results": results,
        "ratios": ratios,
    }
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    main(tyro.cli(LearnBenchConfig, description=__doc__))
