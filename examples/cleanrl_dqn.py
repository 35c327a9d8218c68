"""A CleanRL-style single-file DQN on overtake's vector environment.

    python examples/cleanrl_dqn.py                                  # 8 arenas in this process
    python examples/cleanrl_dqn.py --connect tcp/127.0.0.1:7447     # 8 arenas on a server
    python examples/cleanrl_dqn.py --total-timesteps 500000 --num-envs 16

Everything is in this file, in CleanRL's manner: the arguments, the Q-network, the replay
buffer, the loop. It learns from the LIDAR and the ego vector (concatenated, an MLP), which is
enough to show the wiring; overtake's own trainer (``overtake-train``) has the papers' networks.

Two things a vector environment of Gymnasium 1.x asks of a hand-written loop, both handled
below: next-step autoreset (the step after an episode ends is a reset, whose transition is not
one to learn from) and truncation (a time limit is not a terminal state, so the target still
bootstraps from the next observation).
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch
import tyro
from torch import nn

import overtake.client  # noqa: F401  (registers overtake/Highway-v0 and RemoteHighway-v0)
from overtake.client.episodes.scenario import parse_overrides


@dataclass(frozen=True)
class Args:
    preset: str = "min2018"
    connect: str | None = None
    """a simulator server's Zenoh endpoint; None runs the simulator in this process"""
    set: tuple[str, ...] = ()
    """simulator overrides, dotted.name=value"""
    seed: int = 1
    num_envs: int = 8
    total_timesteps: int = 100_000
    """environment steps, all arenas together"""
    learning_rate: float = 2.5e-4
    buffer_size: int = 100_000
    gamma: float = 0.99
    target_network_frequency: int = 500
    """gradient steps between target-network copies"""
    batch_size: int = 128
    start_e: float = 1.0
    end_e: float = 0.05
    exploration_fraction: float = 0.5
    learning_starts: int = 5_000
    train_frequency: int = 8
    """environment steps (all arenas) per gradient step"""
    log_every: int | None = None
    """environment steps between progress lines (default: a tenth of the run)"""


def flat_observation(obs: dict[str, np.ndarray]) -> np.ndarray:
    """LIDAR (metres, scaled to [0, 1] by its 80 m range) and the ego vector, side by side."""
    return np.concatenate([obs["lidar"] / 80.0, obs["ego"] / 25.0], axis=-1).astype(np.float32)


