"""The messages trainers and simulator servers exchange, as small frozen dataclasses.

Each message validates itself on construction (:meth:`Message.check`), so a message that
exists is well formed, whether it was built here or decoded from the wire. Arrays are numpy
arrays of a fixed dtype; the first axis of every per-agent array is the agents the message
is about (``agents``).

Conversations (``T`` a trainer, ``S`` a server; queries are answered, puts are not):

- ``T -> S`` query :class:`StatusRequest`, reply :class:`StatusReply`.
- ``T -> S`` query :class:`OpenRequest` or :class:`JoinRequest`, reply :class:`Opened`.
- ``T -> S`` query :class:`ResetRequest`, reply :class:`Steps`.
- ``T -> S`` put :class:`Actions`; ``S -> T`` put :class:`Steps` when the group has stepped.
- ``T -> S`` query :class:`SnapshotRequest`, reply :class:`GroupState`; query
  :class:`RestoreRequest`, reply :class:`Steps` (1.8: an exact resume of a remote run).
- ``T -> S`` query :class:`CloseRequest`, reply :class:`Ack`.
- ``S -> anyone`` put :class:`WorldFrame` (spectators; dropped under congestion).
- Any request may be answered with :class:`ErrorReply`; a bad :class:`Actions` put is
  answered with an :class:`ErrorReply` put where the trainer's :class:`Steps` would go.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .channel_offers import ChannelOffer, check_transports
from .errors import DecodeError
from .records import (
    MAX_AGENTS_PER_ARENA,
    MAX_ARENAS_PER_REQUEST,
    MAX_ARRAY_DIMS,
    MAX_FRAME_BYTES,
    MAX_TEXT_CHARS,
    NAME_PATTERN,
    WIRE_DTYPES,
    Message,
    Part,
    Scalar,
    check_array,
    check_name,
    check_names,
    check_range,
)
from .rows import Rows
from .shm_messages import ShmArray, ShmOffer
from .specs import BehaviourSpec, CarSpec, ColumnScale, ObservationSpec, Reach, RoadSpec
from .state_messages import GroupState, RestoreRequest, SnapshotRequest
from .version import (
    AS_RECORDED_SINCE_MINOR,
    PROTOCOL_HISTORY,
    PROTOCOL_VERSION,
    REQUESTED_READING_SINCE_MINOR,
    TYPED_SPEC_SINCE_MINOR,
)
from .vocabulary import ACTION_COUNT, ACTION_NAMES, TRANSLATIONS

__all__ = [
    "ACTION_COUNT",
    "ACTION_NAMES",
    "AS_RECORDED_SINCE_MINOR",
    "MAX_AGENTS_PER_ARENA",
    "MAX_ARENAS_PER_REQUEST",
    "MAX_ARRAY_DIMS",
    "MAX_FRAME_BYTES",
    "MAX_TEXT_CHARS",
    "MESSAGE_TYPES",
    "NAME_PATTERN",
    "PROTOCOL_HISTORY",
    "PROTOCOL_VERSION",
    "REQUESTED_READING_SINCE_MINOR",
    "TYPED_SPEC_SINCE_MINOR",
    "WIRE_DTYPES",
    "Ack",
    "Actions",
    "BehaviourSpec",
    "CarSpec",
    "ChannelOffer",
    "CloseRequest",
    "ColumnScale",
    "ErrorReply",
    "GroupState",
    "GroupStatus",
    "JoinRequest",
    "Message",
    "ObservationSpec",
    "OpenRequest",
    "Opened",
    "Part",
    "Reach",
    "ResetRequest",
    "RestoreRequest",
    "RoadSpec",
    "Scalar",
    "ShmArray",
    "ShmOffer",
    "SnapshotRequest",
    "StatusReply",
    "StatusRequest",
    "Steps",
    "Translation",
    "WorldFrame",
    "check_array",
    "check_name",
    "check_range",
]


# Observations an open request may name (a simulation has a handful of sensors).
MAX_OBSERVATIONS = 16
# Ego vector fields an open request may name (vocabulary.EGO_FIELDS has eleven).
MAX_EGO_FIELDS = 32


@dataclass(frozen=True, eq=False)
class Translation(Part):
    """A configuration in another simulator's own words (highway-env's ``config`` dict on its
    scenes), which the server translates into its settings beside its scene, as the
    in-process simulator does; what it does not take is refused (bad_config) in its words."""

    source: str  # whose words: one of vocabulary.TRANSLATIONS (highway-env)
    config_json: str  # the configuration as that simulator takes it, as a JSON object

    def check(self) -> None:
        if self.source not in TRANSLATIONS:
            raise DecodeError(
                f"translation source must be one of {list(TRANSLATIONS)}, got {self.source!r}"
            )


@dataclass(frozen=True, eq=False)
class StatusRequest(Message):
    TYPE: ClassVar[str] = "status_request"


@dataclass(frozen=True, eq=False)
class GroupStatus(Part):
    """One group of arenas: opened by one request, stepped together in one numpy pass."""

    group: int  # the group's id on its server
    preset: str  # the preset its arenas run
    arenas: tuple[int, ...]  # its arena ids (server-wide)
    agents_per_arena: int  # car slots per arena
    trainers: tuple[str, ...]  # the trainers driving cars in it
    rounds: int  # rounds stepped since it opened
    rounds_per_s: float  # its recent rate of rounds
    agent_steps_per_s: float  # rounds per second × its driven cars
    late_agents: int  # agents given the default action at a deadline so far


@dataclass(frozen=True, eq=False)
class StatusReply(Message):
    TYPE: ClassVar[str] = "status"
    server: str  # the server's name (its key expressions')
    package_version: str  # overtake's version on the server
    max_arenas: int  # arenas it may hold at once (--max-arenas)
    arenas_used: int  # arenas open now
    step_deadline_s: float  # how long a group waits for late trainers once one has acted
    uptime_s: float  # seconds since the server started
    groups: tuple[GroupStatus, ...]  # every open group
    queued_actions: int = field(default=0, metadata={"since": 4})
    """Actions frames received and not yet handled, over all trainers' keys."""
    queued_requests: int = field(default=0, metadata={"since": 4})
    """Requests received and not yet answered."""
    dropped_frames: int = field(default=0, metadata={"since": 4})
    """Frames dropped at the queues' bounds since the server started (a flood's)."""

    def check(self) -> None:
        check_name("server", self.server)

    @property
    def arenas_free(self) -> int:
        return self.max_arenas - self.arenas_used


