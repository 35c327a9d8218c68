"""What a training run writes beside its checkpoints: where its code and packages came from
(for run.json) and its metrics log, one JSON object per line."""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any

from overtake.client.provenance import git_commit, package_versions

__all__ = ["git_commit", "life_record", "package_versions"]


class MetricsLog:
    """Appends JSON lines; each line is flushed, so a kill loses at most the line being written."""

    def __init__(self, path: Path) -> None:
        self.handle = open(path, "a", encoding="utf-8")  # noqa: SIM115 (open for the run)

    def write(self, record: dict[str, Any]) -> None:
        self.handle.write(json.dumps(record) + "\n")
        self.handle.flush()

    def close(self) -> None:
        self.handle.close()


def run_record(**facts: Any) -> dict[str, Any]:
    """run.json's contents: the run's ``facts`` (its configuration, algorithm, overrides,
    spaces, network, seed, resumes, replay size), with where and from what code it runs."""
    return {
        **facts,
        "versions": package_versions(),
        "commit": git_commit(),
        "host": platform.node(),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def life_record(
    step: int,
    device: str,
    precision: str,
    restored: dict[str, bool] | None,
    warm: int,
    members: int = 1,
) -> dict[str, Any]:
    """One life of a run (its start, or a resume from ``step``), for its provenance: the
    device and precision it learns in, and what of the checkpoint it resumed from it restored
    (``restored``: None for a run's start). A target network or an optimiser not restored
    starts afresh; a replay not restored is refilled for ``warm`` steps before learning goes
    on; episodes under way not restored (arenas on a server, a foreign environment, a
    checkpoint from before exact resume) restart. A resume that restored all of them goes on
    exactly as the run never stopped would have. ``members``: the runs this life trained
    beside as members of one learner (itself included; 1: a lone run)."""
    return {
        "from_step": step,
        "members": members,
        "device": device,
        "precision": precision,
        "target_restored": None if restored is None else restored["target"],
        "optimizer_restored": None if restored is None else restored["optimizer"],
        "replay_restored": None if restored is None else restored["replay"],
        "refill_steps": None if restored is None else (0 if restored["replay"] else warm),
        "arenas_restored": None if restored is None else restored.get("arenas", False),
    }
