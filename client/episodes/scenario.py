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

import dataclasses
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any

import gymnasium as gym

from overtake.cli import UsageError
from overtake.cli.options import unset
from overtake.client.wire.remote_config import RemoteConfig
from overtake.envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments
from overtake.envs.faces import VectorFace
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


@dataclass(frozen=True, kw_only=True)
class Where:
    """Where the simulator is: in this process, or on a server reached over Zenoh."""

    connect: tuple[str, ...] = ()
    """simulator servers' (or a router's) Zenoh endpoints, e.g. tcp/127.0.0.1:7447 (one or
    more: the first reachable is used); none runs the simulator in this process"""
    link: RemoteConfig = field(default_factory=RemoteConfig)
    """with --connect: which server, how its rounds travel, the timeouts and the
    credentials"""
    # RemoteConfig's own connect is not a flag: remote() puts this configuration's in it.

    @property
    def in_process(self) -> bool:
        """Whether the simulator runs in this process (no --connect)."""
        return not self.connect

    def remote(self) -> RemoteConfig:
        """How this process reaches the server --connect names: :attr:`link` on these
        endpoints."""
        if self.in_process:
            raise UsageError("no --connect: the simulator runs in this process")
        return dataclasses.replace(self.link, connect=self.connect)

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
