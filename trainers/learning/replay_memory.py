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

**On disk, for an exact resume** (``directory``): the per-slot arrays are memory-mapped
``.npy`` files in that directory, written as they fill, so a checkpoint writes none of them
(only :meth:`ReplayMemory.state`, a few small arrays) and a run's replay outlives its process.
Each ring then has ``spare`` slots beyond the ``capacity // num_envs`` it holds: the writes
after a checkpoint go into slots that the checkpoint's window does not cover, so a run killed
between checkpoints and resumed from the last one finds that window as it was. The writer
must checkpoint again before a ring has taken ``spare`` writes since the last one
(:attr:`ReplayMemory.needs_checkpoint`).

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

import json
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
        directory: Path | None = None,
        spare: int = 0,
        reopen: bool = False,
    ) -> None:
        if n_step < 1:
            raise ValueError(f"n_step must be >= 1, got {n_step}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if spare < 0 or (spare == 0 and directory is not None):
            raise ValueError(f"a replay on disk needs spare slots >= 1, got {spare}")
        per_env = capacity // num_envs
        if per_env < stack + 1:
            raise ValueError(
                f"a replay of {capacity} transitions over {num_envs} environments "
                f"leaves {per_env} frames each; at least {stack + 1} are needed"
            )
        self.capacity, self.num_envs, self.per_env = capacity, num_envs, per_env
        self.shapes, self.stack, self.stacked = shapes, stack, stacked
        # Slots per ring: the per_env it holds, and the spare ones written after a checkpoint.
        self.slots = per_env + spare
        self.spare = spare
        self.directory = directory
        layout = {
            **{
                f"frame_{name}": (tuple(shape), dtype)
                for name, (shape, dtype) in shapes.shapes.items()
            },
            "mask": ((shapes.actions,), np.int8),
            "action": ((), np.int64),
            "reward": ((), np.float32),
            "terminated": ((), bool),
            "has_next": ((), bool),
            "ep_step": ((), np.int64),
        }
        self._files: list[np.memmap] = []
        arrays = self._allocate(layout, reopen)
        self.frames = {name: arrays[f"frame_{name}"] for name in shapes.shapes}
        self.mask = arrays["mask"]
        self.action = arrays["action"]
        self.reward = arrays["reward"]
        self.terminated = arrays["terminated"]
        self.has_next = arrays["has_next"]
        self.ep_step = arrays["ep_step"]
        self.pos = np.zeros(num_envs, dtype=np.int64)  # next slot to write, per env
        self.count = np.zeros(num_envs, dtype=np.int64)  # frames held, per env
        self.held = 0  # transitions held (has_next within the rings' windows)
        # Frames written per ring since the last checkpoint (mark()).
        self.written = np.zeros(num_envs, dtype=np.int64)
        self.rng = np.random.default_rng(seed)
        self.n_step, self.gamma = n_step, gamma
        self.priority_alpha, self.priority_eps = priority_alpha, priority_eps
        # Leaf env * slots + slot: the transition that left that slot.
        self.tree = SumTree(num_envs * self.slots) if prioritized else None
        self.max_priority = 1.0

    def _allocate(
        self, layout: dict[str, tuple[tuple[int, ...], Any]], reopen: bool
    ) -> dict[str, np.ndarray]:
        """The per-slot arrays: in memory, or memory-mapped files in :attr:`directory`
        (created afresh, or with ``reopen`` the ones there, checked against the layout)."""
        size = (self.num_envs, self.slots)
        if self.directory is None:
            return {
                name: np.zeros(size + shape, dtype=dtype) for name, (shape, dtype) in layout.items()
            }
        if not reopen:
            # Made in a side directory, then renamed: a replay directory is never half made.
            partial = self.directory.with_name(self.directory.name + ".tmp")
            for old in (partial, self.directory):
                if old.exists():
                    for file in old.iterdir():
                        file.unlink()
                    old.rmdir()
            partial.mkdir(parents=True)
            for name, (shape, dtype) in layout.items():
                np.lib.format.open_memmap(
                    partial / f"{name}.npy", mode="w+", dtype=dtype, shape=size + shape
                ).flush()
            partial.rename(self.directory)
        arrays = {}
        for name, (shape, dtype) in layout.items():
            path = self.directory / f"{name}.npy"
            try:
                mapped = np.lib.format.open_memmap(path, mode="r+")
            except (OSError, ValueError) as error:
                raise ReplayMismatch(f"{path} is not a readable replay file ({error})") from None
            if mapped.shape != size + shape or mapped.dtype != np.dtype(dtype):
                raise ReplayMismatch(
                    f"{path} is {mapped.dtype}{mapped.shape}, this run needs "
                    f"{np.dtype(dtype)}{size + shape} (same replay size, environments and inputs)"
                )
            self._files.append(mapped)
            arrays[name] = mapped.view(np.ndarray)
        return arrays

    # --- writing --------------------------------------------------------------------------

    def _write(
        self, envs: np.ndarray, frames: Frames, mask: np.ndarray, ep_step: np.ndarray
    ) -> None:
        slots = self.pos[envs]
        # A full ring's oldest frame leaves its window (left as it is: a checkpoint's window
        # may still hold it), and with it the transition that left that frame.
        full = envs[self.count[envs] == self.per_env]
        if full.size:
            leaving = (self.pos[full] - self.per_env) % self.slots
            self.held -= int(self.has_next[full, leaving].sum())
            if self.tree is not None:
                self.tree.update(full * self.slots + leaving, np.zeros(full.size))
        for name, store in self.frames.items():
            store[envs, slots] = frames[name]
        self.mask[envs, slots] = mask
        self.ep_step[envs, slots] = ep_step
        self.has_next[envs, slots] = False  # an overwritten slot's old transition is gone
        if self.tree is not None:
            self.tree.update(envs * self.slots + slots, np.zeros(envs.size))
        self.pos[envs] = (slots + 1) % self.slots
        self.count[envs] = np.minimum(self.count[envs] + 1, self.per_env)
        self.written[envs] += 1

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
        last = (self.pos[envs] - 1) % self.slots
        self.action[envs, last] = action
        self.reward[envs, last] = reward
        self.terminated[envs, last] = terminated
        next_step = self.ep_step[envs, last] + 1
        self._write(envs, frames, mask, next_step)
        self.has_next[envs, last] = True
        self.held += envs.size
        if self.tree is not None:
            leaves = envs * self.slots + last
            self.tree.update(leaves, np.full(envs.size, self.max_priority**self.priority_alpha))

    def __len__(self) -> int:
        """Transitions held (those a sample may still draw are a few fewer)."""
        return self.held

    # --- sampling -------------------------------------------------------------------------

    def _valid(self, envs: np.ndarray, slots: np.ndarray) -> np.ndarray:
        oldest = (self.pos[envs] - self.count[envs]) % self.slots
        age = (slots - oldest) % self.slots
        needed = np.minimum(self.ep_step[envs, slots], self.stack - 1)
        return self.has_next[envs, slots] & (age >= needed) & (age < self.count[envs])

    def _stack_slots(self, slots: np.ndarray, ep_step: np.ndarray) -> np.ndarray:
        """(B, stack) slots of the stack ending at ``slots``, oldest first, repeating the
        episode's first frame before its start."""
        back = np.minimum(np.arange(self.stack - 1, -1, -1)[None, :], ep_step[:, None])
        return (slots[:, None] - back) % self.slots

    def _draw(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """``count`` (env, slot) pairs: uniformly over the transitions held, or in proportion
        to their priorities."""
        if self.tree is not None:
            leaves = self.tree.sample(count, self.rng)
            return leaves // self.slots, leaves % self.slots
        weights = self.count / self.count.sum()
        e = self.rng.choice(self.num_envs, size=count, p=weights)
        oldest = (self.pos[e] - self.count[e]) % self.slots
        s = (oldest + (self.rng.random(count) * self.count[e]).astype(np.int64)) % self.slots
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
        nxt = (last + 1) % self.slots
        next_slots = self._stack_slots(nxt, self.ep_step[envs, last] + 1)
        weight = index = None
        if self.tree is not None:
            index = envs * self.slots + slots
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
            following = (slot + 1) % self.slots
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

    # --- on disk ----------------------------------------------------------------------------

    @property
    def needs_checkpoint(self) -> bool:
        """Whether a ring has taken as many writes since the last :meth:`mark` as it has spare
        slots: the next write would overwrite a frame the last checkpoint's window holds, so
        a checkpoint must come first (always False for a replay in memory)."""
        return self.directory is not None and int(self.written.max()) >= self.spare

    def mark(self) -> dict[str, Any]:
        """At a checkpoint: the files flushed to disk and the writes counted from here; returns
        :meth:`state`, what the checkpoint stores of the replay."""
        for mapped in self._files:
            mapped.flush()
        self.written[:] = 0
        return self.state()

    def state(self) -> dict[str, Any]:
        """What the per-slot arrays do not hold: the rings' positions and counts, the
        transitions held, the sampling generator, and the priorities (plain data and
        arrays; the arrays are copies)."""
        state: dict[str, Any] = {
            "layout": self._layout(),
            "pos": self.pos.copy(),
            "count": self.count.copy(),
            "held": self.held,
            "rng_json": json.dumps(self.rng.bit_generator.state),
        }
        if self.tree is not None:
            state["tree_nodes"] = self.tree.nodes.copy()
            state["max_priority"] = self.max_priority
        return state

    def load_state(self, state: dict[str, Any]) -> None:
        """Back to a checkpoint's :meth:`state` (the per-slot arrays being the files it was
        taken with): the frames written since then lie outside its windows, and the one
        transition that may have been completed since (each ring's newest frame's) is
        undone."""
        if state.get("layout") != self._layout():
            raise ReplayMismatch(
                f"the checkpoint's replay is {state.get('layout')}, this run's {self._layout()}"
            )
        if (self.tree is not None) != ("tree_nodes" in state):
            raise ReplayMismatch(
                "the checkpoint's replay was "
                + ("not " if self.tree is not None else "")
                + "prioritized, this run's is"
                + ("" if self.tree is not None else " not")
            )
        self.pos[:] = state["pos"]
        self.count[:] = state["count"]
        self.held = int(state["held"])
        self.rng.bit_generator.state = json.loads(state["rng_json"])
        newest = (self.pos - 1) % self.slots
        envs = np.flatnonzero(self.count > 0)
        self.has_next[envs, newest[envs]] = False
        if self.tree is not None:
            self.tree.nodes[:] = state["tree_nodes"]
            self.max_priority = float(state["max_priority"])
        self.written[:] = 0

    def _layout(self) -> dict[str, Any]:
        return {
            "capacity": self.capacity,
            "num_envs": self.num_envs,
            "slots": self.slots,
            "frames": {
                name: [list(shape), np.dtype(dtype).name]
                for name, (shape, dtype) in self.shapes.shapes.items()
            },
        }


class ReplayMismatch(ValueError):
    """A replay on disk, or a checkpoint's account of it, that does not fit the run that
    opens it (another size, number of environments or inputs)."""
