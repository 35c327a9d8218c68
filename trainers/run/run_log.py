"""A training run's log lines: what each ``{"kind": "train", ...}`` line averages since the
last one (losses, Q-values of the actions taken, the rewards stored, where the time went), and
the progress bar."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from ..config.train_config import TrainConfig


@dataclass
class Timings:
    """Wall seconds spent per part of the loop since the last log line."""

    env: float = 0.0
    act: float = 0.0
    update: float = 0.0
    replay: float = 0.0

    def shares(self) -> dict[str, float]:
        total = self.env + self.act + self.update + self.replay
        return {
            f"time_{k}": (v / total if total else 0.0) for k, v in dataclasses.asdict(self).items()
        }


class LogWindow:
    """What the next training log line averages, since ``start_step`` at ``start_t``
    (``time.perf_counter()`` seconds)."""

    def __init__(self, start_step: int, start_t: float) -> None:
        self.start_step, self.start_t = start_step, start_t
        self.losses: list[float] = []
        self.q_taken: list[float] = []
        self.reward_sum = 0.0
        self.shield_overrides = 0
        self.timings = Timings()

    def add_times(self, times: tuple[float, float, float, float, float]) -> None:
        """An iteration's time split: act, env, replay and update, from five clock readings."""
        t0, t1, t2, t3, t4 = times
        self.timings.act += t1 - t0
        self.timings.env += t2 - t1
        self.timings.replay += t3 - t2
        self.timings.update += t4 - t3

    def train_line(
        self,
        step: int,
        now: float,
        *,
        episodes: int,
        wall_s: float,
        epsilon: float,
        updates: int,
        replay: int,
        shielded: bool,
    ) -> dict[str, Any]:
        """The ``{"kind": "train", ...}`` line of the window ending at ``step``, ``now``: the
        run's counters, then the window's averages: loss, Q of the taken actions, the rewards
        of the transitions stored since ``from_step`` (Fayjie et al.'s Fig. 6 plots them per
        3,000 steps; a resumed run's first window begins at its checkpoint, not at the line
        before), the shield's overrides where it is on, steps per second and the time split."""
        return {
            "kind": "train",
            "step": step,
            "episodes": episodes,
            "wall_s": wall_s,
            "epsilon": epsilon,
            "updates": updates,
            "loss": float(np.mean(self.losses)) if self.losses else None,
            "q_taken": float(np.mean(self.q_taken)) if self.q_taken else None,
            "reward_sum": self.reward_sum,
            "from_step": self.start_step,
            **({"shield_overrides": self.shield_overrides} if shielded else {}),
            "steps_per_s": (step - self.start_step) / max(now - self.start_t, 1e-9),
            "replay": replay,
            **self.timings.shares(),
        }


def progress_bar(config: TrainConfig, start: int) -> Any:
    """A tqdm bar of the run's steps from ``start`` (None with --no-progress)."""
    if not config.progress:
        return None
    from tqdm import tqdm

    return tqdm(
        total=config.total_steps,
        initial=start,
        unit="step",
        dynamic_ncols=True,
        desc=f"{config.algo}/{config.inputs}",
        file=sys.stderr,
    )
