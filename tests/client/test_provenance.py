"""The commit a run, a table or an episode record names."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from overtake.client.provenance import git_commit


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(repo), *args], capture_output=True, text=True, check=True
    ).stdout.strip()


@pytest.fixture
def repo(tmp_path: Path) -> Path:
    _git(tmp_path, "init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    _git(tmp_path, "add", "code.py")
    _git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "c")
    return tmp_path


def test_a_clean_checkout_names_its_commit(repo: Path) -> None:
    assert git_commit(repo) == _git(repo, "rev-parse", "HEAD")


def test_untracked_results_beside_the_code_do_not_make_it_uncommitted(repo: Path) -> None:
    (repo / "table.md").write_text("results\n")
    (repo / "runs").mkdir()
    (repo / "runs" / "metrics.jsonl").write_text("{}\n")
    assert git_commit(repo) == _git(repo, "rev-parse", "HEAD")


def test_a_changed_tracked_file_is_uncommitted(repo: Path) -> None:
    (repo / "code.py").write_text("x = 2\n")
    assert git_commit(repo) == _git(repo, "rev-parse", "HEAD") + "+uncommitted"


def test_outside_a_checkout_it_says_so(tmp_path: Path) -> None:
    assert git_commit(tmp_path) == "unknown (not a git checkout)"
