"""Helpers for the deployment tests (tests/e2e/test_deploy_*.py): routers, servers and
trainers run as real commands (``python -m ...``) on 127.0.0.1 with free ports, each ended
by its PID, and the check that a short training run trained. tests/e2e/conftest.py offers
the fixtures below to those tests.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from overtake.client.wire.remote import Connection, RemoteConfig
from overtake.ipc.transport import PASSWORD_ENV, USER_ENV

from tests.support.remote import child_env, free_port, stop_process, wait_until

ROOT = Path(__file__).resolve().parents[2]


PY = sys.executable


LOOPBACK = "127.0.0.1"


# A trainer short enough for a test, long enough to learn (updates start at step 100) and to
# end episodes (50 decisions each), with the LIDAR network only (no camera rendered).
SHORT_TRAINING = [
    "--inputs",
    "lidar",
    "--total-steps",
    "200",
    "--learning-starts",
    "100",
    "--num-envs",
    "2",
    "--torch-threads",
    "1",
    "--no-progress",
    "--sink",
    "off",
    "--log-every",
    "100",
    "--set",
    "episode.max_decisions=50",
]


COMMAND_TIMEOUT_S = 180.0


@pytest.fixture
def no_inherited_credentials(monkeypatch: pytest.MonkeyPatch) -> None:
    """Credentials in the developer's environment must not leak into these tests."""
    monkeypatch.delenv(USER_ENV, raising=False)
    monkeypatch.delenv(PASSWORD_ENV, raising=False)


def env_with(**variables: str) -> dict[str, str]:
    env = child_env()
    env.pop(USER_ENV, None)
    env.pop(PASSWORD_ENV, None)
    env.update(variables)
    return env


class Background:
    """A long-running command (router, server); its output goes to a log file."""

    def __init__(
        self,
        argv: list[str],
        log_path: Path,
        env: dict[str, str] | None = None,
    ) -> None:
        self.argv, self.log_path = argv, log_path
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "wb") as log:
            self.proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=ROOT,
                env=env if env is not None else env_with(),
            )

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_log(self, text: str, timeout_s: float = 30.0) -> None:
        def seen() -> bool:
            if self.proc.poll() is not None:
                raise AssertionError(
                    f"{self.argv[:4]} exited with {self.proc.returncode}:\n"
                    f"{self.log_text()[-3000:]}"
                )
            return text in self.log_text()

        wait_until(seen, timeout_s, f"{text!r} in {self.log_path.name}")

    def stop(self) -> int:
        return stop_process(self.proc)


@pytest.fixture
def background(tmp_path: Path) -> Iterator:
    """``background(name, argv, env=None)``: a started command, ended by its PID at teardown."""
    started: list[Background] = []

    def start(name: str, argv: list[str], env: dict[str, str] | None = None) -> Background:
        process = Background(argv, tmp_path / "logs" / f"{name}.log", env)
        started.append(process)
        return process

    yield start
    for process in reversed(started):
        process.stop()


def start_router(
    background, name: str, listen: list[str], *options: str, env: dict[str, str] | None = None
) -> Background:
    argv = [
        PY,
        "-m",
        "overtake.server.router",
        "--config",
        str(ROOT / "docker" / "zenoh-router.json5"),
        "--listen",
        *listen,
        *options,
    ]
    router = background(name, argv, env)
    router.wait_log("listening on")
    return router


def start_server(
    background,
    name: str,
    router: str,
    *options: str,
    env: dict[str, str] | None = None,
    listen: bool = True,
) -> Background:
    """A simulator server that joins the network via ``router``; it listens on loopback only,
    or (``listen=False``, docs/remote-hosts.md's recipe) nowhere: reached only through the
    router."""
    endpoints = [f"tcp/{LOOPBACK}:{free_port()}"] if listen else []
    argv = [
        PY,
        "-m",
        "overtake.server",
        "--name",
        name,
        "--listen",
        *endpoints,
        "--connect",
        router,
        *options,
    ]
    return background(name, argv, env)


def wait_for_server(
    name: str, remote: RemoteConfig, server: Background, timeout_s: float = 30.0
) -> None:
    """Until ``name`` answers a status request sent through the router."""
    connection = Connection(remote)
    try:

        def listed() -> bool:
            if server.proc.poll() is not None:
                raise AssertionError(f"server {name} exited: {server.log_text()[-3000:]}")
            return any(s.server == name for s in connection.discover())

        wait_until(listed, timeout_s, f"server {name} answering through the router")
    finally:
        connection.close()


def run(
    argv: list[str], env: dict[str, str] | None = None, timeout_s: float = COMMAND_TIMEOUT_S
) -> subprocess.CompletedProcess:
    """A command run to its end (killed by its PID if it overruns ``timeout_s``)."""
    return subprocess.run(
        argv,
        cwd=ROOT,
        env=env if env is not None else env_with(),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def train_argv(algo: str, connect: str, run_dir: Path, *options: str) -> list[str]:
    return [
        PY,
        "-m",
        "overtake.trainers.train",
        "--algo",
        algo,
        "--connect",
        connect,
        "--run-dir",
        str(run_dir),
        *SHORT_TRAINING,
        *options,
    ]


def check_trained(done: subprocess.CompletedProcess, run_dir: Path) -> dict:
    assert done.returncode == 0, f"overtake-train failed:\n{done.stderr[-4000:]}"
    summary = json.loads(done.stdout[done.stdout.index("{") :])
    assert summary["steps"] >= 200 and summary["updates"] > 0
    assert (run_dir / "checkpoint.pt").stat().st_size > 0
    kinds = {
        json.loads(line)["kind"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()
    }
    assert kinds == {"episode", "train"}
    return summary