@dataclass(frozen=True, eq=False)
class OpenRequest(Message):
    """Open ``arenas`` new arenas of ``preset`` with ``overrides``; claim ``claim`` agents of each.

    Arena ``i`` is reset with seed ``seed + i`` (None: fresh entropy). Agents not claimed stay
    off the road until a trainer joins them (:class:`JoinRequest`).
    """

    TYPE: ClassVar[str] = "open"
    trainer: str  # the trainer's name (its steps' key)
    preset: str  # a preset the server knows (min2018, ho2018, fayjie2018)
    # dotted field name -> value, checked against the preset's typed configuration
    overrides: dict[str, Scalar]
    arenas: int  # how many arenas to open, stepped together as one group
    agents_per_arena: int  # car slots per arena
    claim: int  # the slots this trainer drives; the rest wait for JoinRequest
    seed: int | None  # arena i is reset with seed + i; None: fresh entropy
    # The trainer can read Steps from a shared-memory segment (it may share the server's host).
    # A 1.10 trainer lists "shm" in transports and says so here too, for older servers.
    shm: bool = field(default=False, metadata={"since": 6})
    # The configuration an episode record was made on (its header's, as JSON; empty: none):
    # the server builds that simulator again from its settings' history, or refuses.
    as_recorded: str = field(default="", metadata={"since": 9})
    # The channels besides Zenoh the trainer can take its rounds through, the one it prefers
    # first (channel_offers: "shm"); the server offers at most one of them (Opened.offer).
    transports: tuple[str, ...] = field(default=(), metadata={"since": 10})
    # What the trainer reads (none: all); the others' sensors go off; one not on: bad_config.
    observations: tuple[str, ...] = field(default=(), metadata={"since": 10})
    # The ego vector's fields the trainer reads, in order (vocabulary.EGO_FIELDS; none: the
    # preset's); an unknown one, or an ego vector that is off: bad_config.
    ego_fields: tuple[str, ...] = field(default=(), metadata={"since": 11})
    # A configuration in another simulator's words, translated by the server into settings
    # under ``overrides`` (None: none); ``preset`` names the scene it is written for.
    translation: Translation | None = field(default=None, metadata={"since": 11})

    def check(self) -> None:
        check_name("trainer", self.trainer)
        check_name("preset", self.preset)
        check_transports(self.transports)
        check_names("observation", self.observations, MAX_OBSERVATIONS)
        check_names("ego field", self.ego_fields, MAX_EGO_FIELDS)
        check_range("arenas", self.arenas, 1, MAX_ARENAS_PER_REQUEST)
        check_range("agents per arena", self.agents_per_arena, 1, MAX_AGENTS_PER_ARENA)
        check_range("claimed agents per arena", self.claim, 1, self.agents_per_arena)
        if self.seed is not None:
            check_range("seed", self.seed, 0, 2**63 - 1)

    @property
    def wanted_transports(self) -> tuple[str, ...]:
        """The channels besides Zenoh the trainer can take, preferred first; a trainer of 1.9
        or older lists none and says only whether it reads shared memory (``shm``)."""
        return self.transports or (("shm",) if self.shm else ())


