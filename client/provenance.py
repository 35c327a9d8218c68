"""Where this process's code came from: its git commit and its packages' versions (a training
run's run.json, an experiment's table, an episode record's header)."""

from __future__ import annotations

import platform
import subprocess
from importlib import metadata
from pathlib import Path


def git_commit(where: Path | None = None) -> str:
    """The commit of the checkout holding ``where`` (default: this code), with
    ``+uncommitted`` where a tracked file differs from it. Untracked files (results, run
    directories, scripts beside the code) do not count: they are not the code that ran."""
    try:
        here = where if where is not None else Path(__file__).resolve().parent
        out = subprocess.run(
            ["git", "-C", str(here), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return out + ("+uncommitted" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown (not a git checkout)"


def package_versions() -> dict[str, str]:
    versions = {"python": platform.python_version()}
    for name in ("overtake", "torch", "numpy", "gymnasium", "eclipse-zenoh", "msgpack"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
