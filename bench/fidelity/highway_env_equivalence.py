"""highway-env 1.12.1 and overtake's preset of the same scene, side by side (issue 57).

1. **Fixed drivers**: always IDLE, always FASTER and uniform random drive ``--episodes``
   episodes on each simulator through the same Gymnasium loop, episode ``i`` reset with seed
   ``--seed + i`` on both (the same numbers, not the same random streams: the two simulators
   draw their roads differently) and the random driver's actions drawn from seed ``i`` on both.
   And **idm**: the scene's own IDM + MOBIL car as the controlled car (on highway-env its car
   swapped for ``IDMVehicle.create_from(car)`` after each reset, its actions then unread; on
   overtake the setting ``highway_scene.ego_driver=idm``, what ``overtake-eval --policy idm``
   drives). Reported per simulator and driver: the mean episode length (decisions), the share
   of episodes that ended in a crash, the mean return and the controlled car's mean speed,
   each with its standard deviation.
2. **Transfer** (``--transfer``): Stable-Baselines3's documented highway-fast DQN (its
   hyper-parameters, ``--train-steps`` steps; 20,000 as documented) trained once on highway-env
   and once on overtake's id, each evaluated greedily on both simulators over the same seeds.

It writes table.md and table.json (with the command, the commit and the packages' versions)
into ``--out``; ``bench/results/highway-env-equivalence`` keeps them (``--drivers`` picks
rows; a quick look: ``--drivers idm --episodes 2 --out /tmp/equivalence``)::

    .venv/bin/python -m bench.fidelity.highway_env_equivalence --transfer \\
        --out bench/results/highway-env-equivalence

Needs the bench extra (highway-env) and, for the transfer, stable-baselines3 (dev extra).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

# What a driver does: given the episode's seed and the step, an action in highway-env's order.
Driver = Callable[[np.random.Generator], int]
DRIVERS: dict[str, Callable[[np.random.Generator], int]] = {
    "idle": lambda rng: 1,
    "faster": lambda rng: 3,
    "random": lambda rng: int(rng.integers(0, 5)),
    # The car drives itself (see idm_ego): the action sent is highway-env's IDLE, unread.
    "idm": lambda rng: 1,
}
# The driver whose car is the scene's IDM + MOBIL car rather than its meta-actions' car.
IDM_DRIVER = "idm"
SIMULATORS = {"highway-env": "{scene}", "overtake": "overtake/{scene}"}
SB3_RECIPE: dict[str, Any] = {
    "policy_kwargs": {"net_arch": [256, 256]},
    "learning_rate": 5e-4,
    "buffer_size": 15_000,
    "learning_starts": 200,
    "batch_size": 32,
    "gamma": 0.8,
    "train_freq": 1,
    "gradient_steps": 1,
    "target_update_interval": 50,
}


@dataclass(frozen=True)
class EquivalenceConfig:
    """highway-env and overtake's preset of its scene, side by side."""

    scene: str = "highway-fast-v0"
    """highway-env's id (highway-fast-v0 or highway-v0); overtake's is overtake/<scene>"""
    episodes: int = 60
    seed: int = 10_000
    """episode i is reset with seed + i on both simulators"""
    drivers: tuple[str, ...] = tuple(DRIVERS)
    """the fixed drivers' rows (idle, faster, random, idm)"""
    transfer: bool = False
    """also train SB3's documented DQN on each simulator and evaluate it on both"""
    train_steps: int = 20_000
    out: Path = Path("runs/highway-env-equivalence")


def make(simulator: str, scene: str, idm: bool = False) -> gym.Env:
    """``scene`` on ``simulator``; ``idm``: overtake's with its controlled car driven by the
    scene's IDM + MOBIL (highway-env's is swapped after each reset: :func:`idm_ego`)."""
    if simulator == "highway-env":
        import highway_env  # noqa: F401  (registers highway-env's ids)

        return gym.make(SIMULATORS[simulator].format(scene=scene))
    import overtake.client  # noqa: F401  (registers overtake's)

    overrides = {"highway_scene.ego_driver": "idm"} if idm else None
    return gym.make(SIMULATORS[simulator].format(scene=scene), overrides=overrides)


