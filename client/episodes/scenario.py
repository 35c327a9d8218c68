"""Which simulator a command runs, and where: typed once, for every command.

:class:`Where` is where the simulator is (this process, or a server reached over Zenoh with
its credentials and a transport for its Steps); :class:`Scenario` is which simulator: a
preset, its traffic (a :data:`~overtake.protocol.vocabulary.Density` word), its episode length
and any other overrides. A command's configuration holds them as fields (``where``,
``scenario``) beside its own options: ``overtake-drive``, ``-eval``, ``-train`` and
``-unity-bridge`` hold both; ``overtake-replay`` (whose scenario is the record's) and
``overtake-experiment`` (whose scenario is its paper's) hold a Where. On the command line
(tyro, ``OmitArgPrefixes``) their fields are the same flags in every command (``--connect``,
``--preset``, ...). ``overtake-status`` and ``overtake-spectate`` only watch servers (no
arenas, rounds or transport): they take ``--connect`` and the security options alone.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

import gymnasium as gym

from overtake.cli import UsageError
from overtake.cli.options import unset
from overtake.client.wire.remote_config import RemoteConfig
from overtake.client.wire.steps_channel import Transport
from overtake.envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments
from overtake.envs.faces import VectorFace
from overtake.ipc.transport import SecurityConfig
from overtake.protocol.vocabulary import (
    DEFAULT_PRESET,
    DENSITY_SETTING,
    EPISODE_LENGTH_SETTING,
    Density,
)


def parse_overrides(items: tuple[str, ...]) -> dict[str, object]:
    """Simulator overrides from ``dotted.name=value`` items (the value read as JSON, else kept
    as a string)."""
    overrides: dict[str, object] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise UsageError(f"--set expects dotted.name=value, got {item!r}")
        try:
            overrides[name] = json.loads(text)
        except json.JSONDecodeError:
            overrides[name] = text
    return overrides


# RemoteConfig's defaults, which Where's remote settings keep (one source).
_REMOTE = RemoteConfig()


@dataclass(frozen=True, kw_only=True)
class Where:
    """Where the simulator is: in this process, or on a server reached over Zenoh."""

    connect: tuple[str, ...] = ()
    """simulator servers' (or a router's) Zenoh endpoints, e.g. tcp/127.0.0.1:7447 (one or
    more: the first reachable is used); none runs the simulator in this process"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates for --connect"""
    transport: Transport = "auto"
    """how a server's Steps reach this process (--connect): auto (shared memory where the
    server is on this host, Zenoh otherwise), shm (shared memory or an error), zenoh"""
    spin_s: float = 0.002
    """through shared memory, how long to wait for a round spinning (yielding the core) before
    sleeping: a process that sleeps between rounds computes the next one slower on a virtual
    machine (RemoteConfig.spin_s); 0 always sleeps"""
    server: Annotated[str | None, unset("NAME")] = None
    """with --connect: open the arenas on this server (its --name); unset: the least loaded"""
    connect_timeout_s: float = _REMOTE.connect_timeout_s
    """with --connect: how long to keep trying to reach the endpoint"""
    request_timeout_s: float = _REMOTE.request_timeout_s
    """with --connect: how long an open, reset, close or status request may take"""
    step_timeout_s: float = _REMOTE.step_timeout_s
    """with --connect: how long to wait for a step's observations (longer than the server's
    step deadline)"""
    reconnect_timeout_s: float = _REMOTE.reconnect_timeout_s
    """with --connect: after losing the server, how long to wait for one to reopen the arenas
    on (0: never)"""
    lease_s: float = _REMOTE.lease_s
    """with --connect: if this process's host vanishes, servers free its arenas within this"""
    trainer_name: Annotated[str | None, unset("NAME")] = None
    """with --connect: a readable prefix for this process's id in server logs and status;
    unset: the usrpwd user, else trainer"""

    @property
    def in_process(self) -> bool:
        """Whether the simulator runs in this process (no --connect)."""
        return not self.connect

    def remote(self) -> RemoteConfig:
        """How this process reaches the server --connect names: every setting of
        :class:`RemoteConfig`, from this configuration's fields."""
        if self.in_process:
            raise UsageError("no --connect: the simulator runs in this process")
        return RemoteConfig(
            connect=self.connect,
            server=self.server,
            connect_timeout_s=self.connect_timeout_s,
            request_timeout_s=self.request_timeout_s,
            step_timeout_s=self.step_timeout_s,
            reconnect_timeout_s=self.reconnect_timeout_s,
            lease_s=self.lease_s,
            security=self.security,
            trainer_name=self.trainer_name,
            steps_transport=self.transport,
            spin_s=self.spin_s,
        )

    def describe(self) -> str:
        return "in-process" if self.in_process else f"on {', '.join(self.connect)}"

    def open(
        self,
        preset: str,
        overrides: Mapping[str, Any],
        num_envs: int,
        parts: int = 1,
        as_recorded: Mapping[str, Any] | None = None,
        observations: Sequence[str] = (),
        ego_fields: Sequence[str] = (),
    ) -> VectorFace:
        """``num_envs`` arenas of ``preset`` with ``overrides`` as one vector environment:
        in this process, or on the server, there in ``parts`` groups (see
        ``RemoteHighwayVectorEnv``). ``as_recorded``: the configuration an episode record was
        made on; the simulator (here or the server's) builds that one again from its own
        settings' history, or refuses with BadConfig, naming what differs. ``observations``:
        only these sensors on (a trainer's network reads no others; none named: the
        configuration's). ``ego_fields``: the ego vector's fields the trainer reads, in order
        (none named: the configuration's)."""
        recorded = None if as_recorded is None else dict(as_recorded)
        register_environments()
        if self.in_process:
            envs = gym.make_vec(
                HIGHWAY_ENV_ID,
                num_envs=num_envs,
                vectorization_mode="vector_entry_point",
                preset=preset,
                overrides=dict(overrides),
                as_recorded=recorded,
                observations=tuple(observations),
                ego_fields=tuple(ego_fields),
            )
        else:
            remote = self.remote()
            envs = gym.make_vec(
                REMOTE_HIGHWAY_ENV_ID,
                num_envs=num_envs,
                vectorization_mode="vector_entry_point",
                preset=preset,
                overrides=dict(overrides),
                remote=remote,
                parts=parts,
                as_recorded=recorded,
                observations=tuple(observations),
                ego_fields=tuple(ego_fields),
            )
        # Gymnasium builds the registered entry point itself, no wrapper around it.
        assert isinstance(envs, VectorFace)
        return envs


