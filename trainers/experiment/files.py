"""The experiment directory's files: written whole or not at all, locked while a process works
in them, and the training records of runs that were killed and resumed."""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import secrets
import socket
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..run.checkpoint import CHECKPOINT_NAME, load_checkpoint

LIVES_NAME = "experiment-lives.jsonl"
# On a cluster: the token the experiment writes into its directory for every node to find
# there (the same storage) before it trains anything.
STORAGE_TOKEN_NAME = ".storage-token"
PLAN_NAME = "experiment.json"
LOCK_NAME = ".lock"


def write_atomic(path: Path, data: str | bytes) -> None:
    """Write to a temporary file beside ``path`` and rename it over ``path``: a kill leaves the
    old file or the new one, never half of one."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def read_json(path: Path) -> Any:
    """``path``'s JSON, or None where it is missing or unreadable (a file of a killed
    process)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def checkpoint_step(run_dir: Path) -> int | None:
    """The step of the run's checkpoint, or None where it has none."""
    path = run_dir / CHECKPOINT_NAME
    if not path.exists():
        return None
    return load_checkpoint(path).step


def lock(path: Path) -> int | None:
    """An open descriptor holding an exclusive lock on ``path`` (created), or None where
    another process holds it. The lock lasts while any process keeps the descriptor open: a
    child that inherits it holds it until it exits."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def lock_all(paths: tuple[Path, ...]) -> tuple[int, ...] | None:
    """Descriptors holding the locks of every path, or None (and none held) where another
    process holds one of them."""
    fds: list[int] = []
    for path in paths:
        fd = lock(path)
        if fd is None:
            for held in fds:
                os.close(held)
            return None
        fds.append(fd)
    return tuple(fds)


def note_life(run_dir: Path, from_step: int, node: str | None = None) -> None:
    """Record, before a trainer starts in ``run_dir``, where its records will begin in
    metrics.jsonl and from which step it trains (0: from scratch), and on which cluster node
    (``node``; None: the experiment's machine, and not recorded). The episodes an earlier life
    logged after that step are redone by this one, and the curves drop them."""
    metrics = run_dir / "metrics.jsonl"
    offset = metrics.stat().st_size if metrics.exists() else 0
    record: dict[str, Any] = {
        "from_step": from_step,
        "metrics_offset_bytes": offset,
        "started_utc": utc_now(),
    }
    if node is not None:
        record["node"] = node
    with open(run_dir / LIVES_NAME, "a", encoding="utf-8") as handle:
        handle.write(json.dumps(record) + "\n")


def training_episodes(run_dir: Path) -> list[dict[str, Any]]:
    """The run's training episodes (metrics.jsonl's ``episode`` records) that its final model
    descends from: where a life resumed from step S, the earlier lives' episodes after S are
    left out (that training was lost with the kill and done again)."""
    return training_records(run_dir, "episode")


def training_records(run_dir: Path, kind: str) -> list[dict[str, Any]]:
    """:func:`training_episodes` for metrics.jsonl's records of any ``kind``."""
    metrics = run_dir / "metrics.jsonl"
    data = metrics.read_bytes() if metrics.exists() else b""
    starts: list[tuple[int, int | None]] = [(0, None)]
    lives = run_dir / LIVES_NAME
    if lives.exists():
        for text in lives.read_text(encoding="utf-8").splitlines():
            with contextlib.suppress(ValueError, KeyError, TypeError):
                life = json.loads(text)
                starts.append((int(life["metrics_offset_bytes"]), int(life["from_step"])))
    kept: list[dict[str, Any]] = []
    for i, (begin, from_step) in enumerate(starts):
        end = starts[i + 1][0] if i + 1 < len(starts) else len(data)
        if from_step is not None:
            kept = [record for record in kept if record["step"] <= from_step]
        for line in data[begin:end].splitlines():
            try:
                record = json.loads(line)
            except ValueError:
                continue  # the line a kill cut short
            if isinstance(record, dict) and record.get("kind") == kind:
                kept.append(record)
    return kept


def window_rewards(train_records_by_run: dict[str, list[dict[str, Any]]], window: int) -> Any:
    """A row's reward per ``window`` training steps (Fayjie et al.'s Fig. 6).

    A run logs a training line about every ``window`` steps with the reward summed since the
    window began (``from_step``; lines written before it was logged lack it, and the line
    before stands in). A line that covers less than a window (the last before a stop, the
    budget's last) is joined to the next, and each point is its reward per ``window`` steps,
    so a short line is neither a dip nor a second run. Points are matched across runs by the
    nearest multiple of ``window``: the mean over the row's runs, and the lowest and highest."""
    by_window: dict[int, list[float]] = {}
    for records in train_records_by_run.values():
        points: dict[int, tuple[float, float]] = {}  # k -> (reward, steps)
        last_step, reward, steps = 0, 0.0, 0.0
        for record in records:
            begin = record.get("from_step", last_step)
            last_step = record["step"]
            if record.get("reward_sum") is None:
                continue
            reward += float(record["reward_sum"])
            steps += max(0, record["step"] - begin)
            if steps >= window:
                _add_point(points, max(1, round(record["step"] / window)), reward, steps)
                reward, steps = 0.0, 0.0
        if steps > 0:
            _add_point(points, max(1, round(last_step / window)), reward, steps)
        for k, (total, covered) in points.items():
            by_window.setdefault(k, []).append(total * window / covered)
    windows = sorted(by_window)
    return {
        "window_end_step": [k * window for k in windows],
        "mean": [float(np.mean(by_window[k])) for k in windows],
        "run_min": [min(by_window[k]) for k in windows],
        "run_max": [max(by_window[k]) for k in windows],
    }


def _add_point(points: dict[int, tuple[float, float]], k: int, reward: float, steps: float) -> None:
    """Add a run's ``reward`` over ``steps`` to its point ``k`` (a short last line whose
    nearest multiple is the point before joins it)."""
    before = points.get(k, (0.0, 0.0))
    points[k] = (before[0] + reward, before[1] + steps)


def write_storage_token(out: Path) -> str:
    """A new random token, written into the experiment directory ``out`` for the cluster's
    nodes to read back (:func:`storage_problem`)."""
    token = secrets.token_hex(8)
    write_atomic(out / STORAGE_TOKEN_NAME, token)
    return token


def storage_problem(out: Path, token: str) -> str | None:
    """Why this machine cannot work in the experiment directory ``out``, in words, or None
    where it can: it must see the ``token`` the experiment wrote there (the same storage, not
    a directory of its own at the same path) and may write files beside it."""
    try:
        seen = (out / STORAGE_TOKEN_NAME).read_text(encoding="utf-8")
    except FileNotFoundError:
        return f"does not see the experiment's files there (no {STORAGE_TOKEN_NAME})"
    except OSError as error:
        return f"cannot read it ({error.strerror or error})"
    if seen != token:
        return "sees another directory at that path (not the experiment's token)"
    probe = out / f"{STORAGE_TOKEN_NAME}-{socket.gethostname()}-{os.getpid()}"
    try:
        write_atomic(probe, token)
        probe.unlink()
    except OSError as error:
        return f"cannot write there ({error.strerror or error})"
    return None


def last_train_record(path: Path) -> dict[str, Any] | None:
    """The last ``train`` record among the last 64 kB of a metrics.jsonl."""
    try:
        with open(path, "rb") as handle:
            handle.seek(max(0, path.stat().st_size - 65_536))
            lines = handle.read().splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        with contextlib.suppress(ValueError):
            record = json.loads(line)
            if isinstance(record, dict) and record.get("kind") == "train":
                return record
    return None


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def say(message: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)
