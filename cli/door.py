"""The one door every ``overtake-*`` command goes through: its command line parsed into its
typed configuration, the configuration checked, its ``main`` run, and what a user sees at the
edges the same in every command.

- **One line for what cannot be done**: a ``CommandError`` (and the library's typed
  errors below it: a usage error, a recording sink that cannot open, a checkpoint that is not
  one), a ``ProtocolError`` (the network or a server refused) or a
  ``ValueError`` (a bad override) ends the command with ``<prog>: <message>`` and status 1.
  Anything else is a bug and keeps its traceback.
- **Outputs checked before the work**: a configuration that writes files says which (a
  method ``output_paths()`` returning an ``Output`` for each); one that cannot be
  written (a folder where a file goes, a file where a folder must be made, no permission, a
  Rerun viewer nobody runs) is refused in one line before anything runs, not after an hour of
  episodes.
- **A closed pipe ends it quietly** (``overtake-train --help | head -1``): no traceback, status
  141 as a Unix tool killed by SIGPIPE.
- **The library's INFO lines** go to stderr, unless the caller configured logging itself.

Library functions and the commands' ``main(config)`` raise typed exceptions, because they are
called from Python too (tests, notebooks) and exiting there would end the caller; only the door
exits. It sits below every package that has a command (server, client, trainers, viz) and
imports only the protocol's errors.
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import urllib.parse
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from overtake.protocol import ProtocolError

ConfigT = TypeVar("ConfigT")
ResultT = TypeVar("ResultT")

CLOSED_PIPE_STATUS = 128 + 13  # a Unix tool killed by SIGPIPE


class CommandError(Exception):
    """What a user asked cannot be done; the message says what was expected and what came.
    The door prints it as ``<prog>: <message>``."""


@dataclass(frozen=True)
class Output:
    """A file (or, with ``folder``, a folder) a command will write, or the Rerun viewer it
    streams to (``viewer_url``), and the flag naming it."""

    flag: str
    path: Path | None  # None: not asked for
    folder: bool = False
    viewer_url: str | None = None


def check_outputs(outputs: Iterable[Output]) -> None:
    """Refuse, in one line naming the flag, a path that cannot be written: the nearest
    existing ancestor must be a folder this process may write in, a file must not be a folder
    already, nor a folder a file."""
    for output in outputs:
        flag, path = output.flag, output.path
        if output.viewer_url is not None:
            check_viewer(output.viewer_url)
        if path is None:
            continue
        if not output.folder and path.is_dir():
            raise CommandError(f"{flag} {path}: a folder is there, expected a file")
        if output.folder and path.exists() and not path.is_dir():
            raise CommandError(f"{flag} {path}: a file is there, expected a folder")
        ancestor = path.parent
        while not ancestor.exists() and ancestor != ancestor.parent:
            ancestor = ancestor.parent
        if not ancestor.is_dir():
            raise CommandError(f"{flag} {path}: {ancestor} is a file, not a folder")
        if not os.access(ancestor, os.W_OK | os.X_OK):
            raise CommandError(f"{flag} {path}: no permission to write in {ancestor}")
        if path.exists() and not path.is_dir() and not os.access(path, os.W_OK):
            raise CommandError(f"{flag} {path}: the file is there and not writable")


VIEWER_PROBE_TIMEOUT_S = 2.0


def check_viewer(url: str) -> None:
    """Refuse at once a Rerun viewer address nothing listens on: Rerun's gRPC sink would drop
    everything logged without a word and stall the process's exit for seconds retrying."""
    address = urllib.parse.urlsplit(url.replace("rerun+", "", 1))
    try:
        host, port = address.hostname, address.port
    except ValueError:
        host = port = None
    if host is None or port is None:
        raise CommandError(
            f"--viewer-url {url}: expected rerun+http://HOST:PORT/proxy, the address a Rerun "
            "viewer's gRPC server listens on"
        )
    try:
        socket.create_connection((host, port), timeout=VIEWER_PROBE_TIMEOUT_S).close()
    except OSError as error:
        raise CommandError(
            f"no Rerun viewer listens at {url} ({error.strerror or error}): start one with "
            "`.venv/bin/rerun` first, or record to a file (--sink file)"
        ) from None


def enter(
    prog: str,
    parse: Callable[[list[str] | None], ConfigT],
    main: Callable[[ConfigT], ResultT],
    argv: list[str] | None = None,
) -> ResultT:
    """``main(parse(argv))`` through the door (see the module's docstring)."""
    if not logging.getLogger().handlers:
        logging.basicConfig(format="%(asctime)s %(levelname)s %(name)s: %(message)s")
        logging.getLogger("overtake").setLevel(logging.INFO)
    try:
        try:
            config = parse(argv)
            outputs = getattr(config, "output_paths", None)
            if outputs is not None:
                check_outputs(outputs())
            return main(config)
        finally:
            # What was printed reaches the pipe now, inside the door, not at the interpreter's
            # exit where a closed pipe would print a traceback nobody can catch.
            sys.stdout.flush()
    except BrokenPipeError:
        _quiet_stdout()
        sys.exit(CLOSED_PIPE_STATUS)
    except (CommandError, ProtocolError, ValueError) as error:
        sys.exit(f"{prog}: {error}")


def _quiet_stdout() -> None:
    """Point stdout at /dev/null: the reader is gone, and Python's own flush at exit must not
    fail again."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):
        pass
    finally:
        os.close(devnull)