def idm_ego(env: gym.Env) -> None:
    """highway-env's own IDM ego: the controlled car replaced by ``IDMVehicle.create_from``
    of it (its position, speed, target lane and speed; the class's IDM exponent; its timer
    from its position), in the road's cars and as the controlled car, which the action, the
    observation, the reward and the episode's end read. Its ``act`` ignores the action."""
    from highway_env.vehicle.behavior import IDMVehicle

    scene: Any = env.unwrapped
    car = scene.vehicle
    idm = IDMVehicle.create_from(car)
    scene.road.vehicles[scene.road.vehicles.index(car)] = idm
    scene.controlled_vehicles[0] = idm


def drive(
    env: gym.Env,
    seeds: list[int],
    act: Callable[[np.ndarray, np.random.Generator], int],
    after_reset: Callable[[gym.Env], None] | None = None,
):
    """Per episode: decisions, crashed, return, the car's mean speed (m/s)."""
    rows = []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        if after_reset is not None:
            after_reset(env)
        rng = np.random.default_rng(seed)
        length, total, speeds, crashed = 0, 0.0, [], False
        while True:
            obs, reward, terminated, truncated, info = env.step(act(obs, rng))
            length, total = length + 1, total + float(reward)
            speeds.append(float(info["speed"]))
            if terminated or truncated:
                crashed = bool(info["crashed"])
                break
        rows.append((length, crashed, total, float(np.mean(speeds))))
    return rows


def summary(rows) -> dict[str, Any]:
    length, crashed, total, speed = (np.array(column, dtype=float) for column in zip(*rows))
    return {
        "episodes": len(rows),
        "length_mean": length.mean(),
        "length_std": length.std(),
        "crash_share": crashed.mean(),
        "return_mean": total.mean(),
        "return_std": total.std(),
        "speed_mps_mean": speed.mean(),
        "speed_mps_std": speed.std(),
    }


def fixed_drivers(config: EquivalenceConfig, seeds: list[int]) -> dict[str, dict[str, Any]]:
    unknown = [name for name in config.drivers if name not in DRIVERS]
    if unknown:
        raise SystemExit(f"--drivers: expected names among {', '.join(DRIVERS)}, got {unknown}")
    results: dict[str, dict[str, Any]] = {}
    for simulator in SIMULATORS:
        env = make(simulator, config.scene)
        for name in config.drivers:
            idm = name == IDM_DRIVER
            driven_env = make(simulator, config.scene, idm=True) if idm else env
            swap = idm_ego if idm and simulator == "highway-env" else None
            start = time.perf_counter()
            driver = DRIVERS[name]
            results.setdefault(name, {})[simulator] = {
                **summary(drive(driven_env, seeds, lambda _obs, rng, d=driver: d(rng), swap)),
                "seconds": time.perf_counter() - start,
            }
            if driven_env is not env:
                driven_env.close()
            print(f"{simulator:12s} {name:7s} {results[name][simulator]}", flush=True)
        env.close()
    return results


def transfer(config: EquivalenceConfig, seeds: list[int]) -> dict[str, dict[str, Any]]:
    from stable_baselines3 import DQN

    results: dict[str, dict[str, Any]] = {}
    for trained_on in SIMULATORS:
        env = make(trained_on, config.scene)
        start = time.perf_counter()
        model = DQN("MlpPolicy", env, seed=0, verbose=0, device="cpu", **SB3_RECIPE)
        model.learn(config.train_steps)
        trained_s = time.perf_counter() - start
        env.close()

        def greedy(obs: np.ndarray, _rng: np.random.Generator, model: DQN = model) -> int:
            action, _ = model.predict(obs, deterministic=True)
            return int(action)

        for evaluated_on in SIMULATORS:
            env = make(evaluated_on, config.scene)
            results.setdefault(trained_on, {})[evaluated_on] = {
                **summary(drive(env, seeds, greedy)),
                "train_seconds": trained_s,
            }
            env.close()
            print(f"trained on {trained_on}, on {evaluated_on}: "
                  f"{results[trained_on][evaluated_on]}", flush=True)  # fmt: skip
    return results


