"""The vector environment as a training run steps it.

overtake's vector environment (:class:`~overtake.envs.faces.VectorFace`, in process or
remote) offers EnvPool's ``send(part, actions)`` / ``recv(part)`` over its parts, and its
simulator says what else there is: the behaviour spec, the road in process, the network of a
remote one. Any other Gymnasium vector environment is one part stepped by ``step``, with none of
those. :class:`EnvParts` reads them once, in this one place, so that the training loop calls
one API whatever it was given.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from overtake.envs.faces import Network, Road, VectorFace
from overtake.protocol.messages import BehaviourSpec


class EnvParts:
    """``envs`` (a Gymnasium vector environment of ``num_envs``) by parts."""

    def __init__(self, envs: Any, num_envs: int) -> None:
        self.envs = envs
        # overtake's own face (not wrapped: a wrapper hides what it offers, and the run then
        # steps it as any other environment).
        self.face: VectorFace | None = envs if isinstance(envs, VectorFace) else None
        simulator = self.face.simulator if self.face is not None else None
        self.rows: tuple[slice, ...] = (
            self.face.part_slices if self.face is not None else (slice(0, num_envs),)
        )
        """each part's rows of the vector environment's arrays"""
        self.indices = tuple(np.arange(num_envs)[s] for s in self.rows)
        """each part's environment indices"""
        self.behaviour_spec: BehaviourSpec | None = simulator.spec if simulator else None
        """what an agent sees and drives; None for an environment of the caller's"""
        self.sim_config: dict[str, Any] | None = simulator.sim_config if simulator else None
        """the simulator's configuration, for the run record"""
        self.road: Road | None = simulator.road if simulator else None
        """an in-process simulator's road, for the run's recording (a remote one's roads reach
        a recording through a spectator)"""
        self.network: Network | None = simulator.network if simulator else None
        """where a remote simulator's arenas are"""

    @property
    def count(self) -> int:
        return len(self.rows)

    def step(self, actions: np.ndarray) -> tuple[Any, ...]:
        """All parts at once (lock-step)."""
        return self.envs.step(actions)

    def send(self, part: int, actions: np.ndarray) -> None:
        """Part ``part``'s actions, without waiting for its Steps."""
        assert self.face is not None  # a foreign environment has one part, stepped by step
        self.face.send(part, actions)

    def recv(self, part: int) -> tuple[Any, ...]:
        """Part ``part``'s Steps of the actions sent for it last."""
        assert self.face is not None
        return self.face.recv(part)

    def label_step(self, step: int) -> None:
        """The road's world frames (a spectator's of remote arenas, the run's own in process)
        carry the trainer's step count sent with each action: a recording of them then lies on
        the run's ``step`` timeline."""
        if self.face is not None:
            self.face.label_step(step)

    def remote_facts(self) -> dict[str, Any]:
        """With --connect: this trainer's name on the network, and how often its server was
        lost and its arenas reopened (each loss ends the episodes under way as truncated)."""
        if self.network is None:
            return {}
        return {"trainer": self.network.trainer, "server_losses": self.network.losses()}

    def recorded_arenas(self) -> tuple[str, tuple[int, ...]] | None:
        """The server and arenas environment 0 lies among, for the recording's road view:
        every part's arenas on that server (the usual case; with several servers behind a
        router the parts may open on different ones); None in-process."""
        if self.network is None:
            return None
        placements = self.network.placements()
        server = placements[0][0]
        arenas = tuple(a for where, ids in placements if where == server for a in ids)
        return server, arenas
