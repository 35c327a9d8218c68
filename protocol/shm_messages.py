"""The messages of Steps through shared memory (protocol 1.6; the mechanism is described in
:mod:`overtake.protocol.shared_memory`): the server's offer of a segment, and the notice that
replaces a Steps frame once the trainer reads its Steps from the segment."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from .errors import DecodeError
from .records import (
    MAX_ARRAY_DIMS,
    MAX_FRAME_BYTES,
    WIRE_DTYPES,
    Message,
    Part,
    check_name,
    check_range,
)
from .shared_memory import HEADER_BYTES, NONCE_BYTES

# The Steps fields a notice may name, besides ``obs/<observation name>``.
STEPS_ARRAYS = (
    "agents",
    "reward",
    "terminated",
    "truncated",
    "action_applied",
    "late",
    "action_mask",
    "reward_terms",
    "metrics",
)
OBSERVATION_PREFIX = "obs/"


@dataclass(frozen=True, eq=False)
class ShmOffer(Part):
    """A segment the server writes a group's Steps into, for a trainer on its host."""

    name: str  # the segment's file name in /dev/shm (overtake-<pid>-<128 random bits>)
    nonce: bytes  # 16 random bytes the segment begins with (after its magic)
    size_bytes: int  # the segment's size, header included

    def check(self) -> None:
        check_name("segment name", self.name)
        if len(self.nonce) != NONCE_BYTES:
            raise DecodeError(f"a segment nonce is {NONCE_BYTES} bytes, got {len(self.nonce)}")
        check_range("segment size", self.size_bytes, HEADER_BYTES, MAX_FRAME_BYTES)


@dataclass(frozen=True, eq=False)
class ShmArray(Part):
    """Where one array of a Steps lies in the segment."""

    name: str  # a Steps field (agents, reward, ...) or obs/<observation name>
    offset: int  # bytes from the segment's start
    dtype: str  # a wire dtype
    shape: tuple[int, ...]  # the array's shape

    def check(self) -> None:
        observation = self.name.removeprefix(OBSERVATION_PREFIX)
        if observation != self.name:
            check_name("observation name", observation)
        elif self.name not in STEPS_ARRAYS:
            raise DecodeError(
                f"array name must be one of {', '.join(STEPS_ARRAYS)} or "
                f"{OBSERVATION_PREFIX}<observation>, got {self.name!r}"
            )
        if self.dtype not in WIRE_DTYPES:
            raise DecodeError(f"array {self.name!r}: {self.dtype!r} is not a wire dtype")
        check_range("array offset", self.offset, HEADER_BYTES, MAX_FRAME_BYTES)
        if len(self.shape) > MAX_ARRAY_DIMS or any(
            not 0 <= d <= MAX_FRAME_BYTES for d in self.shape
        ):
            raise DecodeError(f"array {self.name!r}: bad shape {self.shape}")


@dataclass(frozen=True, eq=False)
class StepsInShm(Message):
    """A Steps written into the group's segment: the server sends this instead of the
    :class:`~overtake.protocol.messages.Steps` frame to a trainer that said (``Actions.shm``)
    it reads the segment. The trainer rebuilds the Steps from the arrays named here."""

    TYPE: ClassVar[str] = "steps_shm"
    server: str  # the server that stepped
    group: int  # the group stepped
    round: int  # the round the arrays answer, as Steps.round
    generation: int  # the segment write holding them (even; see overtake.protocol.shared_memory)
    arrays: tuple[ShmArray, ...]  # every Steps array, where it lies

    def check(self) -> None:
        check_name("server", self.server)
        check_range("generation", self.generation, 2, 2**62)
        names = [a.name for a in self.arrays]
        missing = [n for n in STEPS_ARRAYS if n not in names]
        if missing or len(set(names)) != len(names):
            raise DecodeError(
                f"a notice names each Steps array once; missing {missing}, got {names}"
            )
