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
- ``T -> S`` query :class:`CloseRequest`, reply :class:`Ack`.
- ``S -> anyone`` put :class:`WorldFrame` (spectators; dropped under congestion).
- Any request may be answered with :class:`ErrorReply`; a bad :class:`Actions` put is
  answered with an :class:`ErrorReply` put where the trainer's :class:`Steps` would go.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from .errors import DecodeError
from .vocabulary import ACTION_COUNT, ACTION_NAMES

# The wire contract: protocol version (major, minor). A peer of another major version is
# refused; a newer minor may add optional fields, which an older peer ignores.
PROTOCOL_VERSION: tuple[int, int] = (1, 5)
PROTOCOL_HISTORY: tuple[tuple[str, str], ...] = (
    (
        "1.0",
        "First wire protocol: status, open/join, reset, batched actions and steps, close, "
        "world frames for spectators, error replies.",
    ),
    (
        "1.1",
        "World frames carry each agent's reward terms (reward_terms, reward_term_names); "
        "a 1.0 peer's frames decode with none.",
    ),
    (
        "1.2",
        "Actions carry the trainer's step count (trainer_step) and world frames repeat it, so "
        "a spectator's recording shares the trainers' step timeline; world frames carry each "
        "vehicle's half length and width and each agent's heading. Older peers' messages decode "
        "with -1 and None.",
    ),
    (
        "1.3",
        "Actions may take some of the trainer's cars off the road until their arena is reset "
        "(retire: PettingZoo's finished agents); Opened says the server's minor version "
        "(server_minor), so a trainer can tell a server that would ignore retire. A 1.2 "
        "peer's Actions decode with no retired cars, its Opened with server_minor 2.",
    ),
    (
        "1.4",
        "Status replies say what waits in the server's queues (queued_actions, "
        "queued_requests) and how many frames a flood lost at their bounds (dropped_frames); "
        "a request beyond the bound is answered server_busy at once instead of not at all. "
        "A 1.3 server's status decodes with zeros.",
    ),
    (
        "1.5",
        "The behaviour spec states what a consumer needs to read the observations as typed "
        "fields: the road (RoadSpec: lanes and their width), the car (CarSpec: length, width, "
        "the speeds its actions move between) and per observation its named columns (the ego "
        "vector's fields) and its reach (Reach: metres ahead, behind, to the side, range). "
        "config_json stays, a record of the server's configuration that no consumer reads. A "
        "1.4 server's spec decodes without them, and clients refuse it.",
    ),
)
# The minor version whose spec carries the road, the car and the observations' facts.
TYPED_SPEC_SINCE_MINOR = 5

# Sizes beyond these are refused before anything is allocated.
MAX_FRAME_BYTES = 256 * 2**20
MAX_TEXT_CHARS = 65_536
MAX_ARRAY_DIMS = 5
MAX_ARENAS_PER_REQUEST = 4096
MAX_AGENTS_PER_ARENA = 48

NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")

# The dtypes arrays may travel in; always little-endian on the wire.
WIRE_DTYPES: dict[str, np.dtype] = {
    name: np.dtype(name).newbyteorder("<")
    for name in ("bool", "int8", "uint8", "int32", "int64", "float32", "float64")
}

Scalar = bool | int | float | str


def check_name(what: str, value: str) -> None:
    """Names end up inside Zenoh key expressions: letters, digits, ``_ . -`` only."""
    if not NAME_PATTERN.fullmatch(value):
        raise DecodeError(
            f"{what} must be 1-64 characters of letters, digits, '_', '.' or '-', got {value!r}"
        )


def check_array(what: str, value: np.ndarray, dtype: str, shape: tuple[int | None, ...]) -> None:
    """``value`` has ``dtype`` and ``shape`` (None matches any length on that axis)."""
    if value.dtype != WIRE_DTYPES[dtype]:
        raise DecodeError(f"{what} must be {dtype}, got {value.dtype}")
    if value.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(value.shape, shape, strict=True)
    ):
        wanted = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise DecodeError(f"{what} must have shape {wanted}, got {value.shape}")


