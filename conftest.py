"""The documentation's examples as tests (Sybil): every Python block of README.md and docs/*.md
runs, and every shell block's commands are checked.

- A Python block runs in its page's namespace, in order. ``tcp/127.0.0.1:7447`` (the default
  endpoint the pages use) is replaced by a simulator server this session starts on a free
  port, when a block needs one. ``<!-- skip: next if(...) -->`` skips one whose condition holds
  (Sybil's skip directive; used for what needs an optional install).
- A shell block's commands are checked without running them: an ``overtake-*`` command is
  parsed by its own command line parser (its ``COMMAND.parse``), a Python example's by its
  ``Args``; a ``scripts/*.sh`` must exist, be executable and parse (``bash -n``); ``python -m
  MODULE`` must find the module. A command of another program (docker, zenohd, ray, iptables)
  needs the block marked ``<!-- docs: needs WHAT -->`` (what CI does not have), and its
  overtake commands are still parsed.
- A block marked ``<!-- docs: run -->`` is also run, with ``bash -e`` in the repository, within
  ``RUN_TIMEOUT_S``.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import io
import os
import re
import shlex
import subprocess
import sys
import threading
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import pytest
from sybil import Example, Sybil
from sybil.evaluators.python import pad
from sybil.parsers.markdown import CodeBlockParser, SkipParser

ROOT = Path(__file__).resolve().parent
DOCS_ENDPOINT = "tcp/127.0.0.1:7447"
RUN_TIMEOUT_S = 120
MARK = re.compile(r"<!--\s*docs:\s*(run|needs [^>]+?)\s*-->\s*$")
PLACEHOLDER = re.compile(r"<[^<>\n]+>")
# Programs a block may use unmarked: shell builtins and what the environment itself installs.
PLAIN_PROGRAMS = frozenset(
    {"export", "umask", "printf", "echo", "cd", "mkdir", "rerun", "pip", "pytest", "python"}
)
REDIRECTION = re.compile(r"\d*(>>?|<)")
OPERATORS = frozenset({"&&", "||", ";", "&", "|"})


class DocsServer:
    """A simulator server started the first time a block asks for its endpoint."""

    def __init__(self, log_dir: Path) -> None:
        self.log_dir = log_dir
        self.server: Any = None

    @property
    def endpoint(self) -> str:
        if self.server is None:
            # Imported here, not at the top: Zenoh and the client load only for a page that
            # needs a server (the repository is on sys.path, this file's folder).
            from tests.support.remote import ServerProcess

            self.server = ServerProcess(self.log_dir, "docs").start()
        return str(self.server.endpoint)

    def stop(self) -> None:
        if self.server is not None:
            self.server.stop()


@pytest.fixture(scope="session")
def docs_server(tmp_path_factory: pytest.TempPathFactory):
    server = DocsServer(tmp_path_factory.mktemp("docs-server"))
    yield server
    server.stop()


def run_python(example: Example) -> None:
    __tracebackhide__ = True
    source = str(example.parsed)
    if DOCS_ENDPOINT in source:
        source = source.replace(DOCS_ENDPOINT, example.namespace["docs_server"].endpoint)
    code = compile(pad(source, example.line + example.parsed.line_offset), example.path, "exec")
    exec(code, example.namespace)
    example.namespace.pop("__builtins__", None)


def mark_of(example: Example) -> str | None:
    """``run``, ``needs ...`` or None: the docs mark in the comment right before the block."""
    before = example.document.text[: example.start].rstrip()
    match = MARK.search(before[-200:])
    return match.group(1) if match else None


def commands_in(block: str) -> list[list[str]]:
    """Each command of a shell block as words, continuations joined, comments, environment
    assignments and redirections dropped, ``<placeholders>`` kept as one word."""
    text = PLACEHOLDER.sub("PLACEHOLDER", block.replace("\\\n", " "))
    text = re.sub(r"\d*>&\d", " ", text)  # 2>&1: before the lexer reads its & as an operator
    commands: list[list[str]] = []
    for line in text.splitlines():
        lexer = shlex.shlex(line, posix=True, punctuation_chars="&|;")
        lexer.whitespace_split = True
        lexer.commenters = "#"
        words: list[str] = []
        redirected = False
        for token in [*lexer, ";"]:
            if redirected:  # the file a redirection names is not an argument
                redirected = False
                continue
            if REDIRECTION.fullmatch(token):
                redirected = True
                continue
            if token in OPERATORS:
                while words and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*=.*", words[0]):
                    words.pop(0)
                if words and words[0] == "sudo":
                    words.pop(0)
                if words:
                    commands.append(words)
                words = []
            else:
                words.append(token)
    return commands


def _entry_points() -> dict[str, str]:
    return {
        point.name: point.value.split(":")[0]
        for point in importlib.metadata.entry_points(group="console_scripts")
        if point.name.startswith("overtake-")
    }


def _parse_quietly(parse: Any, argv: list[str], what: str) -> None:
    out = io.StringIO()
    try:
        with redirect_stdout(out), redirect_stderr(out):
            parse(argv)
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise AssertionError(f"{what} is refused by its parser:\n{out.getvalue()}") from None


def check_command(words: list[str], marked: bool) -> None:
    """Raise AssertionError, saying why, where a documented command would not be accepted."""
    program = words[0].removeprefix(".venv/bin/")
    args = words[1:]
    shown = " ".join(words)
    if program.startswith("overtake-"):
        module = _entry_points().get(program)
        assert module is not None, f"{shown}: there is no command {program}"
        _parse_quietly(importlib.import_module(module).COMMAND.parse, args, shown)
    elif program == "python" and args[:1] == ["-m"]:
        name = args[1]
        if name == "pytest":
            for path in args[2:]:
                if path.startswith("tests/") or path.endswith(".py"):
                    assert (ROOT / path.split("::")[0]).exists(), f"{shown}: no {path}"
        else:
            assert importlib.util.find_spec(name) is not None, f"{shown}: no module {name}"
    elif program == "python" and args and args[0].endswith(".py"):
        script = ROOT / args[0]
        assert script.exists(), f"{shown}: no file {args[0]}"
        spec = importlib.util.spec_from_file_location(f"docs_example_{script.stem}", script)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # dataclasses look their module up there
        spec.loader.exec_module(module)
        import tyro

        _parse_quietly(lambda argv: tyro.cli(module.Args, args=argv), args[1:], shown)
    elif program.startswith("scripts/"):
        script = ROOT / program
        assert script.exists(), f"{shown}: no script {program}"
        assert os.access(script, os.X_OK), f"{shown}: {program} is not executable"
        syntax = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True)
        assert syntax.returncode == 0, f"{program} does not parse: {syntax.stderr}"
    elif program not in PLAIN_PROGRAMS and not marked:
        raise AssertionError(
            f"{shown}: {program} is neither checked nor run; mark the block with "
            "<!-- docs: needs WHAT --> if it needs what CI does not have"
        )


def check_shell(example: Example) -> None:
    __tracebackhide__ = True
    mark = mark_of(example)
    commands = commands_in(str(example.parsed))
    assert commands, "a shell block without a command"
    for words in commands:
        check_command(words, marked=mark is not None)
    if mark == "run":
        env = dict(os.environ, PATH=f"{ROOT / '.venv' / 'bin'}{os.pathsep}{os.environ['PATH']}")
        done = subprocess.run(
            ["bash", "-e", "-c", str(example.parsed)],
            cwd=ROOT,
            env=env,
            capture_output=True,
            text=True,
            timeout=RUN_TIMEOUT_S,
        )
        assert done.returncode == 0, f"the block failed ({done.returncode}):\n{done.stderr}"


def _namespace(namespace: dict[str, Any]) -> None:
    try:
        importlib.import_module("mlagents_envs")
        namespace["HAVE_MLAGENTS"] = True
    except ImportError:
        namespace["HAVE_MLAGENTS"] = False


def _close_what_pages_left_open(namespace: dict[str, Any]) -> None:
    """A page may end with an environment open, as a reader's session would; its Zenoh session's
    threads would keep pytest from exiting, so what a page opened is closed after it."""
    for value in list(namespace.values()):
        module = type(value).__module__
        if module.startswith(("overtake.", "gymnasium.", "pettingzoo.")) and callable(
            getattr(value, "close", None)
        ):
            try:
                value.close()
            except Exception as error:  # a page's object closed twice, or broken: said, not raised
                print(f"docs: closing {type(value).__name__} after the page: {error}")


pytest_collect_file = Sybil(
    parsers=[
        SkipParser(),
        CodeBlockParser("python", run_python),
        CodeBlockParser("bash", check_shell),
    ],
    patterns=["README.md", "docs/*.md"],
    fixtures=["docs_server"],
    setup=_namespace,
    teardown=_close_what_pages_left_open,
).pytest()


# --- workers ---------------------------------------------------------------------------------


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist (``-n auto``), each worker and the processes its tests start get
    their share of the cores for OpenMP and PyTorch's threads, so that N workers do not each
    run a thread per core."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if workers:
        share = max(1, (os.cpu_count() or 1) // int(workers))
        os.environ.setdefault("OMP_NUM_THREADS", str(share))
        if "torch" in sys.modules:
            sys.modules["torch"].set_num_threads(share)


# --- a session that ends ---------------------------------------------------------------------

_EXIT_STATUS: list[int] = []
# What was in /dev/shm when the run began (the controller's, under pytest-xdist).
_SHM_BEFORE: set[str] = set()
_SHM = Path("/dev/shm")


def pytest_sessionstart(session: pytest.Session) -> None:
    if hasattr(session.config, "workerinput"):
        return
    if _SHM.is_dir():
        _SHM_BEFORE.update(p.name for p in _SHM.iterdir())
    # The simulator's compiled loops, compiled (or their cache checked) once before any worker
    # starts: otherwise each worker, and each server a test starts, compiles what it first
    # uses, and a server compiling highway-env's scene (about 10 s) misses a test's deadline
    # to answer. Its own process, so that the controller does not load the simulator.
    subprocess.run(
        [sys.executable, "-m", "overtake.server.sim.warm"],
        check=True,
        stdout=subprocess.DEVNULL,
        timeout=600,
    )


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """The suite leaves /dev/shm as it found it (issue 47): a segment left there by any
    process a test started (overtake's or Zenoh's) fails the run, named."""
    if not hasattr(session.config, "workerinput") and _SHM.is_dir():
        left = sorted(
            p.name
            for p in _SHM.iterdir()
            if p.name not in _SHM_BEFORE
            and (p.name.startswith("overtake-") or p.name.endswith(".zenoh"))
        )
        if left:
            print(f"\nconftest: the run left {len(left)} segment(s) in /dev/shm: {left}")
            if exitstatus == pytest.ExitCode.OK:
                session.exitstatus = pytest.ExitCode.TESTS_FAILED
                exitstatus = int(session.exitstatus)
    _EXIT_STATUS.append(int(exitstatus))


def _zenoh_callback_threads() -> list[threading.Thread]:
    return [
        t
        for t in threading.enumerate()
        if "pyo3-closure" in t.name and t.is_alive() and not t.daemon
    ]


def _exit_past_stuck_callbacks() -> None:
    """Zenoh runs each Python callback of a session on a thread of its own, not a daemon, that
    ends a moment after its session closes. One whose session never closes keeps the
    interpreter from exiting, and CI would wait for it for ever (it happened: an ML-Agents
    snippet in docs/ecosystem.md left its environments open inside ML-Agents' wrappers, which
    the page teardown does not know; the snippet closes them now). At exit,
    after pytest's report, such threads get 10 s to end; those still running are named and
    the process ends with pytest's status."""
    # A closed session's callback threads end on their own within a second or two.
    deadline = time.monotonic() + 10.0
    for thread in _zenoh_callback_threads():
        thread.join(max(0.0, deadline - time.monotonic()))
    stuck = _zenoh_callback_threads()
    if stuck and _EXIT_STATUS:
        print(
            f"\nconftest: {len(stuck)} Zenoh callback thread(s) of an unclosed session still "
            f"run ({', '.join(t.name for t in stuck)}); exiting with pytest's status "
            f"{_EXIT_STATUS[-1]} instead of waiting for them",
            file=sys.stderr,
        )
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])


# The interpreter joins non-daemon threads before it runs atexit's functions; the threading
# module's own exit hook (what concurrent.futures uses) runs before that join.
threading._register_atexit(_exit_past_stuck_callbacks)  # type: ignore[attr-defined]
