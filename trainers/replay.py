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
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

# Frame stacking is shared with policies that act without PyTorch (overtake.client.frames).
from overtake.client.frames import Frames, FrameShapes, FrameStacker

__all__ = ["FrameShapes", "FrameStacker", "Frames", "ReplayMemory"]


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
    ) -> None:
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

    def sample(self, batch: int) -> dict[str, np.ndarray]:
        """``batch`` transitions drawn uniformly: states and next states as stacks."""
        if len(self) == 0:
            raise RuntimeError("the replay holds no transitions yet")
        envs = np.empty(batch, dtype=np.int64)
        slots = np.empty(batch, dtype=np.int64)
        weights = self.count / self.count.sum()
        missing = np.arange(batch)
        for _ in range(1000):
            e = self.rng.choice(self.num_envs, size=missing.size, p=weights)
            oldest = (self.pos[e] - self.count[e]) % self.per_env
            s = (
                oldest + (self.rng.random(missing.size) * self.count[e]).astype(np.int64)
            ) % self.per_env
            envs[missing], slots[missing] = e, s
            missing = missing[~self._valid(e, s)]
            if missing.size == 0:
                break
        else:
            raise RuntimeError("could not draw valid transitions (the replay holds too few)")
        ep_step = self.ep_step[envs, slots]
        nxt = (slots + 1) % self.per_env
        now_slots = self._stack_slots(slots, ep_step)
        next_slots = self._stack_slots(nxt, ep_step + 1)
        out: dict[str, np.ndarray] = {
            "action": self.action[envs, slots],
            "reward": self.reward[envs, slots],
            "terminated": self.terminated[envs, slots],
            "next_mask": self.mask[envs, nxt],
        }
        rows = envs[:, None]
        for name, store in self.frames.items():
            if name in self.stacked:
                out[name] = store[rows, now_slots]
                out["next_" + name] = store[rows, next_slots]
            else:
                out[name] = store[envs, slots]
                out["next_" + name] = store[envs, nxt]
        return out

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


def _restore(target: np.ndarray, value: np.ndarray, what: str) -> None:
    if value.shape != target.shape or value.dtype != target.dtype:
        raise ValueError(
            f"saved replay {what} is {value.dtype}{value.shape}, this run needs "
            f"{target.dtype}{target.shape} (same capacity, environments and "
            "inputs required)"
        )
    target[...] = value
