"""Helpers for the end-to-end tests of the wire: real server and trainer processes on
127.0.0.1, free ports, and waits on conditions (never on fixed sleeps).

Every process started here is ended by its PID (SIGTERM, then SIGKILL after a timeout, then
``wait``) when its context manager exits, whatever happened in the test.
"""

from __future__ import annotations

import contextlib
import json
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, TypeVar

import gymnasium as gym
import pytest
import zenoh

from overtake.client.wire.remote import Connection, RemoteConfig
from overtake.envs import REMOTE_HIGHWAY_ENV_ID
from overtake.ipc.transport import TransportConfig
from overtake.protocol import codec, errors, keys
from overtake.protocol.messages import Message, StatusReply, StatusRequest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]  # the repository, where the processes run
TRAINER_SCRIPT = HERE / "trainer_script.py"
LOOPBACK = "127.0.0.1"

T = TypeVar("T")


# --- waiting ---------------------------------------------------------------------------------


def wait_until(
    predicate: Callable[[], T], timeout_s: float, what: str, interval_s: float = 0.02
) -> T:
    """Poll ``predicate`` until it returns something truthy (returned); fail after ``timeout_s``.

    The short pause between polls is the polling period of a condition, not a guess at how
    long something takes: the wait ends as soon as the condition holds.
    """
    deadline = time.monotonic() + timeout_s
    last_error: BaseException | None = None
    pause = threading.Event()
    while True:
        try:
            value = predicate()
        except Exception as error:  # a probe may fail while things start or stop
            value, last_error = None, error
        if value:
            return value
        if time.monotonic() >= deadline:
            detail = f" (last error: {last_error!r})" if last_error is not None else ""
            raise AssertionError(f"timed out after {timeout_s:g} s waiting for {what}{detail}")
        pause.wait(interval_s)


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((LOOPBACK, 0))
        return sock.getsockname()[1]


def endpoint(port: int) -> str:
    return f"tcp/{LOOPBACK}:{port}"


