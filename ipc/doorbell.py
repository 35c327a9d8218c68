"""A doorbell between two processes that share a mapping: a 32-bit word that one side
increments and the other sleeps on, through Linux's futex (protocol 1.7's shared-memory
channel, :mod:`overtake.ipc.shared_memory`).

Why a futex: the fastest samplers block rather than spin (EnvPool sleeps on a futex-backed
semaphore, TorchRL's inference server on a process-shared one): on 2 cores a spinning waiter
takes the core its peer needs (spinning measured a 16 ms worst case here). A futex needs no
file descriptor to pass and no name to clean up: the word lives in the segment, and the
kernel keys its waiters by the page, so two processes mapping the segment meet on it. The
call goes through ctypes, which releases the GIL while the process sleeps.

A waiter may spin first (``spin_s``), yielding the core at every look (``sched_yield``, which
also lets the process's other threads take the GIL), and sleeps only when that time is up.
Measured on this project's 2-core VM: a process that slept between two rounds computes the
next one about 45% slower than one that did not (min2018, one arena: 1.17 against 0.80 ms for
the same simulation step), as a sleeping virtual CPU loses its caches; a short spin keeps the
CPU warm across a lock-step round trip, and a spinner that yields cannot hold a core another
process needs (the unbounded spin that measured a 16 ms worst case did not yield).

Each word has one writer (the server rings the Steps bell, the trainer the Actions bell), so
a plain increment is enough; a waiter compares the word with the value it last saw, and the
kernel checks that comparison again atomically before it sleeps, so no ring is lost between
a look and a sleep. Every wait has a timeout: the waiter looks at the lease and its deadline
between slices, as it did between Zenoh messages.

On x86-64 (and aarch64, where the syscall orders the writes before it) the data written
before a ring is visible to a waiter that sees the ring; the segment's generation check stays
as the guard against a torn read.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
import os
import platform
import sys
import time

import numpy as np

# The futex syscall's number per machine (linux/unistd.h); elsewhere there is no doorbell, and
# the server offers no shared-memory channel.
_SYS_FUTEX = {"x86_64": 202, "amd64": 202, "aarch64": 98, "arm64": 98}.get(
    platform.machine().lower()
)
_FUTEX_WAIT = 0  # not FUTEX_PRIVATE_FLAG: the waiters are in another process
_FUTEX_WAKE = 1
_WAKE_ALL = 2**31 - 1


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _syscall() -> ctypes._CFuncPtr | None:  # type: ignore[name-defined]
    if not sys.platform.startswith("linux") or _SYS_FUTEX is None:
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
    except OSError:
        return None
    function = libc.syscall
    function.restype = ctypes.c_long
    return function


_CALL = _syscall()
AVAILABLE = _CALL is not None
"""Whether this machine has the futex doorbell (Linux on x86-64 or aarch64)."""


class Bell:
    """The 32-bit word at ``offset`` of ``memory`` (4-byte aligned), as a doorbell.

    Holds a view into the mapping: :meth:`release` it before the mapping is closed."""

    def __init__(self, memory: mmap.mmap, offset: int) -> None:
        if not AVAILABLE:
            raise OSError(f"no futex doorbell on {sys.platform}/{platform.machine()}")
        if offset % 4:
            raise ValueError(f"a bell's word must be 4-byte aligned, got offset {offset}")
        self._word: np.ndarray | None = np.frombuffer(memory, dtype="<u4", count=1, offset=offset)
        self._address = ctypes.c_void_p(self._word.ctypes.data)

    @property
    def value(self) -> int:
        """How many times it has rung (modulo 2**32)."""
        assert self._word is not None, "the bell was released"
        return int(self._word[0])

    def ring(self) -> None:
        """Count a ring and wake whoever sleeps on it (this side is the word's only writer)."""
        assert self._word is not None, "the bell was released"
        self._word += 1  # an array's add: wraps at 2**32 unwarned, as the waiter expects
        self.wake()

    def wake(self) -> None:
        """Wake whoever sleeps on the bell without ringing it: they look again at what they
        wait for (a lost server, say), and sleep again if nothing changed."""
        assert _CALL is not None
        _CALL(_SYS_FUTEX, self._address, _FUTEX_WAKE, _WAKE_ALL, None, None, 0)

    def wait(self, seen: int, timeout_s: float, spin_s: float = 0.0) -> int:
        """Wait while the bell still shows ``seen``, at most ``timeout_s``: spinning (and
        yielding) for the first ``spin_s`` of it, then asleep. Its value now (``seen`` again
        after a timeout, an interrupt, or a :meth:`wake` without a ring)."""
        assert _CALL is not None and self._word is not None, "the bell was released"
        word = self._word
        if int(word[0]) != seen:
            return int(word[0])
        if spin_s > 0:
            started = time.perf_counter()
            spin_s = min(spin_s, timeout_s)
            while time.perf_counter() - started < spin_s:
                os.sched_yield()
                if int(word[0]) != seen:
                    return int(word[0])
            timeout_s -= spin_s
        timeout_s = max(timeout_s, 0.0)
        whole = int(timeout_s)
        span = _Timespec(whole, int((timeout_s - whole) * 1e9))
        # EAGAIN (the word changed before the kernel looked), ETIMEDOUT and EINTR all end the
        # sleep: the caller looks at the word either way.
        _CALL(
            _SYS_FUTEX,
            self._address,
            _FUTEX_WAIT,
            ctypes.c_uint32(seen),
            ctypes.byref(span),
            None,
            0,
        )
        return int(self._word[0])

    def release(self) -> None:
        """Drop the view into the mapping (idempotent), so that the mapping can close."""
        self._word = None
