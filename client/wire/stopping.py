"""Ending a process's waits on servers when it is asked to stop.

A command's stop signal (overtake-train's SIGTERM: docker compose stop, a cluster's
preemption) lets the step under way finish. On a healthy server that takes milliseconds; on a
server that is gone the step would wait for its round (``RemoteConfig.step_timeout_s``) and
then for a server to reopen its arenas on (``reconnect_timeout_s``). :func:`interrupt_waits`
makes every open connection give up such waits, with
:class:`~overtake.protocol.errors.Interrupted`; the caller ends as a stopped run does.
"""

from __future__ import annotations

import threading
import weakref

INTERRUPT_AFTER_S = 1.0
"""Once a stop is asked for, a wait for a round ends when it has lasted this long since it began
(a round on a healthy server comes within milliseconds)."""
_STOP_EVENTS: weakref.WeakSet[threading.Event] = weakref.WeakSet()


def stop_event() -> threading.Event:
    """A connection's event, set by :func:`interrupt_waits`."""
    event = threading.Event()
    _STOP_EVENTS.add(event)
    return event


def interrupt_waits() -> None:
    """End the long waits of every open connection of this process: a wait for a round that
    has lasted :data:`INTERRUPT_AFTER_S`, or for a lost server to come back, raises
    :class:`~overtake.protocol.errors.Interrupted`. A round under way on a healthy server
    still completes."""
    for event in list(_STOP_EVENTS):
        event.set()
