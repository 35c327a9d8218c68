"""``RemoteHighwayParallelEnv``: several learning cars on one road of a remote simulator, in
PettingZoo's Parallel API.

The PettingZoo face (:mod:`overtake.envs.parallel_face`) over an arena group on a server,
and so :class:`overtake.server.engine.parallel_env.HighwayParallelEnv` bit for bit for the same
preset, seed and actions: one arena of ``agents`` cars (``car_0``, ``car_1``, ...), every live car
acting in every step (one message each way). A car whose episode ended leaves the road until
the next ``reset``: with the next step the client asks the server to retire it (protocol 1.3),
so that the server does not restart it behind the others as it does on shared roads. A server
older than 1.3 would ignore that and is refused when the environment opens.

A server restart ends the episode: every live car is truncated (``info["server_restarted"]``),
and ``reset`` starts the next one on whichever server reopened the arena.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from overtake.client.envs.remote_gym import _OnNetwork, remote_simulator
from overtake.client.wire.remote_config import RemoteConfig
from overtake.envs.parallel_face import RETIRE_SINCE_MINOR, ParallelFace
from overtake.ipc.transport import Endpoints
from overtake.protocol.messages import Scalar
from overtake.protocol.vocabulary import DEFAULT_PRESET


class RemoteHighwayParallelEnv(_OnNetwork, ParallelFace):
    """``agents`` learning cars on one road of a remote simulator server."""

    metadata: dict[str, Any] = {  # noqa: RUF012
        **ParallelFace.metadata,
        "name": "overtake_remote_highway_parallel_v0",
    }

    def __init__(
        self,
        agents: int = 2,
        connect: Endpoints | None = None,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Scalar] | None = None,
        remote: RemoteConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        # A car whose episode ended must leave the road (Actions.retire, protocol 1.3).
        retire = (RETIRE_SINCE_MINOR, "several cars on one road in PettingZoo's API")
        self._open_on_network(
            render_mode,
            lambda: remote_simulator(
                connect,
                remote,
                preset,
                overrides,
                arenas=1,
                agents_per_arena=agents,
                needs=(retire,),
            ),
        )