def stop_process(proc: subprocess.Popen, timeout_s: float = 5.0, sig: int = signal.SIGTERM) -> int:
    """End ``proc`` by its PID: ``sig``, then SIGKILL after ``timeout_s``; its exit status."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(proc.pid, sig)
        try:
            return proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.kill(proc.pid, signal.SIGKILL)
    return proc.wait(timeout=30)


def child_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONUNBUFFERED"] = "1"
    env.pop("RUST_LOG", None)
    return env


def remote_config(
    ep: str | Iterable[str], server: str | None = None, **kwargs: Any
) -> RemoteConfig:
    """A RemoteConfig with short timeouts for tests (any of them can be overridden)."""
    connect = (ep,) if isinstance(ep, str) else tuple(ep)
    settings: dict[str, Any] = dict(
        connect_timeout_s=10.0,
        request_timeout_s=5.0,
        step_timeout_s=20.0,
        reconnect_timeout_s=0.0,
        lease_s=3.0,
    )
    settings.update(kwargs)
    return RemoteConfig(connect=connect, server=server, **settings)


def remote_vector_env(
    server: ServerProcess, num_envs: int, **env_kwargs: Any
) -> gym.vector.VectorEnv:
    """``num_envs`` arenas on ``server`` as one remote vector environment, with
    :func:`remote_config`'s test timeouts; ``env_kwargs``: the environment's own (``preset``,
    ``overrides``, ``parts``)."""
    return gym.make_vec(
        REMOTE_HIGHWAY_ENV_ID,
        num_envs=num_envs,
        vectorization_mode="vector_entry_point",
        remote=remote_config(server.endpoint, server.name),
        **env_kwargs,
    )


# --- servers ---------------------------------------------------------------------------------


class ServerProcess:
    """``python -m overtake.server`` on 127.0.0.1; its stderr log goes to a file.

    ``with ServerProcess(tmp_path, "srv") as server:`` starts it and waits until its status
    answers (a StatusRequest through :meth:`Connection.discover` lists its name).
    """

    def __init__(
        self,
        log_dir: Path,
        name: str,
        *,
        port: int | None = None,
        connect: tuple[str, ...] = (),
        step_deadline_s: float | None = None,
        max_arenas: int | None = None,
        lease_s: float | None = None,
        world_rate_hz: float | None = None,
        extra: tuple[str, ...] = (),
        start_timeout_s: float = 20.0,
        env: dict[str, str] | None = None,
    ) -> None:
        self.name = name
        self.env = {**child_env(), **(env or {})}
        self.port = port if port is not None else free_port()
        self.endpoint = endpoint(self.port)
        self.connect = connect
        self.args = ["--listen", self.endpoint, "--name", name, "--log-level", "info"]
        for flag, value in (
            ("--step-deadline-s", step_deadline_s),
            ("--max-arenas", max_arenas),
            ("--lease-s", lease_s),
            ("--world-rate-hz", world_rate_hz),
        ):
            if value is not None:
                self.args += [flag, str(value)]
        if connect:
            self.args += ["--connect", *connect]
        self.args += list(extra)
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.start_timeout_s = start_timeout_s
        self.proc: subprocess.Popen | None = None
        self.log_path = self.log_dir / f"server-{name}-{self.port}-{id(self)}.log"
        self._probe: Connection | None = None

    # lifecycle

    def start(self) -> ServerProcess:
        log = open(self.log_path, "wb")  # noqa: SIM115 (the server writes it until stopped)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "overtake.server", *self.args],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                env=self.env,
                cwd=ROOT,
            )
        finally:
            log.close()
        try:
            self.wait_ready(self.start_timeout_s)
        except BaseException:
            self.stop()
            raise
        return self

    def wait_ready(self, timeout_s: float) -> None:
        assert self.proc is not None

        def listed() -> bool:
            if self.proc.poll() is not None:
                raise RuntimeError(
                    f"server {self.name} exited with {self.proc.returncode}: "
                    f"{self.log_text()[-2000:]}"
                )
            return any(s.server == self.name for s in self.probe().discover())

        deadline = time.monotonic() + timeout_s
        while True:
            try:
                if listed():
                    return
            except RuntimeError:
                raise
            except errors.ConnectError:
                pass  # not listening yet: the probe is opened again
            if time.monotonic() >= deadline:
                raise AssertionError(
                    f"server {self.name} did not answer a status request on "
                    f"{self.endpoint} within {timeout_s:g} s; log:\n"
                    f"{self.log_text()[-2000:]}"
                )
            threading.Event().wait(0.05)

    def probe(self) -> Connection:
        """The test's own trainer-side connection to this server (status queries)."""
        if self._probe is None:
            self._probe = Connection(
                remote_config(
                    self.endpoint, server=self.name, connect_timeout_s=2.0, request_timeout_s=2.0
                )
            )
        return self._probe

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int) -> None:
        assert self.proc is not None
        os.kill(self.proc.pid, sig)

    def kill(self) -> int:
        """SIGKILL and reap: the server vanishes without saying goodbye."""
        assert self.proc is not None
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
        return self.proc.wait(timeout=30)

    def wait_exit(self, timeout_s: float) -> int:
        assert self.proc is not None
        return self.proc.wait(timeout=timeout_s)

    def stop(self) -> None:
        try:
            if self._probe is not None:
                self._probe.close()
                self._probe = None
        finally:
            if self.proc is not None:
                stop_process(self.proc)

    def __enter__(self) -> ServerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # views

    def status(self) -> StatusReply:
        """This server's StatusReply (asked by name)."""
        return self.probe().request(self.name, StatusRequest(), StatusReply)

    def discovered(self) -> list[StatusReply]:
        return self.probe().discover()

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def wait_log(self, text: str, timeout_s: float = 10.0) -> str:
        wait_until(lambda: text in self.log_text(), timeout_s, f"{text!r} in {self.name}'s log")
        return self.log_text()


# --- trainers ---------------------------------------------------------------------------------


