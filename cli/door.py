"""The one door every ``overtake-*`` command goes through: a :class:`Command` built from the
command's typed configuration and its ``main`` (the parser, from the configuration's fields and
docstrings; the entry point ``[project.scripts]`` names, ``module:COMMAND.run``; its signals),
and what a user sees at the edges the same in every command.

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
- **Freed memory kept for reuse** (:mod:`.allocator`): every command's rounds and updates
  allocate the same blocks again and again, and reuse their pages instead of faulting in
  fresh ones (unless the user set glibc's own variables).
- **SIGINT and SIGTERM** stop it as the command chose (:data:`Stopping`): as Python does, as
  an interrupt ended in one line, or as a stop ``main`` finishes (a second signal ends it).

Library functions and the commands' ``main(config)`` raise typed exceptions, because they are
called from Python too (tests, notebooks) and exiting there would end the caller; only the door
exits. It sits below every package that has a command (server, client, trainers, viz) and
imports only the protocol's errors (and :mod:`.allocator`, which imports nothing of ours).
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import threading
import urllib.parse
from collections.abc import Callable, Iterable
from dataclasses import KW_ONLY, dataclass
from pathlib import Path
from typing import Any, Generic, Literal, TypeVar, cast

from overtake.protocol import ProtocolError

from .allocator import keep_freed_memory

ConfigT = TypeVar("ConfigT")
ResultT = TypeVar("ResultT")

CLOSED_PIPE_STATUS = 128 + 13  # a Unix tool killed by SIGPIPE


class CommandError(Exception):
    """What a user asked cannot be done; the message says what was expected and what came.
    The door prints it as ``<prog>: <message>``."""


class UsageError(CommandError, ValueError):
    """The user asked for something that cannot be done (an option out of range, options that
    exclude each other, a file that is not what the option names); the message says what was
    expected and what came.

    Library functions and the commands' ``main(config)`` raise it rather than exit, because
    they are called from Python too (tests, benchmarks, notebooks) and exiting there would end
    the caller; only a command exits, through the door, which prints ``<prog>: <message>``."""


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


Stopping = Literal["default", "interrupt", "event"]
"""How SIGINT and SIGTERM stop a command: ``default`` as Python does (Ctrl-C raises
KeyboardInterrupt; SIGTERM ends the process); ``interrupt``: both raise the command's
``stop_error`` where ``main`` is (KeyboardInterrupt unless it names another), which ends the
command in one line (``<prog>: stopped; <hint>``); ``event``: the first sets the
``stop`` event ``main(config, stop)`` was given (it finishes what is under way), the second
ends the command at once in one line."""


@dataclass(frozen=True)
class Command(Generic[ConfigT, ResultT]):
    """One ``overtake-*`` command, built from its typed configuration and its ``main``: the
    parser (tyro, from the configuration's fields and their docstrings), the entry point
    (:meth:`run`, what ``[project.scripts]`` names: ``module:COMMAND.run``) and the door around
    ``main`` (see the module's docstring)."""

    prog: str
    config: type[ConfigT]
    main: Callable[..., ResultT]
    """``main(config)``, or ``main(config, stop)`` where :attr:`stopping` is ``event``"""
    _: KW_ONLY
    description: str | None = None
    """what ``--help`` says first; None: the configuration's docstring"""
    report: Callable[[ConfigT, ResultT], int | None] | None = None
    """what the command prints of ``main``'s result; the status to exit with (None: 0)"""
    default: Callable[[list[str]], ConfigT] | None = None
    """the defaults a command line starts from, read from it (a preset's training); None:
    the configuration's own"""
    prefixed: bool = False
    """whether a nested configuration's options keep its name (``--recording.sink``); the
    commands' options are flat (``--sink``) unless two sections share a name"""
    stopping: Stopping = "default"
    stopped_hint: str = ""
    """what the one line says after ``stopped`` (how to go on)"""
    on_stop: Callable[[str], None] | None = None
    """with ``event``: called with the signal's name when the stop is asked (say what happens,
    end waits that would hold it)"""
    stop_error: Callable[[str], BaseException] = lambda _signal: KeyboardInterrupt()
    """with ``interrupt``: what a signal (named) raises where ``main`` is, so that ``main``
    can say so to its peer on the way out"""
    log_format: str = "%(asctime)s %(levelname)s %(name)s: %(message)s"

    def parse(self, argv: list[str] | None = None) -> ConfigT:
        """The configuration a command line asks for (``sys.argv`` when ``argv`` is None);
        what :meth:`run` runs, and what the documentation's checks parse commands with."""
        import tyro

        args = sys.argv[1:] if argv is None else list(argv)
        config = tyro.cli(
            self.config,
            args=args,
            default=self.default(args) if self.default is not None else None,
            config=() if self.prefixed else (tyro.conf.OmitArgPrefixes,),
            prog=self.prog,
            description=self.description,
        )
        return cast(ConfigT, config)  # tyro types a result with no default as optional

    def run(self, argv: list[str] | None = None) -> None:
        """The command: ``main(parse(argv))`` through the door, ending the process with the
        report's status."""
        keep_freed_memory()
        stop = threading.Event()
        previous = self._handle_signals(stop)
        try:
            status = self._through_door(argv, stop)
        finally:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
        if status:
            sys.exit(status)

    def _handle_signals(self, stop: threading.Event) -> dict[int, Any]:
        if self.stopping == "default" or threading.current_thread() is not threading.main_thread():
            return {}

        def interrupt(signum: int, _frame: Any) -> None:
            raise self.stop_error(signal.Signals(signum).name)

        def ask_to_stop(signum: int, _frame: Any) -> None:
            name = signal.Signals(signum).name
            if stop.is_set():  # asked twice: stop now
                raise SystemExit(self._stopped_line(f"at once by a second {name}"))
            stop.set()
            if self.on_stop is not None:
                self.on_stop(name)

        handler = interrupt if self.stopping == "interrupt" else ask_to_stop
        return {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}

    def _through_door(self, argv: list[str] | None, stop: threading.Event) -> int:
        """``main(parse(argv))`` and its report; the status to exit with."""
        if not logging.getLogger().handlers:
            logging.basicConfig(format=self.log_format)
            logging.getLogger("overtake").setLevel(logging.INFO)
        try:
            try:
                config = self.parse(argv)
                outputs = getattr(config, "output_paths", None)
                if outputs is not None:
                    check_outputs(outputs())
                result = (
                    self.main(config, stop=stop) if self.stopping == "event" else self.main(config)
                )
                if self.report is None:
                    return 0
                return self.report(config, result) or 0
            finally:
                # What was printed reaches the pipe now, inside the door, not at the interpreter's
                # exit where a closed pipe would print a traceback nobody can catch.
                sys.stdout.flush()
        except BrokenPipeError:
            _quiet_stdout()
            return CLOSED_PIPE_STATUS
        except (CommandError, ProtocolError, ValueError) as error:
            sys.exit(f"{self.prog}: {error}")
        except KeyboardInterrupt:
            if self.stopping != "interrupt":
                raise
            sys.exit(self._stopped_line())

    def _stopped_line(self, how: str = "") -> str:
        line = f"{self.prog}: stopped" + (f" {how}" if how else "")
        return f"{line}; {self.stopped_hint}" if self.stopped_hint else line


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