@dataclass(frozen=True, eq=False)
class JoinRequest(Message):
    """Claim ``agents`` free agent slots of an existing arena and drive them on its road."""

    TYPE: ClassVar[str] = "join"
    trainer: str  # the joining trainer's name
    arena: int  # the arena's id (server-wide)
    agents: int  # free slots to claim

    def check(self) -> None:
        check_name("trainer", self.trainer)
        check_range("arena", self.arena, 0, 2**62)
        check_range("agents", self.agents, 1, MAX_AGENTS_PER_ARENA)


@dataclass(frozen=True, eq=False)
class Steps(Message, Rows):
    """What a group's step (or reset) produced for one trainer's agents: their :class:`Rows`
    (:mod:`.rows` names them), with the server, group and round they answer.

    ``agents`` are ids within the group (arena index in the group × agents per arena + slot).
    An agent with ``terminated`` or ``truncated`` (ML-Agents' interrupted) ended its episode
    here, and ``observations`` are its last; it is reset on the group's next step, whose row
    for it has the new episode's first observation, reward 0 and both flags false (Gymnasium's
    next-step autoreset). ``metrics`` are each agent's episode so far. ``late`` marks agents
    whose action missed the deadline: ``action_applied`` shows what was done instead.
    """

    TYPE: ClassVar[str] = "steps"
    server: str  # the server that stepped
    group: int  # the group stepped
    round: int  # the round these rows answer; the next Actions answer it

    def check(self) -> None:
        check_name("server", self.server)
        self.check_rows()


@dataclass(frozen=True, eq=False)
class Opened(Message):
    """Reply to open or join: where the agents are, the spec, and the first observations."""

    TYPE: ClassVar[str] = "opened"
    server: str  # the server that opened (or holds) the group
    group: int  # the group's id on that server
    arenas: tuple[int, ...]  # the group's arena ids (server-wide), by index in the group
    ticket: bytes  # proves later requests come from this trainer
    spec: BehaviourSpec  # what the agents observe and do
    steps: Steps  # this trainer's agents and their current observations
    # The minor protocol version the server speaks; a server of 1.2 or older sends none (2).
    server_minor: int = field(default=2, metadata={"since": 3})
    # A segment this trainer may read its Steps from, when it asked (OpenRequest.shm) and the
    # group is its alone (filled beside ``offer`` for 1.9 trainers); None: Steps over Zenoh.
    shm: ShmOffer | None = field(default=None, metadata={"since": 6})
    # The channel this trainer's rounds may take instead of Zenoh frames, one of those its
    # OpenRequest.transports listed, tagged with its transport; None: Steps come over Zenoh.
    offer: ChannelOffer | None = field(default=None, metadata={"since": 10})

    def check(self) -> None:
        check_name("server", self.server)
        if not 16 <= len(self.ticket) <= 64:
            raise DecodeError(f"ticket must be 16-64 bytes, got {len(self.ticket)}")
        if not self.arenas:
            raise DecodeError("an opened group has at least one arena, got none")


