"""The command layer's errors: what a request that cannot be carried out raises, and the one
place where a command turns such errors into ``<prog>: <message>`` and a non-zero exit status.

Library functions and the commands' ``main(config)`` raise typed exceptions, because they are
called from Python too (tests, benchmarks, notebooks) and exiting there would end the caller.
Only a command's ``cli()`` exits, through :func:`run_command`.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import TypeVar

from overtake.protocol import ProtocolError
from overtake.viz.recording import RecordingError

ConfigT = TypeVar("ConfigT")
ResultT = TypeVar("ResultT")


class UsageError(ValueError):
    """The user asked for something that cannot be done (an option out of range, options that
    exclude each other, a file that is not what the option names); the message says what was
    expected and what came."""


def run_command(prog: str, main: Callable[[ConfigT], ResultT], config: ConfigT) -> ResultT:
    """``main(config)``, exiting with ``<prog>: <message>`` (status 1) if it raises a
    :class:`UsageError`, a :class:`~overtake.protocol.ProtocolError` (the network or a server
    refused), a :class:`~overtake.viz.recording.RecordingError` (a Rerun sink could not be
    opened) or another ``ValueError`` (such as the in-process simulator's ``ConfigError`` for
    a bad override); anything else is a bug and keeps its traceback.

    The library's lines at INFO and above go to stderr (Python's default shows warnings only):
    which way a trainer's rounds go and why, a busy server, where a recording goes. A caller
    that configured logging itself keeps its own."""
    if not logging.getLogger().handlers:
        logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        logging.getLogger("overtake").setLevel(logging.INFO)
    try:
        return main(config)
    except (UsageError, ProtocolError, RecordingError, ValueError) as error:
        sys.exit(f"{prog}: {error}")
