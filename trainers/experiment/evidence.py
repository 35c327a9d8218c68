"""What an experiment's table says of how its runs were made (each run's lives: steps,
device, code, what a resume restored), and what of it is kept in git: the table, its JSON and
the curves, and the collision episodes of the records it names, with no machine's directories
in any of them."""

from __future__ import annotations

import dataclasses
import json
import os
import re
from pathlib import Path
from typing import Any

from overtake.client.episodes.records import read_records, write_records

from .files import read_json, say, write_atomic

EVIDENCE = ("table.md", "table.json", "curves.png")


def run_lives(run_dir: Path, final_step: int) -> list[dict[str, Any]]:
    """A training run's provenance: its lives (its start and each resume, from their run
    records), each with the steps it trained (up to the next life's start, the last to
    ``final_step``), the device it learned on, the commit of its code, and for a resume what
    of the checkpoint it restored (a target network or optimiser not restored started afresh;
    a replay not restored was refilled before learning went on). A life that trained no
    step of the final run (one resumed again from the same checkpoint) is left out."""
    found = []
    for path in run_dir.glob("run*.json"):
        match = re.fullmatch(r"run(?:-resume-(\d+))?\.json", path.name)
        record = read_json(path) if match else None
        if record is not None:
            found.append((int(match.group(1) or 0), record))  # type: ignore[union-attr]
    lives: list[dict[str, Any]] = []
    for _, record in sorted(found, key=lambda item: item[0]):
        life = record.get("life") or {}
        config = record.get("config") or {}
        lives.append(
            {
                "from_step": int(life.get("from_step", record.get("resumed_at_step") or 0)),
                "device": life.get("device", config.get("device")),
                "precision": life.get("precision", config.get("precision")),
                "commit": record.get("commit"),
                "started_utc": record.get("started_utc"),
                "target_restored": life.get("target_restored"),
                "optimizer_restored": life.get("optimizer_restored"),
                "replay_restored": life.get("replay_restored"),
                "refill_steps": life.get("refill_steps"),
                "arenas_restored": life.get("arenas_restored"),
                # None: a life recorded before members (issue 66), which says nothing of it.
                "members": life.get("members"),
            }
        )
    for life, following in zip(lives, [*lives[1:], None], strict=True):
        life["to_step"] = final_step if following is None else following["from_step"]
    kept = [life for life in lives if life["to_step"] > life["from_step"]]
    # A transfer done by hand before lives recorded what they restored (transfer.json).
    transfer = read_json(run_dir / "transfer.json")
    if transfer is not None and kept:
        kept[-1]["transfer"] = transfer
    return kept


def provenance_line(lives: list[dict[str, Any]]) -> str:
    """A run's lives in a line of table.md: the steps each trained, where, from which code,
    and what a resume restored or started afresh."""
    if not lives:
        return "not recorded"
    parts = []
    for number, life in enumerate(lives):
        commit = str(life.get("commit") or "unknown")
        short = commit[:7] + ("+uncommitted" if commit.endswith("+uncommitted") else "")
        text = (
            f"{life['from_step']:,}–{life['to_step']:,} on {life.get('device') or '?'} "
            f"({life.get('precision') or 'fp32'}), commit {short}"
        )
        if (life.get("members") or 1) > 1:
            text += f", one of {life['members']} members of one learner"
        if number:
            fresh = [
                what
                for key, what in (
                    ("target_restored", "target network copied from the online network"),
                    ("optimizer_restored", "optimiser started afresh"),
                )
                if life.get(key) is False
            ]
            if life.get("replay_restored") is False:
                fresh.append(f"replay refilled for {life.get('refill_steps') or 0:,} steps")
            if life.get("arenas_restored") is not True:  # before issue 56 they always did
                fresh.append("the episodes under way restarted")
            if life.get("target_restored") is None:
                fresh.append("what it restored not recorded")
            text = ("resumed " if fresh else "resumed exactly ") + text
            text += f" ({'; '.join(fresh)})" if fresh else ""
        if "transfer" in life:
            text += " (a transfer from another machine: transfer.json)"
        parts.append(text)
    return "; ".join(parts)


def portable(value: Any, root: Path) -> Any:
    """``value`` (table.json's data) with every absolute path made relative: to the
    experiment's directory ``root`` where it lies within it, else to the working directory
    where it lies within that (a repository's bench/results), else to ``root``. Kept evidence
    names no machine's directories."""
    if isinstance(value, dict):
        return {key: portable(item, root) for key, item in value.items()}
    if isinstance(value, list):
        return [portable(item, root) for item in value]
    if isinstance(value, str) and value.startswith("/") and os.path.isabs(value):
        path = Path(value)
        for base in (root.resolve(), Path.cwd().resolve()):
            if path.is_relative_to(base):
                return str(path.relative_to(base)) or "."
        return os.path.relpath(path, root.resolve())
    return value


def kept_records(table: dict[str, Any]) -> dict[str, list[int]]:
    """The episode records a table names for its collisions (paths within the experiment's
    directory) and the episodes of each that collided. A table written before records were
    named within the directory names them by absolute paths: those stay out."""
    records: dict[str, list[int]] = {}
    for density in table["densities"].values():
        entries = [run for row in density["rows"] for run in row["runs"]]
        for entry in entries + density["references"]:
            record = entry.get("episodes_record")
            if entry.get("collision_episodes") and record and not Path(record).is_absolute():
                records[record] = entry["collision_episodes"]
    return records


def keep_evidence(out: Path, keep: Path) -> None:
    """Copy an experiment's table and curves from ``out`` into ``keep``, each written whole or
    not at all, and of each episode record its table names, the episodes with a collision, at
    the same path within ``keep``: the table's replay commands play them there; a record an
    earlier keep left there that this table does not name is removed. Small: table.json
    holds summaries, the other episodes stay in the evaluations."""
    keep.mkdir(parents=True, exist_ok=True)
    for name in EVIDENCE:
        write_atomic(keep / name, (out / name).read_bytes())
    records = kept_records(json.loads((out / "table.json").read_text()))
    for relative, crashed in records.items():
        header, episodes = read_records(out / relative)
        # The checkpoint that drove, named within the experiment (a replay finds it there).
        policy = dataclasses.replace(header.policy, name=portable(header.policy.name, out))
        write_records(
            keep / relative,
            dataclasses.replace(header, policy=policy),
            [e for e in episodes if e.episode in crashed],
        )
    # A record an earlier keep copied that this table no longer names (another budget's
    # checkpoint step, a row since removed) would stand beside the evidence as if it were some.
    kept = {keep / relative for relative in records}
    evaluations = keep / "evaluations"
    for path in sorted(evaluations.rglob("*"), reverse=True) if evaluations.is_dir() else []:
        if path.is_file() and path.suffix == ".jsonl" and path not in kept:
            path.unlink()
        elif path.is_dir() and not any(path.iterdir()):
            path.rmdir()
    say(
        f"kept {', '.join(EVIDENCE)} in {keep}"
        + (f", and the collision episodes of {len(records)} episode records" if records else "")
    )
