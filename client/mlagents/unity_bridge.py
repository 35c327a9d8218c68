"""``overtake-unity-bridge``: ML-Agents' Python tools drive overtake as they drive a Unity scene.

ML-Agents' Python side (mlagents-envs' ``UnityEnvironment``, ``mlagents-learn``) listens on a
gRPC port (5004 for the editor, ``base_port + worker_id`` for builds) and waits for a Unity
process to dial in and call ``UnityToExternalProto.Exchange`` with ``UnityMessageProto``s. This
bridge is that Unity process: it opens arenas on an overtake server over Zenoh (a
:class:`~overtake.client.mlagents.environment.RemoteEnvironment`), dials the ML-Agents process, and
answers each exchange:

1. initialisation: overtake's name, communication version and capabilities; the answer
   carries the trainer's seed, version and ``num_areas``;
2. an empty message, whose answer is the first command (a reset);
3. then per command: ``RESET`` restarts every arena, ``STEP`` applies each deciding agent's
   discrete action and advances one decision; the answer to each is the agents' observations,
   rewards, done and max-step flags, ids and action masks (the behaviour's spec the first
   time: one discrete branch of 5 actions, the preset's observations). ``QUIT``, or the
   trainer's close (header status 400), ends the bridge and frees its arenas.

What is chosen here, where ML-Agents leaves it to the scene: the behaviour is named
``PRESET?team=0`` (``--behavior-name`` changes PRESET), as Unity names behaviours; the seed of
the ``n``-th reset (from 0) is ``seed + n * arenas`` for arena 0 and one more per arena, so
resets never repeat an episode; ``num_areas`` above 1 reopens that many arenas (a Unity scene
would instantiate that many training areas). Observations are laid out as mlagents-envs 1.1.0
expects a Unity scene's: images channels-first (1 or 3, height, width), camera pixels (uint8)
as PNG, which ML-Agents scales to [0, 1] (grey in all three channels, as Unity's grey cameras
send it, averaged back), everything else as float32 values. Environment parameters
(``EnvironmentParametersChannel.set_float_parameter("traffic.vehicle_count", 25)``, or an
``environment_parameters`` section of an mlagents-learn configuration) become simulator
overrides at the next reset, which reopens the arenas with them; whole numbers go as ints.
Other side channels (engine configuration, statistics, analytics) are not read: each is
named once in the log.

The messages are ML-Agents' own: their descriptors are read from the generated modules that
mlagents-envs ships (``communicator_objects/*_pb2.py``), into a private descriptor pool, so the
bridge works with today's protobuf while those modules themselves need protobuf 3.20 (the
ML-Agents process keeps its own). Communication version 1.5.0 (mlagents-envs 1.1.0) is the
one supported; another major version is refused, naming both.
"""

from __future__ import annotations

import contextlib
import logging
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from overtake.cli import Command
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.mlagents.environment import RemoteEnvironment
from overtake.client.mlagents.wire import (
    COMMAND_QUIT,
    COMMAND_RESET,
    COMMAND_STEP,
    COMMUNICATION_VERSION,
    COMPRESSION_NONE,
    COMPRESSION_PNG,
    ENVIRONMENT_PARAMETERS_CHANNEL,
    EXCHANGE_METHOD,
    STATUS_FAILED,
    STATUS_OK,
    BridgeError,
    PeerGone,
    agent_infos,
    brain_parameters,
    compatible,
    environment_parameter,
    load_messages,
    observation_proto,
    override_value,
    side_channel_messages,
)
from overtake.client.mlagents.wrappers import SUPPORTED_MLAGENTS_ENVS
from overtake.protocol import ProtocolError
from overtake.protocol.messages import Scalar
from overtake.protocol.vocabulary import DEFAULT_PRESET

__all__ = [
    "COMPRESSION_NONE",
    "COMPRESSION_PNG",
    "ENVIRONMENT_PARAMETERS_CHANNEL",
    "Bridge",
    "BridgeConfig",
    "BridgeError",
    "agent_infos",
    "compatible",
    "environment_parameter",
    "load_messages",
    "observation_proto",
    "override_value",
    "side_channel_messages",
]

