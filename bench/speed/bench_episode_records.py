"""How large an episode record is: bytes per 1,000 decisions, and the header per file.

For every preset, the rule-based and the random driver drive episodes at heavy traffic
(``overtake-drive --episodes-out``, in process), and the record's lines are measured: the
episodes' lines (seed, actions, metrics, events) per 1,000 decisions, and the header (preset,
overrides, the resolved configuration, the policy, the commit) once per file. Sizes, not
times: it may run beside anything.

    .venv/bin/python -m bench.speed.bench_episode_records [--episodes 20] [--max-decisions 1000]
"""

from __future__ import annotations

import contextlib
import io
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path

from overtake.cli import UsageError
from overtake.client.episodes.drive import DriveConfig
from overtake.client.episodes.drive import main as drive
from overtake.client.episodes.scenario import Scenario
from overtake.server.sim.presets import PRESETS


@dataclass(frozen=True)
class RecordSizeConfig:
    episodes: int = 20
    """episodes per preset and driver"""
    max_decisions: int = 1000
    """episode length limit (a collision ends min2018's and fayjie2018's earlier)"""
    json: Path | None = None
    """also write the figures here"""


def measure(config: RecordSizeConfig) -> list[dict[str, float | str]]:
    rows: list[dict[str, float | str]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in sorted(PRESETS):
            for policy in ("rule", "random"):
                out = Path(tmp) / preset / policy
                drive_config = DriveConfig(
                    policy=policy,  # type: ignore[arg-type]
                    scenario=Scenario(
                        preset=preset, max_decisions=config.max_decisions, traffic="heavy"
                    ),
                    episodes=config.episodes,
                    episodes_out=out,
                )
                try:
                    with contextlib.redirect_stdout(io.StringIO()):
                        drive(drive_config)
                except UsageError as error:
                    # highway-env's scenes observe Kinematics only, which the rule-based
                    # driver does not read: said, and the preset's other driver measured.
                    print(f"{preset} {policy}: not driven ({error})")
                    continue
                [path] = list(out.glob("*.jsonl"))
                header, *episodes = path.read_bytes().splitlines(keepends=True)
                decisions = sum(len(json.loads(line)["actions"]) for line in episodes)
                body = sum(len(line) for line in episodes)
                rows.append(
                    {
                        "preset": preset,
                        "policy": policy,
                        "decisions": decisions,
                        "bytes_per_1000_decisions": 1000.0 * body / decisions,
                        "header_bytes": len(header),
                        "file_bytes": path.stat().st_size,
                    }
                )
    return rows


def main(config: RecordSizeConfig) -> list[dict[str, float | str]]:
    rows = measure(config)
    print(f"{'preset':<12} {'driver':<7} {'decisions':>9} {'B/1k dec.':>10} {'header B':>9}")
    for row in rows:
        print(
            f"{row['preset']:<12} {row['policy']:<7} {row['decisions']:>9} "
            f"{row['bytes_per_1000_decisions']:>10.0f} {row['header_bytes']:>9}"
        )
    if config.json is not None:
        config.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    import tyro

    main(tyro.cli(RecordSizeConfig))
