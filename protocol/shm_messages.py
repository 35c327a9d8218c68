"""The message part of the shared-memory channel (protocol 1.7; the mechanism is described in
:mod:`overtake.ipc.shared_memory`): the server's offer of a segment, with the layout of
every array a round writes there. Once the trainer reads the segment, a round sends nothing
over Zenoh: the layout is sent once, here, and each round is a ring of a doorbell.

Protocol 1.6 sent a ``StepsInShm`` notice over Zenoh each round instead; a 1.7 trainer
declines a 1.6 offer (it has no layout), a 1.6 trainer refuses a 1.7 segment by its magic, and
both fall back to Steps over Zenoh."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from .channel_offers import ChannelOffer
from .errors import DecodeError
from .records import (
    MAX_ARRAY_DIMS,
    MAX_FRAME_BYTES,
    WIRE_DTYPES,
    Part,
    check_name,
    check_range,
)
from .rows import OBSERVATION_PREFIX, ROW_ARRAY_NAMES

# The segment's sizes the offer is checked against (the segment itself, its header's fields and
# its mapping: overtake.ipc.shared_memory, which reads these from here).
NONCE_BYTES = 16
HEADER_BYTES = 128
# The Actions' arrays in a layout, each as long as the trainer's cars.
ACTION_ARRAYS = (
    ("actions/agents", "int32"),
    ("actions/actions", "int64"),
    ("actions/retire", "int32"),
)

# The Steps fields a layout names, besides ``obs/<observation name>``: a round's row arrays.
STEPS_ARRAYS = ROW_ARRAY_NAMES
ACTION_ARRAY_NAMES = tuple(name for name, _ in ACTION_ARRAYS)


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
        elif self.name not in STEPS_ARRAYS and self.name not in ACTION_ARRAY_NAMES:
            raise DecodeError(
                f"array name must be one of {', '.join(STEPS_ARRAYS + ACTION_ARRAY_NAMES)} or "
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
class ShmOffer(ChannelOffer):
    """A segment the server writes a group's Steps into, for a trainer on its host."""

    TRANSPORT: ClassVar[str] = "shm"

    name: str  # the segment's file name in /dev/shm (overtake-<pid>-<128 random bits>)
    nonce: bytes  # 16 random bytes the segment begins with (after its magic)
    size_bytes: int  # the segment's size, header included
    # Where each array of a round lies: the Actions' (actions/...) and the Steps'. A 1.6
    # server sends none (its segment holds Steps only, and a 1.7 trainer does not read it).
    layout: tuple[ShmArray, ...] = field(default=(), metadata={"since": 7})

    def check(self) -> None:
        check_name("segment name", self.name)
        if len(self.nonce) != NONCE_BYTES:
            raise DecodeError(f"a segment nonce is {NONCE_BYTES} bytes, got {len(self.nonce)}")
        check_range("segment size", self.size_bytes, HEADER_BYTES, MAX_FRAME_BYTES)
        if not self.layout:
            return
        names = [a.name for a in self.layout]
        missing = [n for n in (*ACTION_ARRAY_NAMES, *STEPS_ARRAYS) if n not in names]
        if missing or len(set(names)) != len(names):
            raise DecodeError(
                f"a segment's layout names each Actions and Steps array once; missing "
                f"{missing}, got {names}"
            )