log = logging.getLogger("overtake.unity_bridge")


# --- the bridge --------------------------------------------------------------------------------


@dataclass(frozen=True)
class BridgeConfig:
    """Play the Unity side for ML-Agents' Python tools, with arenas on an overtake server."""

    where: Where = field(default_factory=Where)
    """the overtake server (--connect: its or a router's Zenoh endpoint, e.g. tcp/SIM:7447;
    required) and every remote setting"""
    scenario: Scenario = field(default_factory=lambda: Scenario(preset=DEFAULT_PRESET))
    """the simulator of the arenas opened: a preset (overtake-server --help lists them), its
    traffic, episode length and overrides"""
    port: int = 5004
    """the ML-Agents process's gRPC port (5004: UnityEnvironment(file_name=None) and
    mlagents-learn without --env; base_port + worker_id otherwise)"""
    host: str = "localhost"
    """where the ML-Agents process runs"""
    arenas: int = 1
    """arenas opened (ML-Agents' num_areas above 1 replaces it)"""
    agents_per_arena: int = 1
    """learning cars per arena (ML-Agents sees each as an agent of the one behaviour)"""
    behavior_name: str | None = None
    """the behaviour's name on the ML-Agents side (sent as NAME?team=0, as Unity names
    behaviours; mlagents-learn's configuration keys on NAME); default the preset's name"""
    dial_timeout_s: float = 60.0
    """how long to wait for the ML-Agents process to listen"""

    @property
    def preset(self) -> str:
        return self.scenario.preset_or(None)

    def brain_name(self) -> str:
        return f"{self.behavior_name or self.preset}?team=0"