@dataclass(frozen=True, eq=False)
class ResetRequest(Message):
    """Start new episodes in ``arenas`` (indices in the group); reply: :class:`Steps`.

    In an arena this trainer shares with others only its own agents restart (the road goes on
    for the others) and the seed is ignored.
    """

    TYPE: ClassVar[str] = "reset"
    trainer: str  # the trainer's name
    ticket: bytes  # the ticket of the group's Opened
    group: int  # the group's id
    arenas: tuple[int, ...]  # indices in the group, distinct
    seeds: tuple[int | None, ...]  # one per arena; None: fresh entropy

    def check(self) -> None:
        check_name("trainer", self.trainer)
        if len(self.seeds) != len(self.arenas):
            raise DecodeError(
                f"expected one seed per arena ({len(self.arenas)}), got {len(self.seeds)}"
            )
        if len(set(self.arenas)) != len(self.arenas):
            raise DecodeError(f"arenas must be distinct, got {list(self.arenas)}")
        for seed in self.seeds:
            if seed is not None:
                check_range("seed", seed, 0, 2**63 - 1)


@dataclass(frozen=True, eq=False)
class Actions(Message):
    """One trainer's actions for its agents in one group, answering step ``round``."""

    TYPE: ClassVar[str] = "actions"
    trainer: str  # the trainer's name; must match the key it is put on
    ticket: bytes  # the ticket of the group's Opened
    group: int  # the group's id
    round: int  # the Steps round these actions answer
    agents: np.ndarray  # int32 (k,), distinct
    actions: np.ndarray  # int64 (k,) in [0, ACTION_COUNT)
    # The trainer's count of environment steps when it chose these actions (-1: not given):
    # world frames repeat it so that recordings of the road share the trainer's timeline.
    trainer_step: int = field(default=-1, metadata={"since": 2})
    # int32 (m,), distinct, none of them in ``agents``: cars of this trainer that leave the
    # road before this round and stay off (not restarted) until their arena is reset.
    retire: np.ndarray | None = field(default=None, metadata={"since": 3})
    # Whether the trainer reads this group's segment (ShmOffer). Sent over Zenoh, these say
    # False (1.7: a trainer that reads it writes its Actions there); a 1.6 trainer said True
    # to get its Steps through a 1.6 segment.
    shm: bool = field(default=False, metadata={"since": 6})

    def check(self) -> None:
        check_name("trainer", self.trainer)
        if self.retire is not None:
            check_array("retire", self.retire, "int32", (None,))
            if np.unique(self.retire).size != self.retire.size:
                raise DecodeError(f"retire must be distinct, got {self.retire.tolist()}")
            both = np.intersect1d(self.retire, self.agents)
            if both.size:
                raise DecodeError(
                    f"agents {both.tolist()} both act and retire; a retired car takes no action"
                )
        if self.trainer_step < -1:
            raise DecodeError(
                f"trainer_step must be >= 0 (or -1: not given), got {self.trainer_step}"
            )
        check_array("agents", self.agents, "int32", (None,))
        check_array("actions", self.actions, "int64", (self.agents.shape[0],))
        if self.actions.size and (self.actions.min() < 0 or self.actions.max() >= ACTION_COUNT):
            bad = self.actions[(self.actions < 0) | (self.actions >= ACTION_COUNT)]
            raise DecodeError(
                f"actions must be in [0, {ACTION_COUNT}) "
                f"({', '.join(ACTION_NAMES)}), got {bad.tolist()}"
            )
        if np.unique(self.agents).size != self.agents.size:
            raise DecodeError(f"agents must be distinct, got {self.agents.tolist()}")


@dataclass(frozen=True, eq=False)
class CloseRequest(Message):
    """Leave a group: its arenas are freed, or this trainer's cars leave the shared ones."""

    TYPE: ClassVar[str] = "close"
    trainer: str  # the trainer's name
    ticket: bytes  # the ticket of the group's Opened
    group: int  # the group's id


@dataclass(frozen=True, eq=False)
class Ack(Message):
    TYPE: ClassVar[str] = "ack"
    message: str  # what was done


@dataclass(frozen=True, eq=False)
class ErrorReply(Message):
    """A refusal: ``code`` is a :class:`~overtake.protocol.errors.ProtocolError` code.

    ``group`` names the group a refused :class:`Actions` put was for (None for a request's
    reply, or when the put could not be read): a trainer raises only errors about a group it
    is stepping, so nobody can break its loop by sending garbage in its name.
    """

    TYPE: ClassVar[str] = "error"
    code: str  # e.g. unknown_preset, bad_config, server_full, bad_action, server_busy
    message: str  # what was expected and what came
    group: int | None = None  # the group a refused Actions put was for; None for a request