def _cell(entry: dict[str, Any]) -> str:
    return (
        f"{entry['length_mean']:.2f} ± {entry['length_std']:.2f} | {entry['crash_share']:.2f} | "
        f"{entry['return_mean']:.2f} ± {entry['return_std']:.2f} | "
        f"{entry['speed_mps_mean']:.2f} ± {entry['speed_mps_std']:.2f}"
    )


def within_bar(drivers: dict[str, dict[str, Any]]) -> dict[str, bool]:
    """Issue 57's bar per driver: the preset's mean length within 20% (or 2 decisions) of
    highway-env's, its crash share within 0.15, its mean return within 25%."""
    verdict = {}
    for name, pair in drivers.items():
        ours, theirs = pair["overtake"], pair["highway-env"]
        length = abs(ours["length_mean"] - theirs["length_mean"])
        verdict[name] = bool(
            (length <= 0.2 * theirs["length_mean"] or length <= 2.0)
            and abs(ours["crash_share"] - theirs["crash_share"]) <= 0.15
            and abs(ours["return_mean"] - theirs["return_mean"])
            <= 0.25 * abs(theirs["return_mean"])
        )
    return verdict


def write(config: EquivalenceConfig, record: dict[str, Any]) -> None:
    config.out.mkdir(parents=True, exist_ok=True)
    (config.out / "table.json").write_text(json.dumps(record, indent=1, default=str))
    head = "| simulator | decisions | crash share | return | speed m/s |\n|---|---|---|---|---|\n"
    lines = [
        f"# highway-env {record['versions'].get('highway-env')} and overtake's preset of "
        f"{config.scene}, side by side",
        "",
        f"Command: `{record['command']}`; commit {record['commit']}; {config.episodes} "
        f"episodes per driver and simulator, seeds {config.seed}-"
        f"{config.seed + config.episodes - 1} "
        "(the same numbers on both, not the same random streams). Mean ± standard deviation. "
        "The bar a fixed driver is held to: its mean episode length within 20% (or 2 "
        "decisions) of highway-env's, its crash share within 0.15, its mean return within 25%.",
        "",
        "## Fixed drivers",
        "",
    ]
    for name, pair in record["drivers"].items():
        verdict = "within" if record["bar"][name] else "NOT within"
        lines += [f"### {name} ({verdict} the bar)", "", head.rstrip("\n")]
        lines += [f"| {sim} | {_cell(entry)} |" for sim, entry in pair.items()]
        lines.append("")
    if record.get("transfer"):
        lines += [
            "## Transfer",
            "",
            f"Stable-Baselines3's documented highway-fast DQN, {config.train_steps:,} steps on "
            "each simulator (seed 0), evaluated greedily on both over the same seeds.",
            "",
            "| trained on | evaluated on | decisions | crash share | return | speed m/s |",
            "|---|---|---|---|---|---|",
        ]
        for trained_on, row in record["transfer"].items():
            lines += [f"| {trained_on} | {sim} | {_cell(entry)} |" for sim, entry in row.items()]
        lines.append("")
    (config.out / "table.md").write_text("\n".join(lines))


def main(config: EquivalenceConfig) -> dict[str, Any]:
    from overtake.client.provenance import git_commit, package_versions

    seeds = [config.seed + i for i in range(config.episodes)]
    drivers = fixed_drivers(config, seeds)
    record: dict[str, Any] = {
        "config": {k: str(v) for k, v in dataclasses.asdict(config).items()},
        "command": " ".join(["python -m bench.fidelity.highway_env_equivalence", *sys.argv[1:]]),
        "commit": git_commit(),
        "versions": {
            **package_versions(),
            **{name: metadata.version(name) for name in ("highway-env", "stable-baselines3")},
        },
        "drivers": drivers,
        "bar": within_bar(drivers),
    }
    if config.transfer:
        record["transfer"] = transfer(config, seeds)
    write(config, record)
    return record


if __name__ == "__main__":
    import tyro

    main(tyro.cli(EquivalenceConfig))
