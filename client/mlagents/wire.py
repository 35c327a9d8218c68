"""ML-Agents' wire as the bridge speaks it: the messages (read from mlagents-envs' generated
modules into a private descriptor pool, so that today's protobuf builds them while those
modules need protobuf 3.20), the version rule, what goes to ML-Agents (observations laid out
as a Unity scene's, agent infos, the brain's parameters) and what comes from it besides
commands (side channels: environment parameters become simulator overrides)."""

from __future__ import annotations

import ast
import functools
import importlib.util
import logging
import struct
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from overtake.cli import UsageError
from overtake.client.mlagents.environment import mlagents_observation_spec, mlagents_observations
from overtake.client.mlagents.wrappers import SUPPORTED_MLAGENTS_ENVS, MLAgentsMissing
from overtake.protocol.messages import Scalar, Steps

log = logging.getLogger("overtake.unity_bridge")

COMMUNICATION_VERSION = "1.5.0"
"""ML-Agents' communication version this bridge speaks (mlagents-envs 1.1.0's API_VERSION)."""
EXCHANGE_METHOD = "/communicator_objects.UnityToExternalProto/Exchange"
PACKAGE = "communicator_objects"
# Header statuses: 200 a message, 500 the bridge's failure; anything else from ML-Agents (its
# close() sends 400) ends the exchanges.
STATUS_OK, STATUS_FAILED = 200, 500
COMMAND_STEP, COMMAND_RESET, COMMAND_QUIT = 0, 1, 2
# ML-Agents' enums: ObservationTypeProto DEFAULT, CompressionTypeProto NONE and PNG.
OBSERVATION_TYPE_DEFAULT, COMPRESSION_NONE, COMPRESSION_PNG = 0, 0, 1


class BridgeError(UsageError):
    """The ML-Agents process could not be reached, spoke another version, or sent what the
    bridge cannot carry out."""


class PeerGone(BridgeError):
    """The ML-Agents process went away in the middle of an exchange."""


# --- ML-Agents' messages -------------------------------------------------------------------------


@dataclass(frozen=True)
class Messages:
    """ML-Agents' message classes, built from the descriptors mlagents-envs ships."""

    message: Any  # UnityMessageProto: header + unity_output / unity_input
    agent_info: Any
    observation: Any
    brain_parameters: Any
    capabilities: Any


def _serialized_descriptor(path: Path) -> bytes | None:
    """The serialized FileDescriptorProto in one generated ``*_pb2.py`` module, read from its
    source (importing it needs protobuf 3.20): ``serialized_pb=b'...'`` or ``_b('...')``."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.keyword) and node.arg == "serialized_pb":
            value = node.value
            if isinstance(value, ast.Call) and isinstance(value.func, ast.Name):
                return bytes(ast.literal_eval(value.args[0]).encode("latin1"))  # _b('...')
            return bytes(ast.literal_eval(value))
    return None


@functools.cache
def load_messages() -> Messages:
    """ML-Agents' message classes (raises :class:`MLAgentsMissing` saying how to install)."""
    try:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    except ImportError as exc:
        raise MLAgentsMissing(
            f"protobuf is not installed ({exc}); scripts/setup-mlagents.sh installs it"
        ) from exc
    spec = importlib.util.find_spec("mlagents_envs")
    if spec is None or spec.submodule_search_locations is None:
        raise MLAgentsMissing(
            f"mlagents-envs {SUPPORTED_MLAGENTS_ENVS} is not installed (the bridge reads "
            "ML-Agents' message definitions from it); scripts/setup-mlagents.sh installs it"
        )
    folder = Path(next(iter(spec.submodule_search_locations))) / "communicator_objects"
    files: dict[str, Any] = {}
    for path in sorted(folder.glob("*_pb2.py")):
        serialized = _serialized_descriptor(path)
        if serialized is not None:
            proto = descriptor_pb2.FileDescriptorProto.FromString(serialized)
            files[proto.name] = proto
    pool = descriptor_pool.DescriptorPool()
    added: set[str] = set()

    def add(name: str) -> None:  # dependencies first
        if name in added:
            return
        if name not in files:
            raise MLAgentsMissing(f"mlagents-envs' message definitions lack {name}")
        for dependency in files[name].dependency:
            add(dependency)
        pool.Add(files[name])
        added.add(name)

    for name in files:
        add(name)

    def cls(name: str) -> Any:
        try:
            return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{PACKAGE}.{name}"))
        except KeyError as exc:
            raise MLAgentsMissing(
                f"mlagents-envs' message definitions lack {name}: is it version "
                f"{SUPPORTED_MLAGENTS_ENVS}?"
            ) from exc

    return Messages(
        message=cls("UnityMessageProto"),
        agent_info=cls("AgentInfoProto"),
        observation=cls("ObservationProto"),
        brain_parameters=cls("BrainParametersProto"),
        capabilities=cls("UnityRLCapabilitiesProto"),
    )


def compatible(ours: str, theirs: str) -> bool:
    """ML-Agents' rule: the same major version, and for major 0 the same minor too."""
    try:
        our_parts = [int(p) for p in ours.split(".")[:2]]
        their_parts = [int(p) for p in theirs.split(".")[:2]]
    except ValueError:
        return False
    if len(their_parts) < 2 or our_parts[0] != their_parts[0]:
        return False
    return our_parts[0] != 0 or our_parts[1] == their_parts[1]


# --- what goes to ML-Agents --------------------------------------------------------------------


