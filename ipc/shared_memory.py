"""The shared-memory channel for a trainer on the server's own host (protocol 1.7).

A server offers a group's trainer a segment (:class:`~overtake.protocol.messages.ShmOffer`: a
name, a nonce, a size, and the layout: where each array of a round lies) in its ``Opened``.
The trainer maps the segment and checks that it holds the nonce: if it does, the two share a
host *and* a ``/dev/shm`` (two containers on one host do not unless told to), and from then on
no round crosses Zenoh: the trainer writes its Actions into the segment and rings the Actions
bell, the server steps, writes the Steps into the segment and rings the Steps bell
(:mod:`overtake.ipc.doorbell`). What is not a round (an error, a round too large for the
segment) still goes over Zenoh, counted in the header and rung, so a waiting trainer knows to
look there. The lease and liveliness stay Zenoh's. Nothing is assumed: a trainer that cannot
map the segment, or finds another nonce or another protocol version's magic there, reads its Steps
from Zenoh.

The segment is a file in ``/dev/shm`` (``OVERTAKE_SHM_DIR`` moves it, for tests), created with
mode 0600 under a name with 128 random bits, so another user's process can neither open it nor
guess it; once the trainer has said whether it reads it, the name goes and only the two
mappings hold it. Its layout:

- a header of :data:`HEADER_BYTES`: the magic ``b"OVTKSHM2"``, the 16-byte nonce, then
  (little-endian) the Steps' write generation (int64), the segment's size (int64), the round
  the Steps answer (int64), the Steps bell and the count of messages sent over Zenoh instead
  (uint32 each, the server's), the Actions bell and the number of actions (uint32, int32), the
  Actions' round and the trainer's step count (int64 each) and the number of cars to retire
  (int32), the trainer's;
- the arrays, each at an offset aligned to :data:`ALIGN` bytes, as the offer's layout places
  them: the Actions' (``actions/agents``, ``actions/actions``, ``actions/retire``, each as long
  as the trainer's cars) and the Steps'.

A Steps write makes the generation odd while it copies and even when done; a reader that sees
another generation before or after its copy has raced a writer and refuses the round
(:class:`~overtake.protocol.errors.DecodeError`) instead of returning torn arrays. The server
writes a group's next round only after its trainer's Actions for this one, and the trainer
writes its next Actions only after that round's Steps, so neither side races the other: the
check is a guard, not a protocol.
"""

from __future__ import annotations

import mmap
import os
import secrets
import struct
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from overtake.protocol.errors import DecodeError
from overtake.protocol.records import WIRE_DTYPES
from overtake.protocol.shm_messages import ACTION_ARRAYS, HEADER_BYTES, NONCE_BYTES

from .doorbell import Bell

MAGIC = b"OVTKSHM2"
ALIGN = 64
# The header's fields after the magic and the nonce, by byte offset (see the module docstring).
GENERATION_OFFSET = 24  # int64: the Steps' write generation (odd while written)
SIZE_OFFSET = 32  # int64
STEPS_ROUND_OFFSET = 40  # int64: the round the Steps in the segment answer
STEPS_BELL_OFFSET = 48  # uint32: rung by the server for every round written or message sent
ZENOH_SENT_OFFSET = 52  # uint32: messages the server sent over Zenoh instead
ACTIONS_BELL_OFFSET = 56  # uint32: rung by the trainer for every Actions written
ACTIONS_COUNT_OFFSET = 60  # int32: how many of actions/agents and actions/actions hold actions
ACTIONS_ROUND_OFFSET = 64  # int64: the round the Actions answer
TRAINER_STEP_OFFSET = 72  # int64: the trainer's step count (Actions.trainer_step)
RETIRE_COUNT_OFFSET = 80  # int32: how many of actions/retire hold cars to retire
# Segment names: this prefix, the creating process's id (so a server can sweep what a dead
# predecessor left), and 128 random bits.
NAME_PREFIX = "overtake-"