class Bridge:
    """One ML-Agents process and one overtake environment, exchange by exchange."""

    def __init__(self, config: BridgeConfig) -> None:
        import grpc

        self.config = config
        self.messages = load_messages()
        self.resets = 0
        self.seed: int | None = None
        self.brain_sent = False
        self.deciding: list[int] = []
        self.env: RemoteEnvironment | None = None
        self.brain_name = config.brain_name()
        # ML-Agents' environment parameters, applied as overrides at the next reset.
        self.parameters: dict[str, Scalar] = {}
        self.opened_with: dict[str, Scalar] = {}
        self.ignored_channels: set[uuid.UUID] = set()
        self.refused: Exception | None = None  # the server's refusal to open the arenas
        self.channel = grpc.insecure_channel(f"{config.host}:{config.port}")
        self._exchange = self.channel.unary_unary(
            EXCHANGE_METHOD,
            request_serializer=self.messages.message.SerializeToString,
            response_deserializer=self.messages.message.FromString,
        )

    def open(self, arenas: int) -> RemoteEnvironment:
        if self.env is not None:
            self.env.close()
        remote = self.config.where.remote()
        overrides: dict[str, Scalar] = {
            **self.config.scenario.overrides(),
            **self.parameters,
        }
        self.env = RemoteEnvironment(
            config=remote,
            preset=self.config.preset,
            overrides=overrides,
            arenas=arenas,
            agents_per_arena=self.config.agents_per_arena,
            seed=self.seed,
        )
        self.opened_with = dict(self.parameters)
        self.brain_sent = False
        return self.env

    def exchange(self, message: Any) -> Any | None:
        """Send ``message``; ML-Agents' next message, or None where it closed meanwhile."""
        import grpc

        try:
            reply = self._exchange(message)
        except grpc.RpcError as error:
            # ML-Agents' close() sends its goodbye (status 400) and stops its server with no
            # grace: the call may be cancelled before the goodbye is read, or (mlagents-learn,
            # closing after its export) end in the GOAWAY gRPC's server stop sends. A process
            # that dies is neither: its connection is reset ("Socket closed").
            stopped = error.code() == grpc.StatusCode.UNAVAILABLE and "Cancelling all calls" in (
                error.details() or ""
            )
            if error.code() == grpc.StatusCode.CANCELLED or stopped:
                log.info("the ML-Agents process closed the environment (its server stopped)")
                return None
            raise PeerGone(
                f"the ML-Agents process at {self.config.host}:{self.config.port} went away "
                f"({error.code().name}: {error.details()})"
            ) from None
        return reply

    def dial(self) -> None:
        import grpc

        try:
            grpc.channel_ready_future(self.channel).result(timeout=self.config.dial_timeout_s)
        except grpc.FutureTimeoutError:
            raise BridgeError(
                f"no ML-Agents process listened on {self.config.host}:{self.config.port} "
                f"within {self.config.dial_timeout_s:g} s (start UnityEnvironment(file_name="
                f"None, base_port={self.config.port}) or mlagents-learn first)"
            ) from None

    def initialise(self) -> Any:
        """The initialisation exchange; returns the answer to the empty message after it
        (the first command). The arenas open in between, with the trainer's seed and
        num_areas; if the server refuses them, the refusal answers that first command (an
        ML-Agents process waiting in its initialisation has no timeout)."""
        from importlib.metadata import version

        message = self.messages.message()
        message.header.status = STATUS_OK
        init = message.unity_output.rl_initialization_output
        init.name = "overtake"
        init.communication_version = COMMUNICATION_VERSION
        init.package_version = version("overtake")
        init.capabilities.CopyFrom(
            self.messages.capabilities(baseRLCapabilities=True, hybridActions=True)
        )
        reply = self.exchange(message)
        if reply is None:
            raise PeerGone("the ML-Agents process closed before the initialisation ended")
        trainer = reply.unity_input.rl_initialization_input
        if not compatible(COMMUNICATION_VERSION, trainer.communication_version):
            raise BridgeError(
                f"the ML-Agents process speaks communication version "
                f"{trainer.communication_version!r} (mlagents-envs "
                f"{trainer.package_version or 'unknown'}); this bridge speaks "
                f"{COMMUNICATION_VERSION} (mlagents-envs {SUPPORTED_MLAGENTS_ENVS})"
            )
        self.seed = int(trainer.seed)
        arenas = int(trainer.num_areas) if trainer.num_areas > 1 else self.config.arenas
        log.info(
            "ML-Agents %s (communication %s) at %s:%d: seed %d, %d arena(s) of %s",
            trainer.package_version,
            trainer.communication_version,
            self.config.host,
            self.config.port,
            self.seed,
            arenas,
            self.config.preset,
        )
        try:
            self.open(arenas)
        except Exception as error:  # told to ML-Agents at its first command, not a hang
            self.refused = error
        empty = self.messages.message()
        empty.header.status = STATUS_OK
        return self.exchange(empty)

    def answer(self, command: Any | None) -> Any | None:
        """Carry out one command from ML-Agents; the output to send, or None to end."""
        if command is None:
            return None
        if command.header.status != STATUS_OK:
            log.info("the ML-Agents process closed the environment")
            return None
        if self.refused is not None:
            raise BridgeError(f"the server refused the arenas: {self.refused}")
        env = self.env
        assert env is not None
        rl_input = command.unity_input.rl_input
        if rl_input.command == COMMAND_QUIT:
            log.info("the ML-Agents process asked to quit")
            return None
        self.read_side_channels(rl_input.side_channel)
        if rl_input.command == COMMAND_RESET:
            if self.parameters != self.opened_with:
                log.info("environment parameters %s: reopening the arenas", self.parameters)
                env = self.open(len(env.group.arena_ids))
            count = len(env.group.arena_ids)
            seed = None if self.seed is None else self.seed + self.resets * count
            env.reset(seed=seed)
            self.resets += 1
        elif rl_input.command == COMMAND_STEP:
            actions = rl_input.agent_actions[self.brain_name].value
            if len(actions) != len(self.deciding):
                raise BridgeError(
                    f"ML-Agents sent {len(actions)} action(s) for behaviour "
                    f"{self.brain_name!r}, expected one per deciding agent "
                    f"({len(self.deciding)}: ids {self.deciding})"
                )
            if actions:
                env.set_actions(
                    env.behavior_name,
                    np.array([_discrete(a) for a in actions], dtype=np.int64),
                )
            env.step()
        else:
            raise BridgeError(
                f"ML-Agents sent command {rl_input.command}; expected STEP (0), RESET (1) or "
                "QUIT (2)"
            )
        output = self.messages.message()
        output.header.status = STATUS_OK
        infos, self.deciding = agent_infos(env.steps, self.messages)
        rl_output = output.unity_output.rl_output
        rl_output.agentInfos[self.brain_name].value.extend(infos)
        if not self.brain_sent and infos:
            # ML-Agents learns a behaviour's spec from its brain parameters beside its first
            # agents, as a Unity scene sends them once per behaviour.
            branches = env.behavior_specs[env.behavior_name].action_spec.discrete_branches
            output.unity_output.rl_initialization_output.brain_parameters.append(
                brain_parameters(self.brain_name, branches, self.messages)
            )
            self.brain_sent = True
        return output

    def read_side_channels(self, data: bytes) -> None:
        """Keep the environment parameters ML-Agents sets; say once per other channel that
        it is not read."""
        for channel, payload in side_channel_messages(data):
            if channel == ENVIRONMENT_PARAMETERS_CHANNEL:
                parameter = environment_parameter(payload)
                if parameter is None:
                    log.warning("a sampled environment parameter is not supported; ignored")
                else:
                    self.parameters[parameter[0]] = override_value(parameter[1])
            elif channel not in self.ignored_channels:
                self.ignored_channels.add(channel)
                log.info(
                    "side channel %s is not read by overtake; its messages are ignored", channel
                )

    def fail(self, why: str) -> None:
        """Tell the ML-Agents process the bridge stops (it raises on its side)."""
        message = self.messages.message()
        message.header.status = STATUS_FAILED
        message.header.message = why
        # It may be gone already; the bridge stops either way.
        with contextlib.suppress(Exception):
            self._exchange(message, timeout=5.0)

    def close(self) -> None:
        try:
            if self.env is not None:
                self.env.close()
        finally:
            self.channel.close()