def check_range(what: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise DecodeError(f"{what} must be from {low} to {high}, got {value}")


def _values_equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        )
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_values_equal(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return True  # NaN
    return type(a) is type(b) and a == b


@dataclass(frozen=True, eq=False)
class Part:
    """A frozen record that checks itself; equality compares arrays by value and dtype."""

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Raise :class:`DecodeError` naming what is wrong. Subclasses add their rules."""

    @classmethod
    def trusted(cls, **values: Any) -> Any:
        """Build without :meth:`check`: only for records a side builds from its own arrays of
        the right dtypes and shapes, on a hot path (the server's Steps). Decoding always
        checks."""
        record = object.__new__(cls)
        for name, value in values.items():
            object.__setattr__(record, name, value)
        return record

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and all(
            _values_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self)
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Message(Part):
    """A top-level message; ``TYPE`` is its tag on the wire."""

    TYPE: ClassVar[str] = ""


# --- specs -----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Reach(Part):
    """How far an observation sees, in metres from the car's centre along the road (ahead,
    behind), across it (to either side) and along its rays (range); 0 where it does not
    apply."""

    ahead_m: float = 0.0
    behind_m: float = 0.0
    side_m: float = 0.0
    range_m: float = 0.0

    def check(self) -> None:
        for name in ("ahead_m", "behind_m", "side_m", "range_m"):
            value = getattr(self, name)
            if not 0.0 <= value < 1e6:
                raise DecodeError(f"reach {name} must be from 0 to 1e6 m, got {value}")


@dataclass(frozen=True, eq=False)
class RoadSpec(Part):
    """The road the agents drive: its lanes."""

    lane_count: int
    lane_width_m: float

    def check(self) -> None:
        check_range("lane count", self.lane_count, 1, 64)
        if not 0.0 < self.lane_width_m < 100.0:
            raise DecodeError(f"lane width must be from 0 to 100 m, got {self.lane_width_m}")


@dataclass(frozen=True, eq=False)
class CarSpec(Part):
    """An agent's car: its body and the speeds its actions move between."""

    length_m: float
    width_m: float
    min_speed_kmh: float
    max_speed_kmh: float

    def check(self) -> None:
        if not (0.0 < self.length_m < 100.0 and 0.0 < self.width_m < 100.0):
            raise DecodeError(
                f"car length and width must be from 0 to 100 m, got {self.length_m} and "
                f"{self.width_m}"
            )
        if not 0.0 <= self.min_speed_kmh <= self.max_speed_kmh < 1e4:
            raise DecodeError(
                f"car speeds must be 0 <= min <= max, got {self.min_speed_kmh} and "
                f"{self.max_speed_kmh} km/h"
            )


@dataclass(frozen=True, eq=False)
class ObservationSpec(Part):
    """One observation of one agent: a Box of ``shape`` and ``dtype`` within [low, high], the
    names of its last axis' entries where they are named (``columns``: the ego vector's fields)
    and how far it sees (``reach``; None for what sees nothing of the road, as the action
    stack)."""

    name: str
    shape: tuple[int, ...]
    dtype: str
    low: np.ndarray
    high: np.ndarray
    columns: tuple[str, ...] = field(default=(), metadata={"since": 5})
    reach: Reach | None = field(default=None, metadata={"since": 5})

    def check(self) -> None:
        check_name("observation name", self.name)
        if self.dtype not in WIRE_DTYPES:
            raise DecodeError(
                f"observation {self.name!r} dtype must be one of "
                f"{sorted(WIRE_DTYPES)}, got {self.dtype!r}"
            )
        if not 1 <= len(self.shape) <= MAX_ARRAY_DIMS - 1 or min(self.shape) < 1:
            raise DecodeError(
                f"observation {self.name!r} shape must have 1 to "
                f"{MAX_ARRAY_DIMS - 1} positive sizes, got {self.shape}"
            )
        for bound in ("low", "high"):
            check_array(
                f"observation {self.name!r} {bound}", getattr(self, bound), self.dtype, self.shape
            )
        if self.columns and len(self.columns) != self.shape[-1]:
            raise DecodeError(
                f"observation {self.name!r} names {len(self.columns)} columns for a last axis "
                f"of {self.shape[-1]}"
            )


@dataclass(frozen=True, eq=False)
class BehaviourSpec(Part):
    """Everything a client needs to rebuild the in-process spaces (ML-Agents' BehaviorSpec)."""

    name: str
    preset: str
    observations: tuple[ObservationSpec, ...]
    action_branches: tuple[int, ...]
    action_names: tuple[str, ...]
    reward_terms: tuple[str, ...]
    metric_fields: tuple[str, ...]
    decision_period_s: float
    max_episode_steps: int
    agents_per_arena: int
    config_json: str
    """the server's resolved configuration, a record (run records, checkpoints): what a
    consumer reads of it is in the typed fields"""
    road: RoadSpec | None = field(default=None, metadata={"since": 5})
    car: CarSpec | None = field(default=None, metadata={"since": 5})

    def check(self) -> None:
        names = [o.name for o in self.observations]
        if not names or len(set(names)) != len(names):
            raise DecodeError(f"observation names must be distinct and at least one, got {names}")
        if self.action_branches != (ACTION_COUNT,):
            raise DecodeError(
                f"action branches must be ({ACTION_COUNT},), got {self.action_branches}"
            )
        if len(self.action_names) != ACTION_COUNT:
            raise DecodeError(f"expected {ACTION_COUNT} action names, got {self.action_names}")
        check_range("agents per arena", self.agents_per_arena, 1, MAX_AGENTS_PER_ARENA)
        check_range("max episode steps", self.max_episode_steps, 1, 2**62)
        if not self.decision_period_s > 0:
            raise DecodeError(f"decision period must be > 0 s, got {self.decision_period_s}")

    def observation(self, name: str) -> ObservationSpec:
        for spec in self.observations:
            if spec.name == name:
                return spec
        raise KeyError(name)

    def has(self, name: str) -> bool:
        """Whether the agents observe ``name``."""
        return any(spec.name == name for spec in self.observations)


# --- requests and replies -------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class StatusRequest(Message):
    TYPE: ClassVar[str] = "status_request"


@dataclass(frozen=True, eq=False)
class GroupStatus(Part):
    """One group of arenas: opened by one request, stepped together in one numpy pass."""

    group: int
    preset: str
    arenas: tuple[int, ...]
    agents_per_arena: int
    trainers: tuple[str, ...]
    rounds: int
    rounds_per_s: float
    agent_steps_per_s: float
    late_agents: int


@dataclass(frozen=True, eq=False)
class StatusReply(Message):
    TYPE: ClassVar[str] = "status"
    server: str
    package_version: str
    max_arenas: int
    arenas_used: int
    step_deadline_s: float
    uptime_s: float
    groups: tuple[GroupStatus, ...]
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
    trainer: str
    preset: str
    overrides: dict[str, Scalar]
    arenas: int
    agents_per_arena: int
    claim: int
    seed: int | None

    def check(self) -> None:
        check_name("trainer", self.trainer)
        check_name("preset", self.preset)
        check_range("arenas", self.arenas, 1, MAX_ARENAS_PER_REQUEST)
        check_range("agents per arena", self.agents_per_arena, 1, MAX_AGENTS_PER_ARENA)
        check_range("claimed agents per arena", self.claim, 1, self.agents_per_arena)
        if self.seed is not None:
            check_range("seed", self.seed, 0, 2**63 - 1)


@dataclass(frozen=True, eq=False)
class JoinRequest(Message):
    """Claim ``agents`` free agent slots of an existing arena and drive them on its road."""

    TYPE: ClassVar[str] = "join"
    trainer: str
    arena: int
    agents: int

    def check(self) -> None:
        check_name("trainer", self.trainer)
        check_range("arena", self.arena, 0, 2**62)
        check_range("agents", self.agents, 1, MAX_AGENTS_PER_ARENA)


@dataclass(frozen=True, eq=False)
class Steps(Message):
    """What a group's step (or reset) produced for one trainer's agents.

    ``agents`` are ids within the group (arena index in the group × agents per arena + slot).
    An agent with ``terminated`` or ``truncated`` (ML-Agents' interrupted) ended its episode
    here, and ``observations`` are its last; it is reset on the group's next step, whose row
    for it has the new episode's first observation, reward 0 and both flags false (Gymnasium's
    next-step autoreset). ``metrics`` are each agent's episode so far. ``late`` marks agents
    whose action missed the deadline: ``action_applied`` shows what was done instead.
    """

    TYPE: ClassVar[str] = "steps"
    server: str
    group: int
    round: int
    agents: np.ndarray  # int32 (k,)
    observations: dict[str, np.ndarray]  # name -> (k, ...)
    reward: np.ndarray  # float64 (k,)
    terminated: np.ndarray  # bool (k,)
    truncated: np.ndarray  # bool (k,)
    action_applied: np.ndarray  # int64 (k,), -1 where nothing was applied (reset)
    late: np.ndarray  # bool (k,)
    action_mask: np.ndarray  # int8 (k, ACTION_COUNT)
    reward_terms: np.ndarray  # float64 (k, terms)
    metrics: np.ndarray  # float64 (k, metric fields)

    def check(self) -> None:
        check_name("server", self.server)
        k = self.agents.shape[0] if self.agents.ndim == 1 else -1
        check_array("agents", self.agents, "int32", (None,))
        for name, value in self.observations.items():
            check_name("observation name", name)
            if value.ndim < 1 or value.shape[0] != k:
                raise DecodeError(
                    f"observation {name!r} must have {k} rows (one per agent), "
                    f"got shape {value.shape}"
                )
        check_array("reward", self.reward, "float64", (k,))
        check_array("terminated", self.terminated, "bool", (k,))
        check_array("truncated", self.truncated, "bool", (k,))
        check_array("action_applied", self.action_applied, "int64", (k,))
        check_array("late", self.late, "bool", (k,))
        check_array("action_mask", self.action_mask, "int8", (k, ACTION_COUNT))
        check_array("reward_terms", self.reward_terms, "float64", (k, None))
        check_array("metrics", self.metrics, "float64", (k, None))

    @property
    def ended(self) -> np.ndarray:
        return self.terminated | self.truncated


@dataclass(frozen=True, eq=False)
class Opened(Message):
    """Reply to open or join: where the agents are, the spec, and the first observations."""

    TYPE: ClassVar[str] = "opened"
    server: str
    group: int
    arenas: tuple[int, ...]  # the group's arena ids (server-wide), by index in the group
    ticket: bytes  # proves later requests come from this trainer
    spec: BehaviourSpec
    steps: Steps  # this trainer's agents and their current observations
    # The minor protocol version the server speaks; a server of 1.2 or older sends none (2).
    server_minor: int = field(default=2, metadata={"since": 3})

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
    trainer: str
    ticket: bytes
    group: int
    arenas: tuple[int, ...]
    seeds: tuple[int | None, ...]

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
    trainer: str
    ticket: bytes
    group: int
    round: int
    agents: np.ndarray  # int32 (k,), distinct
    actions: np.ndarray  # int64 (k,) in [0, ACTION_COUNT)
    # The trainer's count of environment steps when it chose these actions (-1: not given):
    # world frames repeat it so that recordings of the road share the trainer's timeline.
    trainer_step: int = field(default=-1, metadata={"since": 2})
    # int32 (m,), distinct, none of them in ``agents``: cars of this trainer that leave the
    # road before this round and stay off (not restarted) until their arena is reset.
    retire: np.ndarray | None = field(default=None, metadata={"since": 3})

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
    trainer: str
    ticket: bytes
    group: int


@dataclass(frozen=True, eq=False)
class Ack(Message):
    TYPE: ClassVar[str] = "ack"
    message: str


@dataclass(frozen=True, eq=False)
class ErrorReply(Message):
    """A refusal: ``code`` is a :class:`~overtake.protocol.errors.ProtocolError` code.

    ``group`` names the group a refused :class:`Actions` put was for (None for a request's
    reply, or when the put could not be read): a trainer raises only errors about a group it
    is stepping, so nobody can break its loop by sending garbage in its name.
    """

    TYPE: ClassVar[str] = "error"
    code: str
    message: str
    group: int | None = None


@dataclass(frozen=True, eq=False)
class WorldFrame(Message):
    """A spectator's view of one arena: every vehicle, and each agent's latest observation.

    Vehicle arrays are (V,) over the arena's slots (agents first); ``kind`` is the traffic
    behaviour index, or ``agent_kind`` for agents. Positions are metres along the road and
    from its right edge.
    """

    TYPE: ClassVar[str] = "world"
    server: str
    group: int
    arena: int
    round: int
    sim_time_s: float
    lane_count: int
    lane_width_m: float
    agent_kind: int
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
        Ack,
        ErrorReply,
        WorldFrame,
    )
}
