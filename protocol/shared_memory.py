"""Steps through shared memory, for a trainer on the server's own host (protocol 1.6).

A server offers a group's trainer a segment (:class:`~overtake.protocol.messages.ShmOffer`: a
name, a nonce, a size) in its ``Opened``. The trainer maps the segment and checks that it holds
the nonce: if it does, the two share a host *and* a ``/dev/shm`` (two containers on one host do
not), and from then on the server writes each round's arrays into the segment and sends only a
small :class:`~overtake.protocol.messages.StepsInShm` notice over Zenoh: where each array lies
(:class:`~overtake.protocol.messages.ShmArray`) and the write's generation. Nothing is assumed:
a trainer that cannot map the segment, or finds another nonce there, keeps reading its Steps
from Zenoh.

The segment is a file in ``/dev/shm`` (``OVERTAKE_SHM_DIR`` moves it, for tests), created with
mode 0600 under a name with 128 random bits, so another user's process can neither open it nor
guess it. Its layout:

- a header of :data:`HEADER_BYTES`: the magic ``b"OVTKSHM1"``, the 16-byte nonce, the write
  generation (int64 at :data:`GENERATION_OFFSET`), the segment's size;
- the arrays of the latest write, each at an offset aligned to :data:`ALIGN` bytes.

A write makes the generation odd while it copies and even (the value the notice carries) when
done; a reader that sees another generation before or after its copy has raced a writer and
refuses the round (:class:`~overtake.protocol.errors.DecodeError`) instead of returning torn
arrays. The server writes a group's next round only after its trainer's actions for this one,
so a reader that copies out before acting never races: the check is a guard, not a protocol.
"""

from __future__ import annotations

import mmap
import os
import secrets
import struct
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from .errors import DecodeError
from .records import WIRE_DTYPES

MAGIC = b"OVTKSHM1"
NONCE_BYTES = 16
GENERATION_OFFSET = 24
HEADER_BYTES = 64
ALIGN = 64
# Segment names: this prefix, the creating process's id (so a server can sweep what a dead
# predecessor left), and 128 random bits.
NAME_PREFIX = "overtake-"


def shm_dir() -> Path:
    """Where segments live: ``/dev/shm``, or ``OVERTAKE_SHM_DIR``."""
    return Path(os.environ.get("OVERTAKE_SHM_DIR", "/dev/shm"))


def new_name() -> str:
    """A segment name nobody can guess: the prefix, this process's id, 128 random bits."""
    return f"{NAME_PREFIX}{os.getpid()}-{secrets.token_hex(16)}"


def aligned(nbytes: int) -> int:
    return -(-nbytes // ALIGN) * ALIGN


def layout_bytes(arrays: Iterable[tuple[np.dtype, tuple[int, ...]]]) -> int:
    """The segment size that holds arrays of these dtypes and shapes, header included."""
    return HEADER_BYTES + sum(
        aligned(int(np.prod(shape, dtype=np.int64)) * dtype.itemsize) for dtype, shape in arrays
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
        self._generation = np.frombuffer(memory, dtype="<i8", count=1, offset=GENERATION_OFFSET)

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
        memory[:HEADER_BYTES] = MAGIC + nonce + struct.pack("<qq", 0, size) + bytes(24)
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
        return int(self._generation[0])

    def write(
        self, arrays: Mapping[str, np.ndarray]
    ) -> tuple[int, list[tuple[str, int, str, tuple[int, ...]]]] | None:
        """Copy ``arrays`` into the segment; return the write's generation and where each
        lies (name, offset, dtype, shape), or None where they do not fit (the caller sends
        them another way)."""
        places: list[tuple[str, int, str, tuple[int, ...]]] = []
        offset = HEADER_BYTES
        for name, value in arrays.items():
            places.append((name, offset, value.dtype.name, tuple(value.shape)))
            offset += aligned(value.nbytes)
        if offset > self.size:
            return None
        generation = self.generation + 1
        self._generation[0] = generation  # odd: a write is under way
        buffer = self.memory
        for (_, start, _, _), value in zip(places, arrays.values(), strict=True):
            view = np.frombuffer(buffer, dtype=value.dtype, count=value.size, offset=start)
            view[:] = value.reshape(-1)
        self._generation[0] = generation + 1
        return generation + 1, places

    def read(
        self, generation: int, places: Iterable[tuple[str, int, str, tuple[int, ...]]]
    ) -> dict[str, np.ndarray]:
        """Copies of the arrays of write ``generation``; :class:`DecodeError` where a place
        lies outside the segment, a dtype is not a wire dtype, or the write is not (or no
        longer) the one named."""
        if self.generation != generation:
            raise DecodeError(
                f"segment {self.name} holds write {self.generation}, the notice names {generation}"
            )
        buffer = self.memory
        out: dict[str, np.ndarray] = {}
        for name, offset, dtype_name, shape in places:
            dtype = WIRE_DTYPES.get(dtype_name)
            if dtype is None:
                raise DecodeError(f"array {name!r}: {dtype_name!r} is not a wire dtype")
            count = int(np.prod(shape, dtype=np.int64))
            if offset < HEADER_BYTES or offset + count * dtype.itemsize > self.size:
                raise DecodeError(
                    f"array {name!r} of shape {shape} at {offset} lies outside segment "
                    f"{self.name} ({self.size} bytes)"
                )
            out[name] = (
                np.frombuffer(buffer, dtype=dtype, count=count, offset=offset).reshape(shape).copy()
            )
        if self.generation != generation:
            raise DecodeError(f"segment {self.name} was written while it was read")
        return out

    def close(self) -> None:
        """Unmap (idempotent). Views into the segment must be gone first."""
        if self._memory is not None:
            memory, self._memory = self._memory, None
            del self._generation
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
