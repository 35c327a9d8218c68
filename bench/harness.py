"""What the benchmarks of every audience share: an ``overtake.server`` subprocess on a free
port of 127.0.0.1 and its stop, environments made alike in-process or remote and their random
actions, step-latency percentiles, a process's CPU time from /proc, another git revision's
overtake for an A/B, and the JSON report every ``--json`` writes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import tomllib
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
REMOTE_ENV_ID = "overtake/RemoteHighway-v0"
SERVER_NAME = "bench"


def package_folders(tree: Path) -> tuple[str, ...]:
    """The folders ``tree``'s pyproject.toml maps into overtake.* (its package-dir): a
    revision's own, since packages are added over time (cli, envs, ipc)."""
    project = tomllib.loads((tree / "pyproject.toml").read_text(encoding="utf-8"))
    return tuple(sorted(project["tool"]["setuptools"]["package-dir"].values()))


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def latency_summary(seconds: Sequence[float]) -> dict[str, float]:
    """Percentiles of step or round-trip times, in milliseconds."""
    import numpy as np

    ms = np.asarray(seconds, dtype=np.float64) * 1e3
    p50, p90, p99 = np.percentile(ms, [50, 90, 99])
    return {
        "count": int(ms.size),
        "p50_ms": float(p50),
        "p90_ms": float(p90),
        "p99_ms": float(p99),
        "mean_ms": float(ms.mean()),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
    }


def process_usage(pid: int) -> tuple[float, int]:
    """User + system CPU seconds (ticks of 1/CLK_TCK s) and minor page faults of process
    ``pid``, from Linux's /proc."""
    with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
        fields_after_name = stat.read().rsplit(")", 1)[1].split()
    cpu = (int(fields_after_name[11]) + int(fields_after_name[12])) / os.sysconf("SC_CLK_TCK")
    return cpu, int(fields_after_name[7])


def stop_process(proc: subprocess.Popen[Any], timeout_s: float = 10.0) -> int | None:
    """SIGTERM ``proc`` (by its PID), SIGKILL it if it outlives ``timeout_s``; its exit status."""
    if proc.poll() is None:
        try:
            os.kill(proc.pid, signal.SIGTERM)
            return proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.kill(proc.pid, signal.SIGKILL)
            return proc.wait(timeout=timeout_s)
        except ProcessLookupError:
            pass
    return proc.poll()


@contextlib.contextmanager
def zenoh_pools_removed(shm_dir: Path = Path("/dev/shm")) -> Iterator[None]:
    """Remove the shared-memory pools (``<id>.zenoh``) Zenoh made under ``shm_dir`` while the
    block ran and that no process maps any more: a Zenoh process that ends without running
    its exit handlers (``os._exit``, a signal) leaves its pools behind, tens of MiB of memory
    each time. A pool some live process still maps is left alone."""
    before = set(shm_dir.glob("*.zenoh"))
    try:
        yield
    finally:
        made = set(shm_dir.glob("*.zenoh")) - before
        mapped = _mapped_paths() if made else set()
        for path in made - mapped:
            with contextlib.suppress(FileNotFoundError):
                path.unlink()


def _mapped_paths() -> set[Path]:
    """The files every process this user can read maps (``/proc/<pid>/maps``)."""
    mapped: set[Path] = set()
    for maps in Path("/proc").glob("[0-9]*/maps"):
        with contextlib.suppress(OSError):
            for line in maps.read_text().splitlines():
                path = line.split(maxsplit=5)[5:]
                if path and path[0].startswith("/"):
                    mapped.add(Path(path[0]))
    return mapped


def make_env(env_id: str, arenas: int, **kwargs: Any) -> Any:
    import gymnasium

    import overtake.client  # noqa: F401  (registers both environments)

    if arenas == 1:
        return gymnasium.make(env_id, **kwargs)
    return gymnasium.make_vec(
        env_id, num_envs=arenas, vectorization_mode="vector_entry_point", **kwargs
    )


def random_action(rng: Any, arenas: int) -> Any:
    """A random action for what :func:`make_env` made: an int for one arena, an array for a
    vector of them (``rng``: a numpy Generator)."""
    from overtake.protocol import ACTION_COUNT

    actions = rng.integers(0, ACTION_COUNT, size=arenas)
    return int(actions[0]) if arenas == 1 else actions


def start_server(
    endpoint: str, timeout_s: float, extra: tuple[str, ...] = (), env: dict[str, str] | None = None
) -> subprocess.Popen[bytes]:
    """An ``overtake.server`` subprocess (``extra``: more flags; ``env``: its environment,
    by default this process's), returned once it answers a status request."""
    from overtake.client.wire.remote import Connection, RemoteConfig
    from overtake.protocol import errors

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "overtake.server",
            "--listen",
            endpoint,
            "--name",
            SERVER_NAME,
            "--log-level",
            "warning",
            "--max-arenas",
            "256",
            *extra,
        ],
        stdout=subprocess.DEVNULL,
        env=env,
    )
    connection = None
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            if proc.poll() is not None:
                raise RuntimeError(
                    f"the server exited with status {proc.returncode} before "
                    "answering (its messages are above)"
                )
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(
                    f"the server did not answer on {endpoint} within {timeout_s:g} s"
                )
            try:
                if connection is None:  # opening keeps retrying the endpoint for a while
                    connection = Connection(
                        RemoteConfig(
                            connect=(endpoint,),
                            connect_timeout_s=min(10.0, remaining),
                            request_timeout_s=min(2.0, remaining),
                        )
                    )
                if any(status.server == SERVER_NAME for status in connection.discover()):
                    break
            except errors.ConnectError:
                connection = None
            # Polling: the session is up but the server's queryable may not be declared yet.
            time.sleep(0.02)
    except BaseException:
        stop_process(proc)
        raise
    finally:
        if connection is not None:
            connection.close()
    return proc


@contextlib.contextmanager
def baseline_checkout(revision: str) -> Iterator[Path]:
    """A directory to put first on PYTHONPATH for ``revision``'s overtake: a temporary git
    worktree of that revision, its package folders linked under ``overtake/``. The worktree
    and the directory are removed afterwards."""
    where = Path(tempfile.mkdtemp(prefix="overtake-ab-"))
    tree = where / "tree"
    try:
        subprocess.run(
            ["git", "worktree", "add", "--detach", "--quiet", str(tree), revision],
            cwd=ROOT,
            check=True,
        )
        package = where / "path" / "overtake"
        package.mkdir(parents=True)
        for folder in package_folders(tree):
            (package / folder).symlink_to(tree / folder, target_is_directory=True)
        print(f"baseline {revision} from {tree}; working tree {ROOT}", flush=True)
        yield where / "path"
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, check=False)
        shutil.rmtree(where, ignore_errors=True)


def report_head(config: Any, machine: dict[str, Any], threads: Any) -> dict[str, Any]:
    """What every benchmark's JSON report starts with: when (UTC), its configuration (a
    dataclass whose ``json`` is the report's own path), the machine and the thread pools."""
    return {
        "timestamp_utc": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "config": {
            **dataclasses.asdict(config),
            "json": None if config.json is None else str(config.json),
        },
        "machine": machine,
        "threads": threads,
    }


def write_report(path: Path | None, report: dict[str, Any]) -> None:
    """Write a benchmark's report as JSON to ``path`` (``--json``; nothing for None), values
    JSON has no type for as text, and say where."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2, default=str) + "\n", encoding="utf-8")
    print(f"wrote {path}")
