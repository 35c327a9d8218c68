"""The vector environment as a training run steps it.

A remote vector environment opened in parts (``RemoteHighwayVectorEnv(parts=k)``) offers
EnvPool's ``send(part, actions)`` / ``recv(part)``, the rows of each part, the step label its
server repeats to spectators, and its groups on the server; an in-process or any other
Gymnasium vector environment is one part stepped by ``step``. :class:`EnvParts` reads those
once, in this one place, so that the training loop calls one API whatever it was given.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from overtake.protocol.messages import BehaviourSpec


class EnvParts:
    """``envs`` (a Gymnasium vector environment of ``num_envs``) by parts."""

    def __init__(self, envs: Any, num_envs: int) -> None:
        self.envs = envs
        # What the environment offers beyond Gymnasium's API, under any Gymnasium wrapper.
        self._own = envs.unwrapped
        rows = getattr(self._own, "part_slices", None) or (slice(0, num_envs),)
        self.rows: tuple[slice, ...] = tuple(rows)
        """each part's rows of the vector environment's arrays"""
        self.indices = tuple(np.arange(num_envs)[s] for s in self.rows)
        """each part's environment indices"""
        self.groups: tuple[Any, ...] = tuple(getattr(self._own, "groups", None) or ())
        """the arena groups on a server (one per part); none in-process"""
        self.behaviour_spec: BehaviourSpec | None = getattr(self._own, "behaviour_spec", None)
        """what an agent sees and drives; None for an environment of the caller's"""
        self.sim_config: dict[str, Any] | None = getattr(self._own, "sim_config", None)
        """the simulator's configuration, for the run record"""
        self.world_frame = getattr(self._own, "world_frame", None)
        """an in-process environment's road as a world frame, for the run's recording (a
        remote one's roads reach a recording through a spectator); None where it has none"""

    @property
    def count(self) -> int:
        return len(self.rows)

    def step(self, actions: np.ndarray) -> tuple[Any, ...]:
        """All parts at once (lock-step)."""
        return self.envs.step(actions)

    def send(self, part: int, actions: np.ndarray) -> None:
        """Part ``part``'s actions, without waiting for its Steps (a remote environment)."""
        self._own.send(part, actions)

    def recv(self, part: int) -> tuple[Any, ...]:
        """Part ``part``'s Steps of the actions sent for it last."""
        return self._own.recv(part)

    def label_step(self, step: int) -> None:
        """Remote arenas hear the trainer's step count with each action: a spectator's
        recording of them then lies on the run's ``step`` timeline (in-process environments
        have no spectators)."""
        label = getattr(self._own, "label_step", None)
        if label is not None:
            label(step)

    def remote_facts(self) -> dict[str, Any]:
        """With --connect: this trainer's name on the network, and how often its server was
        lost and its arenas reopened (each loss ends the episodes under way as truncated)."""
        if not self.groups:
            return {}
        losses = sum(g.restarts for g in self.groups)
        return {"trainer": self._own.trainer, "server_losses": losses}

    def recorded_arenas(self) -> tuple[str, tuple[int, ...]] | None:
        """The server and arenas environment 0 lies among, for the recording's road view:
        every part's arenas on that server (the usual case; with several servers behind a
        router the parts may open on different ones); None in-process."""
        if not self.groups:
            return None
        server = self.groups[0].server
        arenas = tuple(a for g in self.groups if g.server == server for a in g.arena_ids)
        return server, arenas
