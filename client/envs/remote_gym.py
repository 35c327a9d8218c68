"""Gymnasium environments over a remote simulator: ``overtake/RemoteHighway-v0``.

overtake's faces (:mod:`overtake.envs.faces`) over arena groups on a server
(:class:`~overtake.client.wire.remote.ArenaGroup`, each an engine): the spaces are rebuilt
from the server's behaviour spec, and observations, rewards, flags and info are the in-process
environment's bit for bit for the same preset, seed and actions. The vector environment opens
its N arenas as one group (one message each way per step), or as ``parts`` groups stepped in
turn (``send`` / ``recv``, for a trainer that overlaps its work with the simulation), with
Gymnasium 1.x next-step autoreset, as the in-process vector env does.

A server restart is survived: the step that finds the server gone returns the last observation
with ``truncated`` set (``info["server_restarted"]``), the arenas are reopened (on the restarted
server or another one), and the next step (or reset) starts the new episodes.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from overtake.client.wire.connection import Connection
from overtake.client.wire.remote import ArenaGroup
from overtake.client.wire.remote_config import RemoteConfig
from overtake.envs.faces import Simulator, SingleFace, VectorFace
from overtake.envs.registry import check_render_mode
from overtake.ipc.transport import Endpoints
from overtake.protocol import errors
from overtake.protocol.codec import version_text
from overtake.protocol.messages import (
    AS_RECORDED_SINCE_MINOR,
    REQUESTED_READING_SINCE_MINOR,
    TYPED_SPEC_SINCE_MINOR,
    OpenRequest,
    Scalar,
    Translation,
)
from overtake.protocol.vocabulary import DEFAULT_PRESET

__all__ = [
    "TYPED_SPEC_NEED",
    "RemoteHighwayEnv",
    "RemoteHighwayVectorEnv",
    "RemoteNetwork",
    "remote_simulator",
]

# What a server's minor protocol version must be for these environments: (minor, what for).
TYPED_SPEC_NEED = (
    TYPED_SPEC_SINCE_MINOR,
    "this client reads the road, the car and the observations' columns and reach from the "
    "behaviour spec",
)


class RemoteNetwork:
    """A remote simulator's connection and its arena groups (one per part)."""

    def __init__(self, connection: Connection, groups: Sequence[ArenaGroup]) -> None:
        self.connection = connection
        self.groups = tuple(groups)

    @property
    def trainer(self) -> str:
        return self.connection.trainer

    def placements(self) -> tuple[tuple[str, tuple[int, ...]], ...]:
        return tuple((group.server, tuple(group.arena_ids)) for group in self.groups)

    def losses(self) -> int:
        return sum(group.restarts for group in self.groups)

    def close(self) -> None:
        self.connection.close()


def remote_simulator(
    connect: Endpoints | None,
    remote: RemoteConfig | None,
    preset: str,
    overrides: Mapping[str, Scalar] | None,
    arenas: int,
    agents_per_arena: int = 1,
    parts: int = 1,
    needs: tuple[tuple[int, str], ...] = (),
    as_recorded: Mapping[str, Any] | None = None,
    observations: Sequence[str] = (),
    ego_fields: Sequence[str] = (),
    translation: Translation | None = None,
) -> Simulator:
    """``arenas`` arenas of ``preset`` opened on a server reached through ``connect`` (or
    ``remote``, a RemoteConfig), as ``parts`` groups of consecutive arenas (the first ones one
    larger where they do not divide). ``needs``: (minor version, what for) the server must
    speak beyond :data:`TYPED_SPEC_NEED`; the oldest unmet one refuses it. ``as_recorded``:
    the configuration an episode record was made on, which the server builds again (or
    refuses, naming what differs). ``observations``: only these sensors on (none named: the
    configuration's; a 1.9 server ignores the request and sends every one). ``ego_fields``:
    the ego vector's fields, in order (none named: the configuration's). ``translation``: a
    configuration in another simulator's words (highway-env's config), which the server
    translates under ``overrides``; a server older than 1.11, which would ignore these two, is
    refused."""
    if not 1 <= parts <= arenas:
        raise ValueError(f"parts must be between 1 and the {arenas} arena(s), got {parts}")
    if remote is None:
        remote = RemoteConfig.from_connect(connect)
    elif connect is not None:
        raise ValueError("pass either connect or remote (a RemoteConfig), not both")
    connection = Connection(remote)
    groups: list[ArenaGroup] = []
    network = RemoteNetwork(connection, groups)
    sizes = [len(a) for a in np.array_split(np.arange(arenas), parts)]
    try:
        for size in sizes:
            groups.append(
                ArenaGroup.open(
                    connection,
                    OpenRequest(
                        trainer=connection.trainer,
                        preset=preset,
                        overrides=dict(overrides or {}),
                        arenas=size,
                        agents_per_arena=agents_per_arena,
                        claim=agents_per_arena,
                        seed=None,
                        as_recorded=json.dumps(as_recorded) if as_recorded is not None else "",
                        observations=tuple(observations),
                        ego_fields=tuple(ego_fields),
                        translation=translation,
                    ),
                )
            )
        first = groups[0]
        if as_recorded is not None:
            # A 1.8 server ignores as_recorded: it would replay on today's simulator.
            needs = (*needs, (AS_RECORDED_SINCE_MINOR, "an episode record's simulator built again"))
        if ego_fields or translation is not None:
            # A 1.10 server ignores both: it would open another simulator than the one asked for.
            needs = (
                *needs,
                (
                    REQUESTED_READING_SINCE_MINOR,
                    "the ego fields and a translated configuration asked for by the request",
                ),
            )
        for need, why in sorted((TYPED_SPEC_NEED, *needs)):
            if first.server_minor < need:
                raise errors.VersionMismatch(
                    f"server {first.server} speaks protocol 1.{first.server_minor}; {why}, "
                    f"which need 1.{need} or newer (this client speaks {version_text()}): "
                    "upgrade the server"
                )
        spec = first.spec
        assert spec is not None
    except BaseException:
        try:
            for group in groups:
                group.close()
        finally:
            connection.close()
        raise
    network.groups = tuple(groups)
    return Simulator(
        parts=tuple(groups),
        spec=spec,
        sim_config=json.loads(spec.config_json),
        network=network,
    )