class QNetwork(nn.Module):
    def __init__(self, inputs: int, actions: int) -> None:
        super().__init__()
        self.network = nn.Sequential(
            nn.Linear(inputs, 256),
            nn.ReLU(),
            nn.Linear(256, 128),
            nn.ReLU(),
            nn.Linear(128, actions),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.network(x)


class ReplayBuffer:
    """A ring of flat transitions."""

    def __init__(self, size: int, inputs: int, rng: np.random.Generator) -> None:
        self.obs = np.zeros((size, inputs), np.float32)
        self.next_obs = np.zeros((size, inputs), np.float32)
        self.actions = np.zeros(size, np.int64)
        self.rewards = np.zeros(size, np.float32)
        self.terminal = np.zeros(size, np.float32)
        self.size, self.count, self.at, self.rng = size, 0, 0, rng

    def add(self, obs, next_obs, actions, rewards, terminal) -> None:
        for i in range(len(actions)):
            j = self.at
            self.obs[j], self.next_obs[j] = obs[i], next_obs[i]
            self.actions[j], self.rewards[j], self.terminal[j] = actions[i], rewards[i], terminal[i]
            self.at = (self.at + 1) % self.size
            self.count = min(self.count + 1, self.size)

    def sample(self, batch: int) -> tuple[torch.Tensor, ...]:
        idx = self.rng.integers(0, self.count, batch)
        return tuple(
            torch.from_numpy(a[idx])
            for a in (self.obs, self.actions, self.rewards, self.next_obs, self.terminal)
        )


def linear_schedule(start_e: float, end_e: float, duration: int, t: int) -> float:
    slope = (end_e - start_e) / duration
    return max(slope * t + start_e, end_e)


def make_envs(args: Args) -> gym.vector.VectorEnv:
    overrides = parse_overrides(args.set)
    if args.connect is None:
        return gym.make_vec(
            "overtake/Highway-v0",
            num_envs=args.num_envs,
            vectorization_mode="vector_entry_point",
            preset=args.preset,
            overrides=overrides,
        )
    return gym.make_vec(
        "overtake/RemoteHighway-v0",
        num_envs=args.num_envs,
        vectorization_mode="vector_entry_point",
        connect=args.connect,
        preset=args.preset,
        overrides=overrides,
    )


def main(args: Args) -> list[float]:
    """Train; returns the return of every episode that ended, in order."""
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)

    envs = make_envs(args)
    try:
        actions_n = int(envs.single_action_space.n)
        obs, _ = envs.reset(seed=args.seed)
        flat = flat_observation(obs)
        q_network = QNetwork(flat.shape[1], actions_n)
        optimizer = torch.optim.Adam(q_network.parameters(), lr=args.learning_rate)
        target_network = QNetwork(flat.shape[1], actions_n)
        target_network.load_state_dict(q_network.state_dict())
        buffer = ReplayBuffer(args.buffer_size, flat.shape[1], rng)

        returns: list[float] = []
        episode_return = np.zeros(args.num_envs)
        resetting = np.zeros(args.num_envs, dtype=bool)  # next-step autoreset pending
        steps_per_iteration = args.num_envs
        iterations = args.total_timesteps // steps_per_iteration
        gradient_steps = 0
        start = time.time()
        # By default a line every tenth of the run: a short run says something too.
        log_every = max(steps_per_iteration, args.log_every or args.total_timesteps // 10)
        print(f"training {args.total_timesteps} steps on {args.num_envs} environment(s)")
        for iteration in range(iterations):
            global_step = iteration * steps_per_iteration
            epsilon = linear_schedule(
                args.start_e,
                args.end_e,
                int(args.exploration_fraction * args.total_timesteps),
                global_step,
            )
            with torch.no_grad():
                greedy = q_network(torch.from_numpy(flat)).argmax(dim=1).numpy()
            explore = rng.random(args.num_envs) < epsilon
            actions = np.where(explore, rng.integers(0, actions_n, args.num_envs), greedy)

            next_obs, rewards, terminations, truncations, _ = envs.step(actions)
            next_flat = flat_observation(next_obs)
            # The step after an episode ended only reset that arena: nothing to learn from it.
            keep = ~resetting
            buffer.add(
                flat[keep], next_flat[keep], actions[keep], rewards[keep], terminations[keep]
            )
            episode_return += np.where(keep, rewards, 0.0)
            ended = terminations | truncations
            returns.extend(float(r) for r in episode_return[ended])
            episode_return[ended] = 0.0
            resetting = ended
            flat = next_flat

            if (
                global_step > args.learning_starts
                and iteration % max(1, args.train_frequency // steps_per_iteration) == 0
            ):
                b_obs, b_actions, b_rewards, b_next, b_terminal = buffer.sample(args.batch_size)
                with torch.no_grad():
                    target_max = target_network(b_next).max(dim=1).values
                    td_target = b_rewards + args.gamma * target_max * (1.0 - b_terminal)
                old_val = q_network(b_obs).gather(1, b_actions[:, None]).squeeze(1)
                loss = nn.functional.mse_loss(td_target, old_val)
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()
                gradient_steps += 1
                if gradient_steps % args.target_network_frequency == 0:
                    target_network.load_state_dict(q_network.state_dict())

            if global_step and global_step % log_every < steps_per_iteration:
                recent = returns[-20:]
                mean = float(np.mean(recent)) if recent else float("nan")
                rate = global_step / max(time.time() - start, 1e-9)
                print(
                    f"step {global_step}: epsilon {epsilon:.2f}, {len(returns)} episodes, "
                    f"return of the last 20 {mean:.2f}, {rate:.0f} steps/s"
                )
        return returns
    finally:
        envs.close()


if __name__ == "__main__":
    main(tyro.cli(Args))