@dataclass(frozen=True, kw_only=True)
class Scenario:
    """Which simulator: a preset, its traffic, its episode length and other overrides."""

    preset: Annotated[str | None, unset("NAME")] = None
    """the simulator preset (docs/presets.md); unset: a checkpoint's or model's own, else
    min2018"""
    traffic: Annotated[Density | None, unset("{light,medium,heavy}")] = None
    """traffic density (each preset's cars per density: docs/presets.md); unset: the
    preset's"""
    max_decisions: Annotated[int | None, unset("N")] = None
    """episode length in decisions; unset: the preset's"""
    set: tuple[str, ...] = ()
    """more simulator overrides as dotted.name=value (the value read as JSON, else as a
    string)"""

    def preset_or(self, default: str | None) -> str:
        """The preset: this scenario's, else ``default``, else min2018."""
        return self.preset or default or DEFAULT_PRESET

    def overrides(self, base: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """The simulator overrides: ``base`` (a checkpoint's, a paper's evaluation), then
        --set, then the traffic and the episode length this scenario names."""
        overrides = dict(base or {})
        overrides.update(parse_overrides(self.set))
        if self.traffic is not None:
            overrides[DENSITY_SETTING] = self.traffic
        if self.max_decisions is not None:
            overrides[EPISODE_LENGTH_SETTING] = self.max_decisions
        return overrides


__all__ = ["Scenario", "Where", "parse_overrides"]
