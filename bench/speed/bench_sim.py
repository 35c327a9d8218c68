"""Benchmark: how much highway driving overtake simulates per second, against highway-env.

What is measured, in one run so that every ratio is taken under the same machine conditions:

* overtake in-process, every preset with its default sensors (min2018: 5 lanes, a 360-ray
  LIDAR and an 80x80 grey camera; ho2018: 7 lanes, its occupancy grid; fayjie2018: 3 lanes,
  camera and LIDAR map), as a trainer would use it: one arena through
  ``gymnasium.make("overtake/Highway-v0")`` and batches of 8 and 64 arenas through
  ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")``;
* the peer, highway-env's ``highway-fast-v0`` on a comparable scene (5 lanes, 40 vehicles,
  DiscreteMetaAction, a LIDAR and an 84x84 grayscale image per decision), through
  :func:`bench.peers.highway_env_peer.measure_highway_env`: the peer every figure in
  ``bench/RESULTS.md`` (and its journal) since the first run is a ratio to;
* and highway-env on each preset's own scene (its lanes, traffic cars, physics and decision
  rates, and the closest observation: :func:`bench.peers.highway_env_peer.matched_scene`),
  "x own scene": ho2018 simulates 50 physics frames a second, 10 times highway-fast-v0's 5,
  and min2018 and fayjie2018 drive 10 traffic cars, not 40.

Every measurement drives uniformly random actions from a seeded generator, runs untimed warm-up
decisions, then times a fixed number of decisions. Episode ends are handled inside the timed
loop: the single environment is reset on terminated or truncated, the vector environment resets
an arena by itself on the step after its episode ended. Such an autoreset step advances no
simulated time, so it is timed but not counted as a decision.

For each measurement it reports decisions (arena-steps) per wall second, and simulated seconds
per wall second and per CPU second, summed over arenas. Simulated seconds are decisions times
the decision period that each environment reports (overtake: ``env.unwrapped.decision_period_s``;
highway-env: ``1 / policy_frequency``). CPU seconds are ``time.process_time()`` of the whole
process, so they count every thread; for that reason numpy's BLAS/OpenMP pools are pinned to one
thread by default (before numpy is imported), which keeps idle spinning pool threads from
inflating the CPU time.

The figure that matters is simulated seconds per CPU second: it says how much driving one core
buys, whatever the number of cores. The bars (issue 18) are on its ratio to highway-env's,
for every preset: one arena at least 30x, a batch of 64 arenas at least 250x (issue 3's were
20x and 100x, for min2018). PASS/FAIL against them is printed
as information; the benchmark exits 0 whether they pass or not, and non-zero only on an error.
"""

from __future__ import annotations

import dataclasses
import os
import platform
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

import tyro

from bench.harness import report_head, write_report
from bench.rates import Rates

if TYPE_CHECKING:
    from overtake.server.sim import SimConfig

ENV_ID = "overtake/Highway-v0"
PRESET = "min2018"  # bench_sim_ab's and bench_remote's
PRESETS = ("min2018", "ho2018", "fayjie2018")
BATCH_SIZES = (8, 64)
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# The bars: arenas -> least ratio of overtake's simulated seconds per CPU second to
# highway-env's, for every preset.
BARS: dict[int, float] = {1: 30.0, 64: 250.0}
QUICK_DIVISOR = 10
# overtake's code folders, whose uncommitted changes the report flags.
SOURCE_FOLDERS = ("protocol", "viz", "server", "client")


