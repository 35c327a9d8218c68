"""RLlib's DQN on overtake: Ray's env runners each open arenas on the simulator servers.

    # one machine: a simulator server (or several) and a local Ray cluster
    overtake-server --name sim-a &  overtake-server --listen tcp/127.0.0.1:7448 --name sim-b &
    python examples/rllib_dqn.py --connect tcp/127.0.0.1:7447 tcp/127.0.0.1:7448 --env-runners 2

    # many machines: join a running Ray cluster, reach the servers through a Zenoh router
    python examples/rllib_dqn.py --ray-address auto --connect tcp/router:7447 --env-runners 16

Distribution is Ray's: each env runner (a Ray actor, on any node of the cluster) makes its
environments with ``overtake/RemoteHighway-v0``. Given several endpoints (servers without a
router), runner i dials endpoint i mod n, so the runners share the servers out in turn; given
one endpoint (a router), every runner reaches every server behind it and its client opens the
arenas on the one with the most free arenas. Learning happens in RLlib's learner. The
observations RLlib gets are the LIDAR and the ego vector, flattened by RLlib's own
``FlattenObservations`` connector (the camera is switched off: it would only be rendered to be
thrown away).

Needs ``pip install -e ".[rllib]"`` (ray[rllib]).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import tyro


@dataclass(frozen=True)
class Args:
    connect: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    """Zenoh endpoints of the simulator servers (or of a router in front of them)"""
    preset: str = "min2018"
    set: tuple[str, ...] = ()
    """simulator overrides, dotted.name=value"""
    env_runners: int = 2
    """Ray actors stepping environments, each with its own arenas"""
    envs_per_runner: int = 1
    iterations: int = 10
    """RLlib training iterations"""
    learning_starts: int = 1_000
    train_batch_size: int = 32
    ray_address: str | None = None
    """a running Ray cluster ("auto" or host:port); None starts a local one"""
    num_cpus: int | None = None
    """CPUs of the local Ray cluster (None: Ray counts them)"""


def overtake_env(env_config: dict[str, Any]) -> Any:
    """RLlib's env creator: one remote arena (runs inside each env runner; ``env_config`` is
    RLlib's EnvContext, which knows the runner's index, 1 for the first remote runner)."""
    import gymnasium as gym

    import overtake.client  # noqa: F401  (registers overtake/RemoteHighway-v0)
    from overtake.client.wire.remote import RemoteConfig

    endpoints = list(env_config["connect"])
    runner = max(getattr(env_config, "worker_index", 1), 1)
    dialled = (endpoints[(runner - 1) % len(endpoints)],)
    return gym.make(
        "overtake/RemoteHighway-v0",
        preset=env_config["preset"],
        overrides=env_config["overrides"],
        remote=RemoteConfig(connect=dialled, trainer_name=f"rllib-runner-{runner}"),
    )


def main(args: Args) -> list[dict[str, Any]]:
    """Train; returns each iteration's episode return mean and the steps sampled."""
    import ray
    from ray.rllib.algorithms.dqn import DQNConfig
    from ray.rllib.connectors.env_to_module import FlattenObservations
    from ray.tune.registry import register_env

    from overtake.client.episodes.scenario import parse_overrides

    overrides = {"camera.enabled": False, **parse_overrides(args.set)}
    register_env("overtake-remote", overtake_env)
    ray.init(
        address=args.ray_address,
        num_cpus=args.num_cpus if args.ray_address is None else None,
        include_dashboard=False,
        log_to_driver=False,
    )
    try:
        config = (
            DQNConfig()
            .environment(
                "overtake-remote",
                env_config={
                    "connect": list(args.connect),
                    "preset": args.preset,
                    "overrides": overrides,
                },
            )
            .env_runners(
                num_env_runners=args.env_runners,
                num_envs_per_env_runner=args.envs_per_runner,
                env_to_module_connector=lambda env, spaces=None, device=None: FlattenObservations(),
            )
            .training(
                train_batch_size_per_learner=args.train_batch_size,
                num_steps_sampled_before_learning_starts=args.learning_starts,
                replay_buffer_config={"type": "PrioritizedEpisodeReplayBuffer", "capacity": 50_000},
            )
        )
        algo = config.build_algo()
        history = []
        try:
            for iteration in range(args.iterations):
                result = algo.train()
                runners = result.get("env_runners", {})
                row = {
                    "iteration": iteration + 1,
                    "episode_return_mean": runners.get("episode_return_mean"),
                    "env_steps_sampled": result.get("num_env_steps_sampled_lifetime"),
                }
                print(row)
                history.append(row)
        finally:
            algo.stop()
        return history
    finally:
        ray.shutdown()


if __name__ == "__main__":
    main(tyro.cli(Args))
