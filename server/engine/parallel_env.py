"""``HighwayParallelEnv``: several learning cars on one road, in PettingZoo's Parallel API.

The PettingZoo face (:mod:`overtake.envs.parallel_face`) over the simulator in this
process: one arena holds ``agents`` controlled cars (``car_0``, ``car_1``, ...) among the
preset's traffic, every live car acting in every step, each with the single-agent spaces of
``overtake/Highway-v0`` and its own reward, flags and info. A car whose episode ended leaves the
road until the next ``reset`` (PettingZoo's rule), while the others drive on. This differs from
the server's shared roads, where a car that ended restarts behind the others at once
(Gymnasium's autoreset): those serve trainers that never stop, this serves PettingZoo's
episodes.

With one agent it is ``HighwayEnv`` bit for bit (same seed, same actions).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from overtake.envs.parallel_face import ParallelFace
from overtake.protocol.vocabulary import DEFAULT_PRESET

from ..sim import SimConfig
from .env import _InProcess, in_process_config
from .local import local_simulator


class HighwayParallelEnv(_InProcess, ParallelFace):
    """``agents`` learning cars on one simulated road (Min et al. 2018 by default)."""

    def __init__(
        self,
        agents: int = 2,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Any] | None = None,
        config: SimConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        self.config = in_process_config(preset, overrides, config)
        super().__init__(
            local_simulator(self.config, arenas=1, agents_per_arena=agents), render_mode
        )