class TrainerProcess:
    """``tests/support/trainer_script.py`` as a subprocess: commands on stdin, one event per
    line out.

    Each output line is ``EVENT {json}``; :meth:`expect` waits (with a deadline) for the next
    line of an event, failing on an ``ERROR`` line or an early exit.
    """

    def __init__(self, args: list[str], log_dir: Path, label: str = "trainer") -> None:
        self.args = args
        self.label = label
        Path(log_dir).mkdir(parents=True, exist_ok=True)
        self.stderr_path = Path(log_dir) / f"{label}-{id(self)}.stderr"
        self.lines: queue.Queue[str | None] = queue.Queue()
        self._pushback: list[str | None] = []
        self.history: list[str] = []
        self.proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None

    def start(self) -> TrainerProcess:
        err = open(self.stderr_path, "wb")  # noqa: SIM115 (the trainer writes it until stopped)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, str(TRAINER_SCRIPT), *self.args],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=err,
                env=child_env(),
                cwd=ROOT,
                text=True,
                bufsize=1,
            )
        finally:
            err.close()
        self._reader = threading.Thread(target=self._read, name=f"{self.label}-stdout", daemon=True)
        self._reader.start()
        return self

    def _read(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def send(self, command: str) -> None:
        assert self.proc is not None and self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def stderr_text(self) -> str:
        try:
            return self.stderr_path.read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def next_event(self, timeout_s: float) -> tuple[str, dict[str, Any]]:
        """The next (event, fields) line; AssertionError if none comes within ``timeout_s``."""
        try:
            line = self._pushback.pop() if self._pushback else self.lines.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError(
                f"{self.label}: no output line within {timeout_s:g} s; "
                f"so far {self.history[-5:]}; stderr:\n"
                f"{self.stderr_text()[-3000:]}"
            ) from None
        if line is None:
            self._pushback.append(None)  # stay at end of file for later calls
            code = self.proc.wait(timeout=10) if self.proc is not None else None
            raise AssertionError(
                f"{self.label} exited ({code}) ; last lines "
                f"{self.history[-5:]}; stderr:\n{self.stderr_text()[-3000:]}"
            )
        self.history.append(line)
        event, _, rest = line.partition(" ")
        try:
            fields = json.loads(rest) if rest else {}
        except json.JSONDecodeError:
            fields = {"text": rest}
        return event, fields

    def expect(self, event: str, timeout_s: float = 20.0) -> dict[str, Any]:
        """Wait for the next ``event`` line (skipping others); fail on ERROR or exit."""
        deadline = time.monotonic() + timeout_s
        while True:
            got, fields = self.next_event(max(deadline - time.monotonic(), 0.0))
            if got == event:
                return fields
            if got == "ERROR" and event != "ERROR":
                raise AssertionError(
                    f"{self.label} reported an error while we waited for {event}: {fields}"
                )

    def no_event_within(self, timeout_s: float) -> bool:
        """True when no line arrives within ``timeout_s`` (a bounded check that nothing
        happens, e.g. a round that must wait for another trainer)."""
        if self._pushback:
            return False
        try:
            line = self.lines.get(timeout=timeout_s)
        except queue.Empty:
            return True
        self._pushback.append(line)
        return False

    def stop(self, timeout_s: float = 5.0) -> int | None:
        if self.proc is None:
            return None
        try:
            if self.proc.poll() is None and self.proc.stdin is not None:
                with contextlib.suppress(BrokenPipeError, OSError, ValueError):
                    self.send("exit")
            try:
                return self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                return stop_process(self.proc, timeout_s)
        finally:
            if self.proc.poll() is None:
                stop_process(self.proc, timeout_s)
            for stream in (self.proc.stdin, self.proc.stdout):
                try:
                    if stream is not None:
                        stream.close()
                except (BrokenPipeError, OSError, ValueError):
                    pass

    def kill(self) -> int:
        assert self.proc is not None
        if self.proc.poll() is None:
            os.kill(self.proc.pid, signal.SIGKILL)
        return self.proc.wait(timeout=30)

    def __enter__(self) -> TrainerProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def trainer_args(server: ServerProcess | str, name: str, **options: Any) -> list[str]:
    """argv for tests/support/trainer_script.py (options are its flags, ``_`` for ``-``)."""
    ep = server.endpoint if isinstance(server, ServerProcess) else server
    args = ["--connect", ep, "--server", name]
    for key, value in options.items():
        flag = "--" + key.replace("_", "-")
        if value is True:
            args.append(flag)
        elif value is not None and value is not False:
            args += [flag, json.dumps(value) if isinstance(value, dict) else str(value)]
    return args


# --- raw Zenoh ----------------------------------------------------------------------------------


class RawClient:
    """A bare Zenoh client session (no overtake client code): hostile input, spectators."""

    def __init__(self, ep: str, timeout_s: float = 10.0) -> None:
        self.session = zenoh.open(
            TransportConfig(
                mode="client", connect=(ep,), connect_timeout_s=timeout_s
            ).zenoh_config()
        )
        self._declared: list[Any] = []

    def query(self, key: str, payload: bytes, timeout_s: float = 5.0) -> list[bytes]:
        """The ok replies' payloads of one query."""
        replies = self.session.get(key, payload=payload, timeout=timeout_s)
        out = []
        for reply in replies:
            if reply.ok is not None:
                out.append(reply.ok.payload.to_bytes())
            else:
                raise AssertionError(
                    "query error reply: " + reply.err.payload.to_bytes().decode("utf-8", "replace")
                )
        return out

    def request(self, server: str, message: Message | bytes, timeout_s: float = 5.0) -> Message:
        payload = message if isinstance(message, bytes) else codec.encode(message)
        replies = self.query(keys.server_request(server), payload, timeout_s)
        assert len(replies) == 1, f"expected one reply, got {len(replies)}"
        return codec.decode(replies[0])

    def put(self, key: str, payload: bytes) -> None:
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def subscribe(self, key: str, callback: Callable[[zenoh.Sample], None]) -> Any:
        sub = self.session.declare_subscriber(key, callback)
        self._declared.append(sub)
        return sub

    def collect(self, key: str) -> queue.Queue[tuple[str, bytes]]:
        """Subscribe to ``key``; the samples (key, payload) land in the returned queue."""
        inbox: queue.Queue[tuple[str, bytes]] = queue.Queue()
        self.subscribe(key, lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes())))
        return inbox

    def token(self, key: str) -> Any:
        token = self.session.liveliness().declare_token(key)
        self._declared.append(token)
        return token

    def close(self) -> None:
        for obj in reversed(self._declared):
            with contextlib.suppress(Exception):
                obj.undeclare()
        self._declared.clear()
        with contextlib.suppress(Exception):
            self.session.close()

    def __enter__(self) -> RawClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def next_message(
    inbox: queue.Queue[tuple[str, bytes]], timeout_s: float, what: str
) -> tuple[str, Message]:
    try:
        key, payload = inbox.get(timeout=timeout_s)
    except queue.Empty:
        raise AssertionError(f"no {what} within {timeout_s:g} s") from None
    return key, codec.decode(payload)


