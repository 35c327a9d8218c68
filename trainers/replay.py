"""Frame stacking and a replay memory that stores every frame once.

The environment sends one frame per decision; the trainer keeps the last ``stack`` of them per
environment (:class:`FrameStacker`) for acting, and the replay rebuilds the same stacks when it
samples. Both follow one rule at an episode's start: the slots before the first frame hold
copies of that first frame (a LIDAR of zeros would read as a wall at 0 m).

Each environment has its own ring of ``capacity // num_envs`` frames, so its frames stay in
order and a stack is a run of neighbouring slots. Slot ``j`` holds a frame, its step within its
episode, and the transition that left it (action, reward, terminated); ``has_next[j]`` says the
following slot holds the next frame of the same episode. A transition is sampled only if its
next frame is there and the frames its stack needs have not been overwritten, so no stack or
transition ever crosses an episode boundary or mixes old and new data.

Two options of Rainbow's (Hessel et al. 2018), off by default: **n-step returns**
(``n_step`` > 1): a sample's reward is the discounted sum of up to ``n_step`` rewards of its
episode from that transition on, ``steps`` says how many (the target discounts the bootstrap
by ``gamma ** steps``), and its next state is the state after them; the window stops early at
a termination (no bootstrap), where the episode was cut by its time limit (bootstrap from the
last state it reached) and at the newest frame. **Prioritized replay** (``prioritized``,
Schaul et al. 2016, proportional): transitions are drawn with probability ``p ** alpha`` over
the sum (:class:`.sum_tree.SumTree`), new ones at the largest priority seen, and after each
update at their TD error's magnitude plus a small constant; a sample carries its importance
weight ``(N * P(i)) ** -beta`` over the batch's largest, and its ``leaves`` for the update.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

# Frame stacking is shared with policies that act without PyTorch (overtake.client.policies.frames).
from overtake.client.policies.frames import Frames, FrameShapes, FrameStacker

from .sum_tree import SumTree

__all__ = ["FrameShapes", "FrameStacker", "Frames", "ReplayBatch", "ReplayMemory"]


class ReplayBatch(NamedTuple):
    """A sample of transitions, (B, ...) each: the states and next states as the network reads
    them (stacked sensors and the latest frame of the others, by observation name), the taken
    actions, rewards (an n-step window's discounted sum), whether the episodes terminated,
    the transitions each covers (``steps``: the bootstrap is discounted by ``gamma ** steps``),
    the next states' action masks; with prioritized replay each sample's importance weight
    and its place in the sum tree (``leaves``, for its new priority), else None."""

    obs: dict[str, np.ndarray]
    next_obs: dict[str, np.ndarray]
    action: np.ndarray
    reward: np.ndarray
    terminated: np.ndarray
    steps: np.ndarray
    next_mask: np.ndarray
    weight: np.ndarray | None = None
    leaves: np.ndarray | None = None


class ReplayMemory:
    """Transitions of ``num_envs`` environments, each frame stored once."""

    def __init__(
        self,
        capacity: int,
        num_envs: int,
        shapes: FrameShapes,
        stack: int,
        stacked: tuple[str, ...],
        seed: int | None = None,
        *,
        n_step: int = 1,
        gamma: float = 0.99,
        prioritized: bool = False,
        priority_alpha: float = 0.6,
        priority_eps: float = 1e-6,
    ) -> None:
        if n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {n_step}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        per_env = capacity // num_envs
        if per_env < stack + 1:
            raise ValueError(
                f"a replay of {capacity} transitions over {num_envs} environments "
                f"leaves {per_env} frames each; at least {stack + 1} are needed"
            )
        self.capacity, self.num_envs, self.per_env = capacity, num_envs, per_env
        self.shapes, self.stack, self.stacked = shapes, stack, stacked
        size = (num_envs, per_env)
        self.frames = {
            name: np.zeros(size + tuple(shape), dtype=dtype)
            for name, (shape, dtype) in shapes.shapes.items()
        }
        self.mask = np.zeros(size + (shapes.actions,), dtype=np.int8)
        self.action = np.zeros(size, dtype=np.int64)
        self.reward = np.zeros(size, dtype=np.float32)
        self.terminated = np.zeros(size, dtype=bool)
        self.has_next = np.zeros(size, dtype=bool)
        self.ep_step = np.zeros(size, dtype=np.int64)
        self.pos = np.zeros(num_envs, dtype=np.int64)  # next slot to write, per env
        self.count = np.zeros(num_envs, dtype=np.int64)  # frames held, per env
        self.rng = np.random.default_rng(seed)
        self.n_step, self.gamma = n_step, gamma
        self.priority_alpha, self.priority_eps = priority_alpha, priority_eps
        # Leaf env * per_env + slot: the transition that left that slot.
        self.tree = SumTree(num_envs * per_env) if prioritized else None
        self.max_priority = 1.0

    # --- writing --------------------------------------------------------------------------

    def _write(
        self, envs: np.ndarray, frames: Frames, mask: np.ndarray, ep_step: np.ndarray
    ) -> None:
        slots = self.pos[envs]
        for name, store in self.frames.items():
            store[envs, slots] = frames[name]
        self.mask[envs, slots] = mask
        self.ep_step[envs, slots] = ep_step
        self.has_next[envs, slots] = False  # an overwritten slot's old transition is gone
        if self.tree is not None:
            self.tree.update(envs * self.per_env + slots, np.zeros(envs.size))
        self.pos[envs] = (slots + 1) % self.per_env
        self.count[envs] = np.minimum(self.count[envs] + 1, self.per_env)

    def start(self, envs: np.ndarray, frames: Frames, mask: np.ndarray) -> None:
        """The first frames of new episodes in ``envs`` (after a reset)."""
        envs = np.asarray(envs, dtype=np.int64)
        self._write(envs, frames, mask, np.zeros(envs.size, dtype=np.int64))

    def add(
        self,
        envs: np.ndarray,
        action: np.ndarray,
        reward: np.ndarray,
        terminated: np.ndarray,
        frames: Frames,
        mask: np.ndarray,
    ) -> None:
        """Transitions from each env's latest frame: the action taken there, the reward, whether
        the episode terminated, and the frame it led to (with its action mask)."""
        envs = np.asarray(envs, dtype=np.int64)
        if np.any(self.count[envs] == 0):
            raise RuntimeError("add() before start(): an environment has no current frame")
        last = (self.pos[envs] - 1) % self.per_env
        self.action[envs, last] = action
        self.reward[envs, last] = reward
        self.terminated[envs, last] = terminated
        next_step = self.ep_step[envs, last] + 1
        self._write(envs, frames, mask, next_step)
        self.has_next[envs, last] = True
        if self.tree is not None:
            leaves = envs * self.per_env + last
            self.tree.update(leaves, np.full(envs.size, self.max_priority**self.priority_alpha))

    def __len__(self) -> int:
        """Transitions held (those a sample may still draw are a few fewer)."""
        return int(self.has_next.sum())

    # --- sampling -------------------------------------------------------------------------

    def _valid(self, envs: np.ndarray, slots: np.ndarray) -> np.ndarray:
        oldest = (self.pos[envs] - self.count[envs]) % self.per_env
        age = (slots - oldest) % self.per_env
        needed = np.minimum(self.ep_step[envs, slots], self.stack - 1)
        return self.has_next[envs, slots] & (age >= needed) & (age < self.count[envs])

    def _stack_slots(self, slots: np.ndarray, ep_step: np.ndarray) -> np.ndarray:
        """(B, stack) slots of the stack ending at ``slots``, oldest first, repeating the
        episode's first frame before its start."""
        back = np.minimum(np.arange(self.stack - 1, -1, -1)[None, :], ep_step[:, None])
        return (slots[:, None] - back) % self.per_env

    def _draw(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """``count`` (env, slot) pairs: uniformly over the transitions held, or in proportion
        to their priorities."""
        if self.tree is not None:
            leaves = self.tree.sample(count, self.rng)
            return leaves // self.per_env, leaves % self.per_env
        weights = self.count / self.count.sum()
        e = self.rng.choice(self.num_envs, size=count, p=weights)
        oldest = (self.pos[e] - self.count[e]) % self.per_env
        s = (oldest + (self.rng.random(count) * self.count[e]).astype(np.int64)) % self.per_env
        return e, s

    def sample(self, batch: int, beta: float = 1.0) -> ReplayBatch:
        """``batch`` transitions, states and next states as stacks (``beta``: the importance
        weights' exponent, with prioritized replay)."""
        if len(self) == 0:
            raise RuntimeError("the replay holds no transitions yet")
        envs = np.empty(batch, dtype=np.int64)
        slots = np.empty(batch, dtype=np.int64)
        missing = np.arange(batch)
        for _ in range(1000):
            e, s = self._draw(missing.size)
            envs[missing], slots[missing] = e, s
            missing = missing[~self._valid(e, s)]
            if missing.size == 0:
                break
        else:
            raise RuntimeError("could not draw valid transitions (the replay holds too few)")
        ep_step = self.ep_step[envs, slots]
        now_slots = self._stack_slots(slots, ep_step)
        if self.n_step == 1:
            last, steps = slots, np.ones(batch, dtype=np.int64)
            reward = self.reward[envs, slots]
            terminated = self.terminated[envs, slots]
        else:
            last, steps, reward, terminated = self._n_step(envs, slots)
        nxt = (last + 1) % self.per_env
        next_slots = self._stack_slots(nxt, self.ep_step[envs, last] + 1)
        weight = index = None
        if self.tree is not None:
            index = envs * self.per_env + slots
            probability = self.tree.priorities[index] / self.tree.total
            importance = (len(self) * probability) ** -beta
            weight = (importance / importance.max()).astype(np.float32)
        rows = envs[:, None]
        obs, next_obs = {}, {}
        for name, store in self.frames.items():
            if name in self.stacked:
                obs[name], next_obs[name] = store[rows, now_slots], store[rows, next_slots]
            else:
                obs[name], next_obs[name] = store[envs, slots], store[envs, nxt]
        return ReplayBatch(
            obs=obs,
            next_obs=next_obs,
            action=self.action[envs, slots],
            reward=reward,
            terminated=terminated,
            steps=steps,
            next_mask=self.mask[envs, nxt],
            weight=weight,
            leaves=index,
        )

    def _n_step(
        self, envs: np.ndarray, slots: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """From each transition, up to ``n_step`` of its episode: the slot of the last one
        taken, how many, their discounted reward sum (float32) and whether the last
        terminated."""
        slot, last = slots.copy(), slots.copy()
        total = np.zeros(slots.size)
        discount = np.ones(slots.size)
        steps = np.zeros(slots.size, dtype=np.int64)
        terminated = np.zeros(slots.size, dtype=bool)
        live = np.ones(slots.size, dtype=bool)
        for k in range(self.n_step):
            total = np.where(live, total + discount * self.reward[envs, slot], total)
            steps += live
            last = np.where(live, slot, last)
            ended = self.terminated[envs, slot]
            terminated = np.where(live, ended, terminated)
            discount = np.where(live, discount * self.gamma, discount)
            following = (slot + 1) % self.per_env
            # The window goes on only within the episode, to a transition already stored.
            live &= ~ended & self.has_next[envs, following] & (k + 1 < self.n_step)
            slot = np.where(live, following, slot)
        return last, steps, total.astype(np.float32), terminated

    def update_priorities(self, index: np.ndarray, td_error: np.ndarray) -> None:
        """After an update: the sampled transitions' priorities from their TD errors."""
        assert self.tree is not None, "update_priorities() on a replay without priorities"
        priority = np.abs(np.asarray(td_error, dtype=np.float64)) + self.priority_eps
        self.max_priority = max(self.max_priority, float(priority.max()))
        # A transition overwritten since it was drawn keeps its 0.
        held = self.tree.priorities[index] > 0.0
        self.tree.update(index[held], priority[held] ** self.priority_alpha)

    # --- size and persistence -------------------------------------------------------------

    @property
    def nbytes(self) -> int:
        arrays = [
            *self.frames.values(),
            self.mask,
            self.action,
            self.reward,
            self.terminated,
            self.has_next,
            self.ep_step,
        ]
        return sum(a.nbytes for a in arrays)

    def naive_nbytes(self) -> int:
        """What storing each transition's two stacked states would take (the naive layout)."""
        stacked = sum(
            int(np.prod(shape)) * np.dtype(dtype).itemsize * self.stack
            for name, (shape, dtype) in self.shapes.shapes.items()
            if name in self.stacked
        )
        latest = sum(
            int(np.prod(shape)) * np.dtype(dtype).itemsize
            for name, (shape, dtype) in self.shapes.shapes.items()
            if name not in self.stacked
        )
        per_transition = 2 * (stacked + latest) + self.shapes.actions + 8 + 4 + 1
        return self.num_envs * self.per_env * per_transition

    def save(self, path: Path) -> None:
        """Write to ``path`` atomically (a temporary file, then a rename)."""
        arrays: dict[str, Any] = {f"frame_{name}": store for name, store in self.frames.items()}
        arrays.update(
            mask=self.mask,
            action=self.action,
            reward=self.reward,
            terminated=self.terminated,
            has_next=self.has_next,
            ep_step=self.ep_step,
            pos=self.pos,
            count=self.count,
        )
        if self.tree is not None:
            arrays.update(priority=self.tree.priorities, max_priority=np.array(self.max_priority))
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as handle:
            np.savez(handle, **arrays)
            handle.flush()
            os.fsync(handle.fileno())
        tmp.replace(path)

    def load(self, path: Path) -> None:
        with np.load(path) as data:
            for name, store in self.frames.items():
                _restore(store, data[f"frame_{name}"], f"frame {name}")
            for name in (
                "mask",
                "action",
                "reward",
                "terminated",
                "has_next",
                "ep_step",
                "pos",
                "count",
            ):
                _restore(getattr(self, name), data[name], name)
            if self.tree is not None:
                if "priority" not in data:
                    raise ValueError(
                        "saved replay has no priorities (saved without prioritized replay); "
                        "this run samples by priority"
                    )
                priorities = np.zeros(self.tree.size)
                _restore(priorities, data["priority"], "priorities")
                self.tree.update(np.arange(self.tree.size), priorities)
                self.max_priority = float(data["max_priority"])


def _restore(target: np.ndarray, value: np.ndarray, what: str) -> None:
    if value.shape != target.shape or value.dtype != target.dtype:
        raise ValueError(
            f"saved replay {what} is {value.dtype}{value.shape}, this run needs "
            f"{target.dtype}{target.shape} (same capacity, environments and "
            "inputs required)"
        )
    target[...] = value