class _OnNetwork:
    """What the remote faces offer of their network, and how they open it."""

    simulator: Simulator

    def _open_on_network(
        self, render_mode: str | None, open_simulator: Callable[[], Simulator], *face_args: Any
    ) -> None:
        """Open the simulator and the face over it (the next class's ``__init__``, given the
        simulator, ``face_args`` and ``render_mode``); the simulator closes again where the
        face cannot be made."""
        check_render_mode(render_mode, [])  # before the network: a remote road is not drawn
        simulator = open_simulator()
        try:
            super().__init__(simulator, *face_args, render_mode)  # type: ignore[call-arg]
        except BaseException:
            simulator.close()
            raise

    @property
    def network(self) -> RemoteNetwork:
        network = self.simulator.network
        assert isinstance(network, RemoteNetwork)
        return network

    @property
    def group(self) -> ArenaGroup:
        """The arenas on the server (ids, server name, restarts survived); with ``parts``,
        the first part's (:attr:`groups` has them all)."""
        return self.network.groups[0]

    @property
    def groups(self) -> tuple[ArenaGroup, ...]:
        """Every group of this environment's arenas, one per part, in the order of the
        environment indices."""
        return self.network.groups

    @property
    def trainer(self) -> str:
        """This trainer's name on the network (the servers' status lists it)."""
        return self.network.trainer


class RemoteHighwayEnv(_OnNetwork, SingleFace):
    """One agent on one arena of a remote simulator server."""

    def __init__(
        self,
        connect: Endpoints | None = None,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Scalar] | None = None,
        remote: RemoteConfig | None = None,
        render_mode: str | None = None,
        as_recorded: Mapping[str, Any] | None = None,
        observations: Sequence[str] = (),
        ego_fields: Sequence[str] = (),
        translation: Translation | None = None,
    ) -> None:
        self._open_on_network(
            render_mode,
            lambda: remote_simulator(
                connect,
                remote,
                preset,
                overrides,
                arenas=1,
                as_recorded=as_recorded,
                observations=observations,
                ego_fields=ego_fields,
                translation=translation,
            ),
        )


class RemoteHighwayVectorEnv(_OnNetwork, VectorFace):
    """``num_envs`` arenas of a remote server, stepped together (one message each way).

    ``parts`` > 1 opens the arenas as that many groups of consecutive environment indices
    (:attr:`part_slices`), each stepped by the server on its own, so that a trainer can overlap
    its work with the simulation (:meth:`send` / :meth:`recv`).
    """

    def __init__(
        self,
        num_envs: int = 1,
        connect: Endpoints | None = None,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Scalar] | None = None,
        remote: RemoteConfig | None = None,
        render_mode: str | None = None,
        parts: int = 1,
        as_recorded: Mapping[str, Any] | None = None,
        observations: Sequence[str] = (),
        ego_fields: Sequence[str] = (),
        translation: Translation | None = None,
    ) -> None:
        self._open_on_network(
            render_mode,
            lambda: remote_simulator(
                connect,
                remote,
                preset,
                overrides,
                arenas=num_envs,
                parts=parts,
                as_recorded=as_recorded,
                observations=observations,
                ego_fields=ego_fields,
                translation=translation,
            ),
            num_envs,
        )