@dataclass(frozen=True, eq=False)
class WorldFrame(Message):
    """A spectator's view of one arena: every vehicle, and each agent's latest observation.

    Vehicle arrays are (V,) over the arena's slots (agents first); ``kind`` is the traffic
    behaviour index, or ``agent_kind`` for agents. Positions are metres along the road and
    from its right edge.
    """

    TYPE: ClassVar[str] = "world"
    server: str  # the server stepping the arena
    group: int  # the arena's group
    arena: int  # the arena's id (server-wide)
    round: int  # the group's round
    sim_time_s: float  # simulated seconds since the arena's episode began
    lane_count: int  # lanes of the road
    lane_width_m: float  # width of each lane
    agent_kind: int  # the kind value that marks an agent's car
    agent_active: np.ndarray  # bool (N,)
    x_m: np.ndarray  # float64 (V,)
    y_m: np.ndarray  # float64 (V,)
    speed_mps: np.ndarray  # float32 (V,)
    kind: np.ndarray  # int8 (V,)
    active: np.ndarray  # bool (V,)
    observations: dict[str, np.ndarray]  # name -> (N, ...)
    reward: np.ndarray  # float64 (N,)
    action_applied: np.ndarray  # int64 (N,)
    # Since 1.1 (a 1.0 peer's frames decode with these defaults):
    reward_terms: np.ndarray | None = field(default=None, metadata={"since": 1})  # (N, terms)
    # the names of reward_terms' columns
    reward_term_names: tuple[str, ...] = field(default=(), metadata={"since": 1})
    # The step count the arena's trainer sent with its last actions (-1: none sent one).
    trainer_step: int = field(default=-1, metadata={"since": 2})
    half_length_m: np.ndarray | None = field(default=None, metadata={"since": 2})  # float32 (V,)
    half_width_m: np.ndarray | None = field(default=None, metadata={"since": 2})  # float32 (V,)
    # Each agent's heading, radians from the road's direction, left positive (its LIDAR turns
    # with it while it changes lanes).
    agent_heading_rad: np.ndarray | None = field(default=None, metadata={"since": 2})  # f32 (N,)

    def check(self) -> None:
        check_name("server", self.server)
        v = self.x_m.shape[0] if self.x_m.ndim == 1 else -1
        n = self.agent_active.shape[0] if self.agent_active.ndim == 1 else -1
        check_array("agent_active", self.agent_active, "bool", (None,))
        check_array("x_m", self.x_m, "float64", (None,))
        check_array("y_m", self.y_m, "float64", (v,))
        check_array("speed_mps", self.speed_mps, "float32", (v,))
        check_array("kind", self.kind, "int8", (v,))
        check_array("active", self.active, "bool", (v,))
        check_array("reward", self.reward, "float64", (n,))
        check_array("action_applied", self.action_applied, "int64", (n,))
        if self.reward_terms is not None:
            check_array(
                "reward_terms", self.reward_terms, "float64", (n, len(self.reward_term_names))
            )
        elif self.reward_term_names:
            raise DecodeError(
                f"reward_term_names {list(self.reward_term_names)} came without reward_terms"
            )
        for name in self.reward_term_names:
            check_name("reward term name", name)
        if (self.half_length_m is None) != (self.half_width_m is None):
            raise DecodeError("half_length_m and half_width_m must come together or not at all")
        if self.half_length_m is not None and self.half_width_m is not None:
            check_array("half_length_m", self.half_length_m, "float32", (v,))
            check_array("half_width_m", self.half_width_m, "float32", (v,))
        if self.agent_heading_rad is not None:
            check_array("agent_heading_rad", self.agent_heading_rad, "float32", (n,))
        for name, value in self.observations.items():
            check_name("observation name", name)
            if value.ndim < 1 or value.shape[0] != n:
                raise DecodeError(f"observation {name!r} must have {n} rows, got {value.shape}")


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (
        StatusRequest,
        StatusReply,
        OpenRequest,
        JoinRequest,
        Opened,
        ResetRequest,
        Steps,
        Actions,
        CloseRequest,
        SnapshotRequest,
        GroupState,
        RestoreRequest,
        Ack,
        ErrorReply,
        WorldFrame,
    )
}
