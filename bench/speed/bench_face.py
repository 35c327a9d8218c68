"""What the in-process face costs a step, apart from the simulator's own work (issue 58).

Each measurement drives the same random decisions twice, alternately, in one process:

- **face**: through the Gymnasium face, ``gymnasium.make("overtake/Highway-v0", preset=...)``
  at one arena, ``gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`` at many:
  the action check, the local engine's round (:class:`~overtake.server.engine.rounds.Rounds`: the
  actions into the round, the autoreset, the round's rows), and the observation and info the
  face hands out, with Gymnasium's own wrappers;
- **bare**: the simulator alone doing the same round's work: :func:`autoreset_round` with the
  episodes that ended, then the observations, the action mask and the metrics table a round's
  rows carry (what any face needs, however thin).

The face's cost is the difference, in CPU µs per step (per round of every arena) and per
agent-step. Each side is measured ``--rounds`` times, alternately; the better of each is kept.

    .venv/bin/python -m bench.speed.bench_face [--arenas 1 64] [--presets highway-fast min2018]
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import tyro

ENV_ID = "overtake/Highway-v0"


@dataclass(frozen=True)
class FaceBenchConfig:
    arenas: tuple[int, ...] = (1, 64)
    """arena counts: one through ``gymnasium.make``, more through ``make_vec``"""
    presets: tuple[str, ...] = ("highway-fast", "min2018")
    agent_steps: int = 20_000
    """agent-steps timed per measurement (at least 200 steps of the batch)"""
    rounds: int = 3
    seed: int = 0


def _face_stepper(preset: str, arenas: int, seed: int) -> Any:
    import gymnasium
    import numpy as np

    import overtake.client  # noqa: F401  (registers the environment)

    rng = np.random.default_rng(seed)
    if arenas == 1:
        env = gymnasium.make(ENV_ID, preset=preset)
        env.reset(seed=seed)
        count = int(env.action_space.n)

        def single(steps: int) -> None:
            for _ in range(steps):
                _, _, terminated, truncated, _ = env.step(int(rng.integers(count)))
                if terminated or truncated:
                    env.reset()

        return single
    envs = gymnasium.make_vec(
        ENV_ID, num_envs=arenas, vectorization_mode="vector_entry_point", preset=preset
    )
    envs.reset(seed=seed)
    count = int(envs.single_action_space.n)

    def vector(steps: int) -> None:
        for _ in range(steps):
            envs.step(rng.integers(count, size=arenas))

    return vector


def _bare_stepper(preset: str, arenas: int, seed: int) -> Any:
    import numpy as np

    from overtake.envs.registry import arena_seeds
    from overtake.protocol.vocabulary import ACTION_COUNT
    from overtake.server.sim import HighwaySim, autoreset_round, make_config

    sim = HighwaySim(make_config(preset), num_arenas=arenas)
    sim.reset(seeds=arena_seeds(seed, arenas))
    rng = np.random.default_rng(seed)
    count = ACTION_COUNT  # the face's action space
    ended = np.zeros((arenas, sim.agents), dtype=bool)

    def bare(steps: int) -> None:
        nonlocal ended
        for _ in range(steps):
            actions = rng.integers(count, size=(arenas, sim.agents))
            result = autoreset_round(sim, actions, ended)
            ended = result.ended
            sim.observe()
            sim.action_mask()
            sim.metrics_table()

    return bare


def _cpu_us_per_step(drive: Any, steps: int) -> float:
    start = time.process_time()
    drive(steps)
    return (time.process_time() - start) / steps * 1e6


def measure(preset: str, arenas: int, config: FaceBenchConfig) -> dict[str, float]:
    """The better of ``rounds`` alternate measurements of each side, µs of CPU per step."""
    steps = max(200, config.agent_steps // arenas)
    face = _face_stepper(preset, arenas, config.seed)
    bare = _bare_stepper(preset, arenas, config.seed)
    face(50)  # compiled, warmed
    bare(50)
    face_us, bare_us = [], []
    for _ in range(config.rounds):
        face_us.append(_cpu_us_per_step(face, steps))
        bare_us.append(_cpu_us_per_step(bare, steps))
    best_face, best_bare = min(face_us), min(bare_us)
    return {
        "face_us_per_step": best_face,
        "bare_us_per_step": best_bare,
        "face_cost_us_per_step": best_face - best_bare,
        "face_cost_us_per_agent_step": (best_face - best_bare) / arenas,
        "face_share": (best_face - best_bare) / best_face,
    }


def main(config: FaceBenchConfig) -> dict[str, dict[int, dict[str, float]]]:
    report: dict[str, dict[int, dict[str, float]]] = {}
    print(
        f"{'preset':14s} {'arenas':>6s} {'face µs/step':>13s} {'bare µs/step':>13s} "
        f"{'face cost µs/step':>18s} {'per agent-step':>15s} {'share':>6s}"
    )
    for preset in config.presets:
        for arenas in config.arenas:
            row = measure(preset, arenas, config)
            report.setdefault(preset, {})[arenas] = row
            print(
                f"{preset:14s} {arenas:6d} {row['face_us_per_step']:13.1f} "
                f"{row['bare_us_per_step']:13.1f} {row['face_cost_us_per_step']:18.1f} "
                f"{row['face_cost_us_per_agent_step']:15.2f} {row['face_share']:6.0%}"
            )
    return report


def cli() -> None:
    main(tyro.cli(FaceBenchConfig))


if __name__ == "__main__":
    cli()