Place = tuple[str, int, str, tuple[int, ...]]
"""Where one array lies in a segment: its name, byte offset, wire dtype and shape."""


def shm_dir() -> Path:
    """Where segments live: ``/dev/shm``, or ``OVERTAKE_SHM_DIR``."""
    return Path(os.environ.get("OVERTAKE_SHM_DIR", "/dev/shm"))


def new_name() -> str:
    """A segment name nobody can guess: the prefix, this process's id, 128 random bits."""
    return f"{NAME_PREFIX}{os.getpid()}-{secrets.token_hex(16)}"


def aligned(nbytes: int) -> int:
    return -(-nbytes // ALIGN) * ALIGN


def plan(arrays: Iterable[tuple[str, np.dtype, tuple[int, ...]]]) -> tuple[list[Place], int]:
    """A layout for arrays of these names, dtypes and shapes, one after another past the
    header: their places, and the segment size that holds them."""
    places: list[Place] = []
    offset = HEADER_BYTES
    for name, dtype, shape in arrays:
        places.append((name, offset, np.dtype(dtype).name, tuple(int(d) for d in shape)))
        offset += aligned(int(np.prod(shape, dtype=np.int64)) * np.dtype(dtype).itemsize)
    return places, offset


def channel_plan(cars: int, steps: Mapping[str, np.ndarray]) -> tuple[list[Place], int]:
    """The layout of a channel for a trainer with ``cars`` cars whose Steps' arrays are
    ``steps`` (by the names a layout gives them): the Actions' arrays, then the Steps'."""
    return plan(
        [(name, np.dtype(dtype), (cars,)) for name, dtype in ACTION_ARRAYS]
        + [(name, value.dtype, value.shape) for name, value in steps.items()]
    )


class Segment:
    """One mapped segment: :meth:`create` on the server's side, :meth:`attach` on the
    trainer's. ``close`` unmaps it; ``unlink`` removes its name (the memory goes when the last
    mapping does)."""

    def __init__(self, path: Path, memory: mmap.mmap, nonce: bytes) -> None:
        self.path, self.name, self.nonce = path, path.name, nonce
        self.linked = True
        """whether its name is still in the directory (see :meth:`unlink`)"""
        self._memory: mmap.mmap | None = memory
        self.size = len(memory)
        self._i64 = np.frombuffer(memory, dtype="<i8", count=HEADER_BYTES // 8)
        self._i32 = np.frombuffer(memory, dtype="<i4", count=HEADER_BYTES // 4)
        self._u32 = self._i32.view("<u4")
        self._bells: list[Bell] = []
        self._views: dict[str, np.ndarray] = {}  # by array name, once laid out (lay_out)

    @classmethod
    def create(cls, size: int, name: str | None = None) -> Segment:
        """A new segment of ``size`` bytes (header included), readable by this user only."""
        if size < HEADER_BYTES:
            raise ValueError(f"a segment needs at least {HEADER_BYTES} bytes, got {size}")
        path = shm_dir() / (name or new_name())
        nonce = secrets.token_bytes(NONCE_BYTES)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.ftruncate(fd, size)
            memory = mmap.mmap(fd, size)
        except BaseException:
            os.close(fd)
            path.unlink(missing_ok=True)
            raise
        os.close(fd)
        memory[: GENERATION_OFFSET + 16] = MAGIC + nonce + struct.pack("<qq", 0, size)
        return cls(path, memory, nonce)

    @classmethod
    def attach(cls, name: str, nonce: bytes, size: int) -> Segment:
        """Map the segment ``name`` and check that it is the one offered (its magic, nonce and
        size); raise :class:`OSError` where it cannot be opened, :class:`DecodeError` where
        it is another."""
        if os.sep in name or name.startswith("."):
            raise DecodeError(f"a segment name must be a plain file name, got {name!r}")
        path = shm_dir() / name
        fd = os.open(path, os.O_RDWR)
        try:
            actual = os.fstat(fd).st_size
            if actual != size or size < HEADER_BYTES:
                raise DecodeError(f"segment {name} holds {actual} bytes, the offer said {size}")
            memory = mmap.mmap(fd, size)
        finally:
            os.close(fd)
        header = memory[:GENERATION_OFFSET]
        if header[: len(MAGIC)] != MAGIC:
            memory.close()
            raise DecodeError(
                f"segment {name} begins {header[: len(MAGIC)]!r}, not {MAGIC!r} "
                "(a peer of another protocol version)"
            )
        if header != MAGIC + nonce:
            memory.close()
            raise DecodeError(f"segment {name} is not the one offered (another nonce)")
        return cls(path, memory, nonce)

    @property
    def memory(self) -> mmap.mmap:
        if self._memory is None:
            raise DecodeError(f"segment {self.name} is closed")
        return self._memory

    @property
    def generation(self) -> int:
        return int(self._i64[GENERATION_OFFSET // 8])

    def bell(self, offset: int) -> Bell:
        """The doorbell at ``offset`` of the header (:data:`STEPS_BELL_OFFSET` or
        :data:`ACTIONS_BELL_OFFSET`); released when the segment closes."""
        bell = Bell(self.memory, offset)
        self._bells.append(bell)
        return bell

    @property
    def zenoh_sent(self) -> int:
        """Messages the server sent over Zenoh instead of through the segment (modulo 2**32)."""
        return int(self._u32[ZENOH_SENT_OFFSET // 4])

    def count_zenoh_sent(self) -> None:
        """The server sent a message over Zenoh instead (it rings the Steps bell next)."""
        self._u32[ZENOH_SENT_OFFSET // 4 : ZENOH_SENT_OFFSET // 4 + 1] += 1  # wraps, unwarned

    def lay_out(self, places: Iterable[Place]) -> None:
        """Fix where each array lies (the offer's layout; checked, as it may come from the
        wire): :class:`DecodeError` where a place lies outside the segment, off its alignment,
        or names no wire dtype. The reads and writes below then go through views made once."""
        views: dict[str, np.ndarray] = {}
        for name, offset, dtype_name, shape in places:
            dtype = WIRE_DTYPES.get(dtype_name)
            if dtype is None:
                raise DecodeError(f"array {name!r}: {dtype_name!r} is not a wire dtype")
            count = int(np.prod(shape, dtype=np.int64))
            end = offset + count * dtype.itemsize
            if offset < HEADER_BYTES or offset % ALIGN or end > self.size:
                raise DecodeError(
                    f"array {name!r} of shape {shape} at {offset} lies outside segment "
                    f"{self.name} ({self.size} bytes) or off its {ALIGN}-byte alignment"
                )
            views[name] = np.frombuffer(self.memory, dtype, count, offset).reshape(shape)
        self._views = views

    # --- Steps: the server writes, the trainer reads ------------------------------------------

    def write_steps(self, round_: int, arrays: Mapping[str, np.ndarray]) -> bool:
        """Copy a round's ``arrays`` into their places; False, writing nothing, where one is
        not what its place expects (no place, another dtype or shape: the caller sends the
        round another way)."""
        views = self._views
        for name, value in arrays.items():
            view = views.get(name)
            if view is None or view.shape != value.shape or view.dtype != value.dtype:
                return False
        index = GENERATION_OFFSET // 8
        generation = int(self._i64[index]) + 1
        self._i64[index] = generation  # odd: a write is under way
        for name, value in arrays.items():
            np.copyto(views[name], value)
        self._i64[STEPS_ROUND_OFFSET // 8] = round_
        self._i64[index] = generation + 1
        return True

    def steps_round(self) -> int:
        """The round whose Steps the segment holds (0 before the first write)."""
        return int(self._i64[STEPS_ROUND_OFFSET // 8])

    def read_steps(self, names: Iterable[str]) -> tuple[int, dict[str, np.ndarray]]:
        """The round the segment's Steps answer and copies of the arrays ``names``;
        :class:`DecodeError` where a write is under way or came during the copy."""
        generation = self.generation
        if generation % 2 or generation == 0:
            raise DecodeError(f"segment {self.name} holds no finished write ({generation})")
        round_ = self.steps_round()
        views = self._views
        out = {name: views[name].copy() for name in names}
        if self.generation != generation:
            raise DecodeError(f"segment {self.name} was written while it was read")
        return round_, out

    # --- Actions: the trainer writes, the server reads ----------------------------------------

    def write_actions(
        self,
        round_: int,
        trainer_step: int,
        agents: np.ndarray,
        actions: np.ndarray,
        retire: np.ndarray,
    ) -> None:
        """Write a round's Actions into the layout's Actions arrays; ValueError where there
        are more than the trainer's cars."""
        views = self._views
        capacity = views["actions/agents"].size
        if agents.size != actions.size or agents.size > capacity or retire.size > capacity:
            raise ValueError(
                f"the segment holds actions for at most {capacity} cars, got {agents.size} "
                f"agents, {actions.size} actions and {retire.size} to retire"
            )
        views["actions/agents"][: agents.size] = agents
        views["actions/actions"][: actions.size] = actions
        views["actions/retire"][: retire.size] = retire
        self._i32[ACTIONS_COUNT_OFFSET // 4] = agents.size
        self._i32[RETIRE_COUNT_OFFSET // 4] = retire.size
        self._i64[ACTIONS_ROUND_OFFSET // 8] = round_
        self._i64[TRAINER_STEP_OFFSET // 8] = trainer_step

    def read_actions(self) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray]:
        """Copies of the Actions in the segment: their round, the trainer's step count, the
        agents, their actions and the cars to retire; :class:`DecodeError` where the counts
        are out of range (the trainer's to write, so checked)."""
        views = self._views
        capacity = views["actions/agents"].size
        count = int(self._i32[ACTIONS_COUNT_OFFSET // 4])
        retire_count = int(self._i32[RETIRE_COUNT_OFFSET // 4])
        if not (0 <= count <= capacity and 0 <= retire_count <= capacity):
            raise DecodeError(
                f"segment {self.name} says {count} actions and {retire_count} cars to retire; "
                f"it holds at most {capacity}"
            )
        return (
            int(self._i64[ACTIONS_ROUND_OFFSET // 8]),
            int(self._i64[TRAINER_STEP_OFFSET // 8]),
            views["actions/agents"][:count].copy(),
            views["actions/actions"][:count].copy(),
            views["actions/retire"][:retire_count].copy(),
        )

    def close(self) -> None:
        """Unmap (idempotent). Views into the segment must be gone first."""
        if self._memory is not None:
            memory, self._memory = self._memory, None
            for bell in self._bells:
                bell.release()
            self._bells.clear()
            self._views = {}
            del self._i64, self._i32, self._u32
            memory.close()

    def unlink(self) -> None:
        """Remove the segment's name (idempotent): no process can attach any more, and the
        memory goes when the last process that mapped it unmaps it or ends, however it ends."""
        if self.linked:
            self.path.unlink(missing_ok=True)
            self.linked = False


def sweep_orphans(directory: Path | None = None) -> list[str]:
    """Remove segments whose creating process is gone (a server killed while its trainer
    was too): the ones named with a process id that no longer runs. Returns their names."""
    removed: list[str] = []
    folder = directory or shm_dir()
    try:
        candidates = list(folder.glob(f"{NAME_PREFIX}*"))
    except OSError:
        return removed
    for path in candidates:
        pid_text = path.name[len(NAME_PREFIX) :].split("-", 1)[0]
        if not pid_text.isdigit():
            continue
        try:
            os.kill(int(pid_text), 0)
            continue  # its creator still runs
        except ProcessLookupError:
            pass
        except PermissionError:
            continue  # another user's process: alive, and not ours to judge
        try:
            if path.stat().st_uid == os.getuid():
                path.unlink()
                removed.append(path.name)
        except OSError:
            continue
    return removed