# --- fixtures (import them into a test module to use them) --------------------------------------


@pytest.fixture
def start_server(tmp_path):
    """``start_server(name, **ServerProcess options)``: a started server, stopped at teardown."""
    started: list[ServerProcess] = []

    def start(name: str, **options: Any) -> ServerProcess:
        server = ServerProcess(tmp_path / "logs", name, **options)
        started.append(server)
        return server.start()

    yield start
    for server in reversed(started):
        server.stop()


@pytest.fixture(scope="module")
def shared_server(tmp_path_factory, request):
    """One server (default options) for a module's tests that use it only as an endpoint,
    each opening and closing its own arenas: a server's start costs 1.5-2 CPU-seconds."""
    name = "shared-" + request.module.__name__.rsplit(".", 1)[-1].removeprefix("test_")
    server = ServerProcess(tmp_path_factory.mktemp("shared-server-logs"), name)
    server.start()
    yield server
    server.stop()


@pytest.fixture
def start_trainer(tmp_path):
    """``start_trainer(args, label)``: a started trainer_script.py, stopped at teardown."""
    started: list[TrainerProcess] = []

    def start(args: list[str], label: str = "trainer") -> TrainerProcess:
        trainer = TrainerProcess(args, tmp_path / "logs", label)
        started.append(trainer)
        return trainer.start()

    yield start
    for trainer in reversed(started):
        trainer.stop()


def strings_in(value: Any) -> set[str]:
    """Every string in a nest of lists, tuples and dicts (a blueprint, a column's values)."""
    if isinstance(value, str):
        return {value}
    if isinstance(value, dict):
        value = list(value.values())
    if isinstance(value, (list, tuple)):
        return set().union(set(), *(strings_in(item) for item in value))
    return set()


def blueprint_texts(reader: Any, store: Any) -> set[str]:
    """Every text value in one blueprint store of an ``rr.chunk.RrdReader`` (view names,
    origins, entity paths)."""
    import pyarrow as pa

    texts: set[str] = set()
    for chunk in reader.stream(store=store).to_chunks():
        batch = chunk.to_record_batch()
        for column, column_field in zip(batch.columns, batch.schema, strict=True):
            if not pa.types.is_temporal(column_field.type):  # timelines hold no text
                texts |= strings_in(column.to_pylist())
    return texts


def logged_by_round(reader: Any, entity: str, column: str) -> dict[int, list]:
    """From an ``rr.chunk.RrdReader``: round -> the value of ``column`` logged for ``entity``
    in that round (the last one logged there)."""
    out: dict[int, list] = {}
    for chunk in reader.stream().to_chunks():
        if chunk.entity_path != entity or chunk.is_static:
            continue
        batch = chunk.to_record_batch()
        for round_, value in zip(
            batch.column("round").to_pylist(), batch.column(column).to_pylist()
        ):
            out[round_] = value
    return out
