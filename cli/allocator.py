"""The C allocator's settings for an overtake process: freed memory kept for the next round.

Every command applies them at its door (:class:`~.door.Command`), and ``overtake-train``'s
``main`` does too when called as a function. A training update allocates and frees the same
few tensors of a few MiB every time (a convolution's output, its gradient, a layout copy), and
a simulator's round the same numpy temporaries (a sensor's rays, a camera's frame). glibc's
``malloc`` serves a block of 128 KiB or more (its starting threshold) with a fresh ``mmap``
and gives it back with ``munmap`` when it is freed, and trims the top of its heap once 128 KiB
lie free there, so every update touches new pages, and the kernel zeroes each on its first
touch: measured here (ho2018's proposed network, eight members, one thread), 430,000 page
faults in 400 updates, and an update 1.6x slower than with the memory kept
(bench/RESULTS.md, "The allocator"); a server's simulation of 64 arenas 20-25% slower than the
same rounds in a process whose allocator had settled (bench/RESULTS.md, "Remote stepping").
glibc raises its threshold by itself after the first such free, but only to that block's
size, and larger blocks come later.

:func:`keep_freed_memory` sets the threshold to glibc's largest (32 MiB: bigger blocks, such as
a replay memory, are still mapped on their own) and the trim threshold out of reach, so freed
blocks stay in the heap and are reused. The process's peak memory is what it was (its largest
working set); what it no longer gives back is the difference between that peak and what is
live. Numbers are unchanged: this moves no arithmetic.

A user who sets glibc's own variables (``MALLOC_MMAP_THRESHOLD_``, ``MALLOC_TRIM_THRESHOLD_``,
or ``glibc.malloc.*`` in ``GLIBC_TUNABLES``) keeps them: the settings here are not applied over
theirs.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

# mallopt's parameters (glibc's malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024
"""glibc's largest mmap threshold on a 64-bit system (``DEFAULT_MMAP_THRESHOLD_MAX``)."""
TRIM_THRESHOLD_BYTES = 2**31 - 1
"""Free memory at the heap's top is given back beyond this: in practice never."""

_USER_SETTINGS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")


def _user_set_malloc() -> bool:
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    return any(name in os.environ for name in _USER_SETTINGS) or "glibc.malloc." in tunables


def keep_freed_memory() -> bool:
    """Keep freed blocks of up to 32 MiB in this process's heap for reuse (module docstring).
    Returns whether the settings were applied: False off Linux, on a C library other than
    glibc, or where the user set glibc's own variables."""
    if not sys.platform.startswith("linux") or _user_set_malloc():
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # musl (Alpine) has no mallopt
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    return bool(
        mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
        and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    )