def _discrete(action: Any) -> int:
    if len(action.discrete_actions):
        return int(action.discrete_actions[0])
    if len(action.vector_actions_deprecated):
        return int(action.vector_actions_deprecated[0])
    raise BridgeError("ML-Agents sent an action with no discrete value")


def main(config: BridgeConfig) -> dict[str, Any]:
    """Serve one ML-Agents process until it closes; returns what happened. What stops the
    bridge (a version it does not speak, an action it cannot apply, an override the server
    refuses, SIGTERM) is told to the ML-Agents process too, which then raises on its side."""
    if config.where.in_process:
        raise BridgeError(
            "--connect is required: the overtake server's (or a router's) Zenoh endpoint, "
            "e.g. tcp/SIM:7447"
        )
    try:
        bridge = Bridge(config)
    except ImportError as error:  # MLAgentsMissing (says how to install), or grpc missing
        raise BridgeError(str(error)) from None
    exchanges = 0
    try:
        bridge.dial()
        try:
            command = bridge.initialise()
            while (output := bridge.answer(command)) is not None:
                command = bridge.exchange(output)
                exchanges += 1
        except PeerGone:
            raise
        except (BridgeError, ProtocolError, ValueError) as error:
            bridge.fail(f"overtake-unity-bridge: {error}")
            raise BridgeError(str(error)) from None
    finally:
        bridge.close()
    return {"exchanges": exchanges, "resets": bridge.resets}


def _report(_config: BridgeConfig, summary: dict[str, Any]) -> None:
    print(f"overtake-unity-bridge: done after {summary['exchanges']} exchange(s)")


# A signal is told to the ML-Agents process on the way out (main's BridgeError path).
COMMAND = Command(
    "overtake-unity-bridge",
    BridgeConfig,
    main,
    report=_report,
    stopping="interrupt",
    stop_error=lambda name: BridgeError(f"terminated ({name})"),
    log_format="%(asctime)s %(name)s: %(message)s",
)


if __name__ == "__main__":
    COMMAND.run()
