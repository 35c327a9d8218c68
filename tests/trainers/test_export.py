"""``overtake-export`` and ``overtake-drive --onnx``: a trained Q-network leaves PyTorch as ONNX,
matches PyTorch on recorded observations, and drives with ONNX Runtime alone, in step or on the
wall clock."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from overtake.cli import UsageError
from overtake.client.episodes.drive import DriveConfig
from overtake.client.episodes.drive import main as drive
from overtake.client.episodes.runner import RealTime, run_episodes
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.policies.onnx_policy import read_metadata
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.evaluate import main as evaluate
from overtake.trainers.export import ExportConfig
from overtake.trainers.export import main as export
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME
from overtake.trainers.train import COMMAND as train_command

from tests.support.remote import child_env

pytest.importorskip("onnxruntime", reason="onnxruntime is not installed (the onnx extra)")
pytest.importorskip("onnxscript", reason="onnxscript is not installed (the export extra)")

ROOT = Path(__file__).resolve().parents[2]
SMALL = [
    "--total-steps", "120", "--num-envs", "2", "--learning-starts", "48", "--replay-size", "600",
    "--log-every", "60", "--torch-threads", "1", "--no-progress", "--sink", "off",
    "--set", "episode.max_decisions=40",
]  # fmt: skip


# Three small runs: Min et al.'s camera + LIDAR network (convolutions and an LSTM), Ho's
# network on the occupancy grid, and QR-DQN (a quantile head, its Q-values the quantiles' mean).
RUNS = {
    "min2018": ("min2018", ["--inputs", "both"]),
    "ho2018": ("ho2018", ["--inputs", "grid"]),
    "qr": ("min2018", ["--inputs", "lidar", "--algo", "qr", "--quantiles", "11"]),
}


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    runs = {}
    for name, (preset, options) in RUNS.items():
        run_dir = tmp_path_factory.mktemp(name) / "run"
        train_command.run(["--preset", preset, *options, "--run-dir", str(run_dir), *SMALL])
        runs[name] = run_dir
    return runs


@pytest.mark.timeout(300)
@pytest.mark.parametrize("run", sorted(RUNS))
def test_the_exported_model_matches_pytorch_and_drives_as_it_does(trained, run, tmp_path):
    preset = RUNS[run][0]
    checkpoint = trained[run] / CHECKPOINT_NAME
    out = tmp_path / "policy.onnx"
    report = export(ExportConfig(checkpoint=checkpoint, out=out, check_decisions=40))
    assert report["max_abs_diff"] <= 1e-4 and report["same_actions"] == 1.0
    assert report["checked_decisions"] == 40
    meta = read_metadata(out)
    assert meta["preset"] == preset and meta["stack"] == 4
    # The same fixed-seed episodes, driven by PyTorch (overtake-eval) and by ONNX Runtime
    # (overtake-drive --onnx): the same decisions, so the same metrics to the last digit
    # (both deciding as in training: overtake-eval would evaluate ho2018 every frame).
    episodes = {"episodes": 2, "scenario": Scenario(max_decisions=25), "seed": 3}
    by_torch = evaluate(EvalConfig(checkpoint=checkpoint, paper_evaluation=False, **episodes))
    by_torch = by_torch["episodes"]
    by_onnx = drive(DriveConfig(onnx=out, **episodes))
    for name in ("avg_speed_kmh", "lane_changes", "distance_m", "return"):
        assert by_onnx[name]["mean"] == pytest.approx(np.mean([r[name] for r in by_torch]))


@pytest.mark.timeout(300)
def test_onnx_drives_with_pytorch_absent(trained, tmp_path):
    out = tmp_path / "policy.onnx"
    export(ExportConfig(checkpoint=trained["ho2018"] / CHECKPOINT_NAME, out=out, check_decisions=0))
    table = tmp_path / "table.json"
    # `import torch` fails in this process, as on a machine without PyTorch.
    program = (
        "import sys\n"
        "class NoTorch:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'torch':\n"
        "            raise ImportError('PyTorch is not installed here')\n"
        "sys.meta_path.insert(0, NoTorch())\n"
        "from overtake.client.episodes.drive import COMMAND\n"
        f"COMMAND.run(['--onnx', {str(out)!r}, '--episodes', '2', '--max-decisions', '15', "
        f"'--json-out', {str(table)!r}])\n"
        "assert not any(m.split('.')[0] == 'torch' for m in sys.modules)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", program],
        capture_output=True,
        text=True,
        timeout=120,
        env=child_env(),
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    written = json.loads(table.read_text())
    assert written["policy"] == f"onnx:{out}" and written["preset"] == "ho2018"
    assert len(written["episodes"]) == 2


def test_a_model_for_another_preset_is_refused_naming_both(trained, tmp_path):
    out = tmp_path / "ho.onnx"
    export(ExportConfig(checkpoint=trained["ho2018"] / CHECKPOINT_NAME, out=out, check_decisions=0))
    with pytest.raises(UsageError, match=r"reads observation 'grid'.*min2018.*preset ho2018"):
        drive(
            DriveConfig(onnx=out, episodes=1, scenario=Scenario(preset="min2018", max_decisions=2))
        )
    with pytest.raises(UsageError, match=r"'grid' of preset ho2018 is .*built for"):
        drive(
            DriveConfig(
                onnx=out, episodes=1, scenario=Scenario(max_decisions=2, set=("grid.cells=30",))
            )
        )


def test_a_file_that_is_not_an_exported_policy_is_refused(tmp_path):
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a model")
    with pytest.raises(UsageError, match="not an ONNX model ONNX Runtime can load"):
        read_metadata(garbage)
    with pytest.raises(UsageError, match="no ONNX model at"):
        read_metadata(tmp_path / "missing.onnx")


def test_a_failed_check_writes_nothing(trained, tmp_path):
    out = tmp_path / "policy.onnx"
    with pytest.raises(UsageError, match="does not match PyTorch.*nothing written"):
        export(
            ExportConfig(
                checkpoint=trained["ho2018"] / CHECKPOINT_NAME,
                out=out,
                check_decisions=8,
                tolerance=-1.0,  # no difference is small enough
            )
        )
    assert list(tmp_path.iterdir()) == []


def test_on_the_wall_clock_a_slow_decision_is_late_and_the_car_keeps():
    envs = Where().open("ho2018", {"episode.max_decisions": 12}, 1)
    period = envs.decision_period_s  # 0.08 s: Ho's 4 frames of 1/50 s
    calls = []

    def slow_every_third(obs, info, starting):
        calls.append(time.perf_counter())
        if len(calls) % 3 == 0:
            time.sleep(2.5 * period)  # thinking past two ticks: both go by with keep
        return np.full(1, 1, dtype=np.int64)  # accelerate

    clock = RealTime(period_s=period)
    try:
        rows, decisions, _ = run_episodes(envs, slow_every_third, 1, seed=0, realtime=clock)
    finally:
        envs.close()
    assert decisions == clock.decisions >= 12
    # Each slow call lets at least two ticks go by (more on a loaded machine).
    assert 2 <= clock.late < clock.decisions
    assert clock.percentile_ms(99) >= 2.5 * period * 1e3
    # Ticks are a period apart: a fast policy waits for the wall clock.
    assert np.diff(calls[:2])[0] >= period * 0.9
    assert rows[0]["decisions"] == 12