def observation_layout(values: np.ndarray) -> tuple[list[int], list[int]]:
    """The ML-Agents shape and dimension properties of one agent's observation as overtake
    gives it (RemoteEnvironment's: images channels-first, NONE, TE, TE)."""
    if values.ndim > 1 and not (values.ndim == 2 or (values.ndim == 3 and values.shape[2] == 3)):
        raise BridgeError(f"no ML-Agents layout for an observation of shape {values.shape}")
    spec = mlagents_observation_spec("", values.shape)
    return list(spec.shape), [int(p) for p in spec.dimension_property]


def png(values: np.ndarray) -> bytes:
    """A camera image (height, width) grey or (height, width, 3) RGB, uint8, as the PNG a Unity
    camera sensor sends: RGB, grey in all three channels (ML-Agents averages them back)."""
    import io

    from PIL import Image

    rgb = values if values.ndim == 3 else np.repeat(values[:, :, None], 3, axis=2)
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb), mode="RGB").save(out, format="PNG", compress_level=1)
    return out.getvalue()


def observation_protos(messages: Messages, name: str, batch: np.ndarray) -> list[Any]:
    """One observation of every agent in ``batch`` (agents, ...): uint8 images as PNG
    (lossless; ML-Agents scales them to [0, 1]), everything else as float32 values, channels
    first (RemoteEnvironment's conversion, done once for the whole batch)."""
    shape, properties = observation_layout(batch[0])
    as_png = batch.dtype == np.uint8 and batch.ndim >= 3
    floats = None if as_png else mlagents_observations(batch)
    protos = []
    for row in range(len(batch)):
        obs = messages.observation(
            shape=shape,
            dimension_properties=properties,
            observation_type=OBSERVATION_TYPE_DEFAULT,
            name=name,
        )
        if floats is None:
            obs.compression_type = COMPRESSION_PNG
            obs.compressed_data = png(batch[row])
        else:
            obs.compression_type = COMPRESSION_NONE
            obs.float_data.data.extend(floats[row].ravel().tolist())
        protos.append(obs)
    return protos


def observation_proto(messages: Messages, name: str, values: np.ndarray) -> Any:
    """One agent's observation (see :func:`observation_protos`)."""
    return observation_protos(messages, name, values[None])[0]


def agent_infos(steps: Steps, messages: Messages) -> tuple[list[Any], list[int]]:
    """The AgentInfoProtos of one round of Steps (agents whose episode ended first, done, then
    the deciding ones) and the deciding agents' ids in the order sent: ML-Agents answers with
    their actions in that order. An ended agent is back among the deciding ones, with its new
    episode's first observation, after the next step (as with RemoteEnvironment)."""
    ended = steps.ended
    observations = {
        name: observation_protos(messages, name, batch)
        for name, batch in steps.observations.items()
    }
    infos = []
    for row in [*np.flatnonzero(ended), *np.flatnonzero(~ended)]:
        done = bool(ended[row])
        info = messages.agent_info(
            reward=float(steps.reward[row]),
            done=done,
            max_step_reached=done and bool(steps.truncated[row]),
            id=int(steps.agents[row]),
            observations=[protos[row] for protos in observations.values()],
        )
        if not done:
            # ML-Agents' masks: True marks an action that can NOT be taken.
            info.action_mask.extend((steps.action_mask[row] == 0).tolist())
        infos.append(info)
    return infos, [int(a) for a in steps.agents[~ended]]


def brain_parameters(name: str, branches: tuple[int, ...], messages: Messages) -> Any:
    """A behaviour's BrainParametersProto: its name and discrete action branches."""
    brain = messages.brain_parameters(brain_name=name, is_training=True)
    brain.action_spec.num_continuous_actions = 0
    brain.action_spec.num_discrete_actions = len(branches)
    brain.action_spec.discrete_branch_sizes.extend(branches)
    return brain


# --- what comes from ML-Agents: side channels ----------------------------------------------------

ENVIRONMENT_PARAMETERS_CHANNEL = uuid.UUID("534c891e-810f-11ea-a9d0-822485860400")
PARAMETER_FLOAT = 0


def side_channel_messages(data: bytes) -> list[tuple[uuid.UUID, bytes]]:
    """ML-Agents' side-channel frames: a channel id (16 bytes, little-endian UUID), a length
    (int32) and that many bytes, repeated."""
    out, offset = [], 0
    while offset < len(data):
        if len(data) - offset < 20:
            raise BridgeError(f"a side-channel frame cut short at byte {offset} of {len(data)}")
        channel = uuid.UUID(bytes_le=bytes(data[offset : offset + 16]))
        (length,) = struct.unpack_from("<i", data, offset + 16)
        offset += 20
        if length < 0 or offset + length > len(data):
            raise BridgeError(
                f"a side-channel frame says {length} bytes, {len(data) - offset} left"
            )
        out.append((channel, bytes(data[offset : offset + length])))
        offset += length
    return out


def environment_parameter(payload: bytes) -> tuple[str, float] | None:
    """An EnvironmentParametersChannel message's float parameter (key, value); None for a
    sampler (curriculum sampling is the scene's, which overtake has not got)."""
    try:
        (size,) = struct.unpack_from("<i", payload, 0)
        key = payload[4 : 4 + size].decode("ascii")
        (kind,) = struct.unpack_from("<i", payload, 4 + size)
        if kind != PARAMETER_FLOAT:
            return None
        (value,) = struct.unpack_from("<f", payload, 8 + size)
    except (struct.error, UnicodeDecodeError) as error:
        raise BridgeError(
            f"an environment parameter message that does not parse: {error}"
        ) from None
    return key, float(value)


def override_value(value: float) -> Scalar:
    """An environment parameter (always a float in ML-Agents) as an overtake override: whole
    numbers as int, so integer settings (traffic.vehicle_count) take them."""
    return int(value) if float(value).is_integer() else value
