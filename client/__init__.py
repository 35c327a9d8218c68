"""What a trainer imports: environment registration, the remote environment (ML-Agents'
low-level API over Zenoh), baseline drivers. Importing it registers ``overtake/Highway-v0``
and ``overtake/RemoteHighway-v0`` without importing the simulator."""

from overtake.client.mlagents.environment import (
    ActionSpec,
    ActionTuple,
    BehaviorSpec,
    DecisionSteps,
    ObservationSpec,
    RemoteEnvironment,
    TerminalSteps,
    UnsupportedRequest,
)
from overtake.client.policies.drivers import RandomDriver, RuleDriver, RuleDriverConfig
from overtake.client.wire.remote_config import RemoteConfig
from overtake.envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments
from overtake.ipc.transport import SecurityConfig

register_environments()

__all__ = [
    "HIGHWAY_ENV_ID",
    "REMOTE_HIGHWAY_ENV_ID",
    "ActionSpec",
    "ActionTuple",
    "BehaviorSpec",
    "DecisionSteps",
    "ObservationSpec",
    "RandomDriver",
    "RemoteConfig",
    "RemoteEnvironment",
    "RuleDriver",
    "RuleDriverConfig",
    "SecurityConfig",
    "TerminalSteps",
    "UnsupportedRequest",
]