@dataclass(frozen=True)
class BenchConfig:
    """Decision counts, seed and threading of one benchmark run."""

    single_decisions: int = 4000
    """Timed decisions of overtake's single environment."""
    batch_arena_decisions: int = 32000
    """Timed arena-decisions of each overtake batch (the vector env takes this // arenas steps)."""
    highway_env_decisions: int = 120
    """Timed decisions of highway-env."""
    single_warmup: int = 100
    """Untimed decisions before timing the single environment."""
    batch_warmup_steps: int = 20
    """Untimed vector steps before timing each batch."""
    highway_env_warmup: int = 10
    """Untimed decisions before timing highway-env."""
    presets: tuple[str, ...] = PRESETS
    """The presets measured, each with its default sensors and traffic."""
    quick: bool = False
    """Divide the three timed counts by 10: a smoke run, with noisier figures."""
    seed: int = 0
    """Seed of the environments and of the random actions."""
    blas_threads: int | None = 1
    """Threads of numpy's BLAS/OpenMP pools (set in OMP_NUM_THREADS, OPENBLAS_NUM_THREADS and
    MKL_NUM_THREADS before numpy is imported); None leaves the environment as it is."""
    peers: bool = True
    """Also measure highway-env's own scene against EnvPool's C++ port and highway-env
    (:mod:`bench.speed.bench_highway_peers`: 1, 64 and 256 environments, per CPU and wall second;
    EnvPool needs the bench extra)."""
    peer_steps: int = 20_000
    """Timed agent-steps of each peer measurement (divided in quick mode)."""
    json: Path | None = None
    """Also write the results as JSON to this path."""

    def __post_init__(self) -> None:
        for name in ("single_decisions", "batch_arena_decisions", "highway_env_decisions"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        for name in ("single_warmup", "batch_warmup_steps", "highway_env_warmup"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be at least 0, got {getattr(self, name)}")
        if self.blas_threads is not None and self.blas_threads < 1:
            raise ValueError(f"blas_threads must be at least 1 or None, got {self.blas_threads}")

    def timed(self, count: int) -> int:
        """A timed count, divided in quick mode."""
        return max(1, count // QUICK_DIVISOR) if self.quick else count


@dataclass(frozen=True)
class Measurement(Rates):
    """One timed run of one simulator on some arenas."""

    simulator: str
    """overtake's preset, or the peer's name"""
    arenas: int
    decisions: int
    """Arena-decisions that advanced the simulation (autoreset steps excluded)."""
    episodes_ended: int | None
    """Episodes that ended (terminated or truncated) in the timed loop; None where not counted."""
    simulated_seconds: float
    wall_seconds: float
    cpu_seconds: float

    @property
    def decisions_per_wall_second(self) -> float:
        return self.decisions / self.wall_seconds

    def as_dict(self) -> dict[str, Any]:
        return {
            **dataclasses.asdict(self),
            "decisions_per_wall_second": self.decisions_per_wall_second,
            "sim_seconds_per_wall_second": self.sim_seconds_per_wall_second,
            "sim_seconds_per_cpu_second": self.sim_seconds_per_cpu_second,
        }


class _Timer:
    """Wall and process CPU time of a ``with`` block."""

    def __enter__(self) -> _Timer:
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall_seconds = time.perf_counter() - self._wall
        self.cpu_seconds = time.process_time() - self._cpu


def pin_threads(threads: int | None) -> str:
    """Set the thread-count variables (before numpy is imported); describe the setting."""
    if threads is None:
        current = ", ".join(f"{name}={os.environ.get(name, 'unset')}" for name in THREAD_VARIABLES)
        return f"not pinned by the benchmark ({current})"
    if "numpy" in sys.modules:
        raise RuntimeError(
            "numpy was imported before the benchmark could pin its thread pools; "
            "run the benchmark in a fresh process or pass blas_threads=None"
        )
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    return f"pinned to {threads} ({', '.join(THREAD_VARIABLES)}={threads})"


def _overtake_summary(env_config: SimConfig) -> dict[str, Any]:
    """The scene overtake actually simulates, read from its configuration."""
    camera = env_config.camera
    return {
        "preset": env_config.preset,
        "lanes": env_config.road.lane_count,
        "traffic_cars": env_config.traffic.resolved_vehicle_count,
        "density": env_config.traffic.density,
        "lidar_rays": env_config.lidar.ray_count if env_config.lidar.enabled else 0,
        "camera": (
            f"{camera.width_px}x{camera.height_px} {'rgb' if camera.rgb else 'grey'}"
            if camera.enabled
            else "off"
        ),
        "decision_period_s": env_config.episode.decision_period_s,
        "max_decisions": env_config.episode.max_decisions,
    }


def measure_overtake_single(
    decisions: int, warmup: int, seed: int, preset: str = PRESET
) -> tuple[Measurement, dict[str, Any]]:
    """Time ``decisions`` random decisions of one arena made by ``gymnasium.make``."""
    # Imported here, after main() has pinned numpy's thread pools.
    import gymnasium
    import numpy as np

    import overtake.client  # noqa: F401  (registers the environment)

    env = gymnasium.make(ENV_ID, preset=preset)
    try:
        period = env.unwrapped.decision_period_s
        action_count = int(env.action_space.n)
        rng = np.random.default_rng(seed)
        env.reset(seed=seed)

        def drive(count: int) -> int:
            ended = 0
            for _ in range(count):
                _, _, terminated, truncated, _ = env.step(int(rng.integers(action_count)))
                if terminated or truncated:
                    env.reset()
                    ended += 1
            return ended

        drive(warmup)
        with _Timer() as timer:
            ended = drive(decisions)
        summary = _overtake_summary(env.unwrapped.config)
    finally:
        env.close()
    return Measurement(
        preset, 1, decisions, ended, decisions * period, timer.wall_seconds, timer.cpu_seconds
    ), summary


def measure_overtake_batch(
    arenas: int, arena_decisions: int, warmup_steps: int, seed: int, preset: str = PRESET
) -> Measurement:
    """Time about ``arena_decisions`` random arena-decisions of ``arenas`` arenas in one vector
    env made by ``gymnasium.make_vec``."""
    import gymnasium
    import numpy as np

    import overtake.client  # noqa: F401

    envs = gymnasium.make_vec(
        ENV_ID, num_envs=arenas, vectorization_mode="vector_entry_point", preset=preset
    )
    try:
        period = envs.unwrapped.decision_period_s
        action_count = int(envs.single_action_space.n)
        rng = np.random.default_rng(seed)
        envs.reset(seed=seed)
        # Arenas whose next step is an autoreset (their episode ended on the last step).
        autoreset = np.zeros(arenas, dtype=bool)

        def drive(steps: int) -> tuple[int, int]:
            nonlocal autoreset
            advanced = ended = 0
            for _ in range(steps):
                _, _, terminated, truncated, _ = envs.step(rng.integers(action_count, size=arenas))
                advanced += arenas - int(np.count_nonzero(autoreset))
                autoreset = terminated | truncated
                ended += int(np.count_nonzero(autoreset))
            return advanced, ended

        drive(warmup_steps)
        with _Timer() as timer:
            decisions, ended = drive(max(1, arena_decisions // arenas))
    finally:
        envs.close()
    return Measurement(
        preset,
        arenas,
        decisions,
        ended,
        decisions * period,
        timer.wall_seconds,
        timer.cpu_seconds,
    )


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as cpuinfo:
            for line in cpuinfo:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _source_revision() -> str:
    """The git commit of the overtake this process imported (another revision's, when one is
    put first on PYTHONPATH), marked when its code has uncommitted changes."""
    import overtake.server

    root = Path(overtake.server.__file__).resolve().parents[1]

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(root), *args], capture_output=True, text=True, check=True
        ).stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        changed = git("status", "--porcelain", "--", *SOURCE_FOLDERS)
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"
    return f"{commit} + uncommitted changes" if changed else commit


def machine_line(machine: dict[str, Any]) -> str:
    """The report's first line about ``machine`` (:func:`machine_description`)."""
    return (
        f"machine: {machine['cpu_count']} CPUs ({machine['cpu_model']}), "
        f"{machine['platform']}, Python {machine['python']}, numpy {machine['numpy']}, "
        f"gymnasium {machine['gymnasium']}"
    )


def machine_description() -> dict[str, Any]:
    import gymnasium
    import numpy as np

    return {
        "cpu_count": os.cpu_count(),
        "cpu_model": _cpu_model(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "gymnasium": gymnasium.__version__,
        "overtake": metadata.version("overtake"),
        "overtake_source": _source_revision(),
    }


def _preset_config(preset: Any) -> SimConfig:
    """A preset's SimConfig (PRESETS holds configurations or their factories)."""
    return preset() if callable(preset) else preset


def _peer_row(name: str, result: Any) -> Measurement:
    return Measurement(
        name,
        1,
        result.decisions,
        None,
        result.simulated_seconds,
        result.wall_seconds,
        result.cpu_seconds,
    )


def _format_table(
    rows: list[Measurement],
    ratios: Mapping[tuple[str, int], float],
    matched: Mapping[tuple[str, int], float],
) -> str:
    header = (
        "overtake preset / peer",
        "arenas",
        "decisions",
        "episodes",
        "wall s",
        "CPU s",
        "decisions/s",
        "sim s/wall s",
        "sim s/CPU s",
        "x highway-env",
        "x own scene",
    )
    lines = []
    for row in rows:
        ratio = ratios.get((row.simulator, row.arenas))
        own = matched.get((row.simulator, row.arenas))
        lines.append(
            (
                row.simulator,
                str(row.arenas),
                str(row.decisions),
                "-" if row.episodes_ended is None else str(row.episodes_ended),
                f"{row.wall_seconds:.2f}",
                f"{row.cpu_seconds:.2f}",
                f"{row.decisions_per_wall_second:,.1f}",
                f"{row.sim_seconds_per_wall_second:,.1f}",
                f"{row.sim_seconds_per_cpu_second:,.1f}",
                "-" if ratio is None else f"{ratio:,.1f}x",
                "-" if own is None else f"{own:,.1f}x",
            )
        )
    widths = [max(len(cells[i]) for cells in (header, *lines)) for i in range(len(header))]

    def join(cells: tuple[str, ...]) -> str:
        return "  ".join(
            [
                cells[0].ljust(widths[0]),
                *(cell.rjust(width) for cell, width in zip(cells[1:], widths[1:])),
            ]
        )

    return "\n".join([join(header), "  ".join("-" * width for width in widths), *map(join, lines)])


def main(config: BenchConfig) -> dict[str, Any]:
    """Run every measurement, print the report and return it as a JSON-able dict."""
    threads = pin_threads(config.blas_threads)
    from bench.peers.highway_env_peer import ENV_ID as PEER_ENV_ID
    from bench.peers.highway_env_peer import matched_scene, measure_highway_env

    machine = machine_description()
    print("overtake simulation benchmark")
    print(machine_line(machine))
    print(f"numpy BLAS/OpenMP threads: {threads}")
    print("CPU time: time.process_time() of the whole process (all threads)")
    if config.quick:
        print(f"quick mode: timed counts divided by {QUICK_DIVISOR}; figures are noisier")

    from overtake.server.sim import PRESETS as SIM_PRESETS

    rows, scenes, matched = [], {}, {}
    for preset in config.presets:
        single, scenes[preset] = measure_overtake_single(
            config.timed(config.single_decisions), config.single_warmup, config.seed, preset
        )
        source = f"overtake {machine['overtake']} (source {machine['overtake_source']})"
        print(f"{source} {ENV_ID}: {scenes[preset]}")
        rows.append(single)
        for arenas in BATCH_SIZES:
            rows.append(
                measure_overtake_batch(
                    arenas,
                    config.timed(config.batch_arena_decisions),
                    config.batch_warmup_steps,
                    config.seed,
                    preset,
                )
            )
        # highway-env on this preset's own scene (lanes, cars, rates, closest observation).
        scene = matched_scene(_preset_config(SIM_PRESETS[preset]))
        result = measure_highway_env(
            config.timed(config.highway_env_decisions),
            config.seed,
            config.highway_env_warmup,
            scene,
        )
        print(f"highway-env {result.version} {PEER_ENV_ID} on {preset}'s scene: {scene}")
        matched[preset] = _peer_row(f"highway-env ({preset}'s scene)", result)
        rows.append(matched[preset])
    peer = measure_highway_env(
        config.timed(config.highway_env_decisions), config.seed, config.highway_env_warmup
    )
    print(f"highway-env {peer.version} {PEER_ENV_ID}: {dict(peer.config)}")
    peer_row = _peer_row("highway-env", peer)
    rows.append(peer_row)

    overtake_rows = [row for row in rows if row.simulator in config.presets]
    ratios = {
        (row.simulator, row.arenas): row.sim_seconds_per_cpu_second
        / peer_row.sim_seconds_per_cpu_second
        for row in overtake_rows
    }
    matched_ratios = {
        (row.simulator, row.arenas): row.sim_seconds_per_cpu_second
        / matched[row.simulator].sim_seconds_per_cpu_second
        for row in overtake_rows
    }
    print()
    print(
        "Throughput, summed over arenas (x highway-env: ratio of simulated seconds per CPU s to "
        "highway-fast-v0's; x own scene: to highway-env's on the preset's scene)"
    )
    print(_format_table(rows, ratios, matched_ratios))
    print()
    bars = []
    for preset in config.presets:
        for arenas, bar in BARS.items():
            ratio, own = ratios[(preset, arenas)], matched_ratios[(preset, arenas)]
            passed = ratio >= bar
            bars.append(
                {
                    "preset": preset,
                    "arenas": arenas,
                    "bar": bar,
                    "ratio": ratio,
                    "passed": passed,
                    "ratio_own_scene": own,
                    "passed_own_scene": own >= bar,
                }
            )
            print(
                f"bar: {preset}, {arenas} arena{'s' if arenas > 1 else ''}, simulated s per CPU "
                f"s >= {bar:g}x highway-env: {ratio:.1f}x -> {'PASS' if passed else 'FAIL'} "
                f"(on its own scene {own:.1f}x -> {'PASS' if own >= bar else 'FAIL'})"
            )

    peers = None
    if config.peers:
        from bench.speed.bench_highway_peers import PeersConfig
        from bench.speed.bench_highway_peers import main as peers_main

        print()
        print(
            "highway-env's highway-fast-v0 scene: overtake/highway-fast-v0 against EnvPool's "
            "HighwayFast-v0 and highway-env, agent-steps per second (the better of two rounds)"
        )
        peers = peers_main(PeersConfig(steps=config.timed(config.peer_steps)))

    report = {
        **report_head(config, machine, threads),
        "overtake": {"env_id": ENV_ID, "scenes": scenes},
        "highway_env_own_scenes": {preset: row.as_dict() for preset, row in matched.items()},
        "ratios_own_scene": {f"{p} {a}": v for (p, a), v in matched_ratios.items()},
        "highway_env": {
            "env_id": PEER_ENV_ID,
            "version": peer.version,
            "config": dict(peer.config),
        },
        "measurements": [row.as_dict() for row in rows],
        "ratios_sim_seconds_per_cpu_second": {f"{p} {a}": v for (p, a), v in ratios.items()},
        "bars": bars,
        "highway_fast_peers": peers,
    }
    write_report(config.json, report)
    return report


def cli() -> None:
    main(tyro.cli(BenchConfig, description=__doc__))


if __name__ == "__main__":
    cli()
