"""What a trainer's Rerun recording costs in resident memory over time, footer on and off.

The soak (``bench/reliability/soak.py``) saw every learning trainer's memory creep by a few
tenths of a MiB a minute. This bench isolates the trainer's recording from the rest of the
trainer: two processes side by side, each logging what ``overtake-train`` logs to its
``trainer.rrd`` (``TrainingRecording``: environment 0's view every ``--record-every`` steps
with a real observation of the preset, an episode's metrics every ``--episode-every-s``, a
learning line every ``--log-every`` steps) at the pace of a soak trainer (``--steps-per-s``),
through the trainer's own ``open_recording`` (file sink, its flush tick), one with Rerun's
footer and one without. Each samples its resident memory every ``--sample-every-s``; the figure
is each one's least-squares slope after ``--warmup-minutes``, in MiB a minute.

    .venv/bin/python -m bench.reliability.recording_memory [--minutes 10] [--json PATH]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from bench.harness import write_report


@dataclass(frozen=True)
class RecordingMemoryConfig:
    minutes: float = 10.0
    steps_per_s: float = 10.0
    """environment steps a second of the simulated trainer (a soak learner's pace)"""
    record_every: int = 10
    """overtake-train's default: environment 0's view every 10 steps"""
    episode_every_s: float = 30.0
    log_every: int = 1000
    sample_every_s: float = 30.0
    warmup_minutes: float = 2.0
    preset: str = "min2018"
    json: Path | None = None
    child: str = ""
    """internal: run one writer ("footer" or "no-footer") writing to --rrd"""
    rrd: Path | None = None


def rss_mib() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS in /proc/self/status")


def writer(config: RecordingMemoryConfig) -> None:
    """One process: log as a trainer does for ``minutes``; one JSON sample per line."""
    from overtake.protocol import ACTION_NAMES
    from overtake.server.engine.env import HighwayVectorEnv
    from overtake.trainers.run.visual import TrainingRecording, training_blueprint
    from overtake.viz.recording import RecordingConfig, close_recording, open_recording

    assert config.rrd is not None
    env = HighwayVectorEnv(num_envs=1, preset=config.preset)
    obs, _ = env.reset(seed=0)
    frame = {k: v[0] for k, v in obs.items()}
    ego_fields = env.behaviour_spec.observation("ego").columns
    env.close()
    recording = open_recording(
        "overtake",
        RecordingConfig(sink="file", rrd=config.rrd),
        config.rrd,
        training_blueprint("run"),
        footer=config.child == "footer",
    )
    assert recording is not None
    view = TrainingRecording(recording.stream, "run", ego_fields=ego_fields)
    rng = np.random.default_rng(0)
    terms = {"speed": 0.5, "collision": 0.0, "lane_change": -0.1}
    start = time.monotonic()
    next_sample = next_episode = 0.0
    step = 0
    try:
        while (now := time.monotonic() - start) < config.minutes * 60:
            if now >= next_sample:
                print(json.dumps({"t_s": now, "rss_mib": rss_mib()}), flush=True)
                next_sample += config.sample_every_s
            step += config.record_every
            q = rng.normal(size=len(ACTION_NAMES)).astype(np.float32)
            view.car_view(step, frame, int(rng.integers(len(ACTION_NAMES))), q, 0.4, terms)
            if step % config.log_every == 0:
                view.learning(
                    step, {"loss": 0.1, "epsilon": 0.5, "q_taken": 1.0, "steps_per_s": 10.0}
                )
            if now >= next_episode:
                view.episode(step, {"return": 10.0, "avg_speed_kmh": 90.0, "collisions": 0.0})
                next_episode += config.episode_every_s
            # The pace of a trainer: one view every record_every steps.
            time.sleep(max(0.0, start + step / config.steps_per_s - time.monotonic()))
    finally:
        close_recording(recording)


def slope_mib_per_min(samples: list[dict[str, float]], warmup_s: float) -> float:
    judged = [s for s in samples if s["t_s"] >= warmup_s]
    if len(judged) < 3:
        raise RuntimeError(f"{len(judged)} samples after the warm-up: run longer")
    minutes = np.array([s["t_s"] for s in judged]) / 60.0
    return float(np.polyfit(minutes, np.array([s["rss_mib"] for s in judged]), 1)[0])


def main(config: RecordingMemoryConfig) -> dict[str, object]:
    if config.child:
        writer(config)
        return {}
    results: dict[str, object] = {}
    with tempfile.TemporaryDirectory() as tmp:
        procs = {}
        for variant in ("footer", "no-footer"):
            procs[variant] = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "bench.reliability.recording_memory",
                    "--child",
                    variant,
                    "--rrd",
                    str(Path(tmp) / f"{variant}.rrd"),
                    "--minutes",
                    str(config.minutes),
                    "--steps-per-s",
                    str(config.steps_per_s),
                    "--record-every",
                    str(config.record_every),
                    "--sample-every-s",
                    str(config.sample_every_s),
                    "--preset",
                    config.preset,
                ],
                stdout=subprocess.PIPE,
                text=True,
                cwd=Path(__file__).resolve().parents[2],
            )
        for variant, proc in procs.items():
            out, _ = proc.communicate(timeout=config.minutes * 60 + 300)
            if proc.returncode != 0:
                raise RuntimeError(f"the {variant} writer exited with {proc.returncode}")
            samples = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
            size = (Path(tmp) / f"{variant}.rrd").stat().st_size
            results[variant] = {
                "first_mib": round(samples[0]["rss_mib"], 1),
                "last_mib": round(samples[-1]["rss_mib"], 1),
                "slope_mib_per_min": round(
                    slope_mib_per_min(samples, config.warmup_minutes * 60), 3
                ),
                "rrd_mb": round(size / 1e6, 1),
                "samples": samples,
            }
    for variant in ("footer", "no-footer"):
        r = results[variant]
        assert isinstance(r, dict)
        print(
            f"{variant:>9}: {r['first_mib']} -> {r['last_mib']} MiB, "
            f"{r['slope_mib_per_min']:+.3f} MiB/min after the warm-up, .rrd {r['rrd_mb']} MB"
        )
    report = {"config": {k: str(v) for k, v in vars(config).items()}, "results": results}
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main(tyro.cli(RecordingMemoryConfig))
