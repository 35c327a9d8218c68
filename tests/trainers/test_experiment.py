"""overtake-experiment: the registry, its checks, the command lines it runs, the curves' and
the table's figures, and one tiny experiment run end to end: killed mid-training, started again
(it continues from the checkpoints) and once more (it does nothing but write the outputs)."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tyro

from overtake.cli import UsageError
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.wire.remote_config import RemoteConfig
from overtake.ipc.transport import SecurityConfig
from overtake.protocol.vocabulary import WATCH_SETTING
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.experiment import (
    COMMAND,
    EXPERIMENTS,
    LIVES_NAME,
    ExperimentConfig,
    ExperimentError,
    ExperimentRun,
    Schedule,
    command_args,
    episode_statistics,
    keep_evidence,
    learning_curves,
    main,
    make_plan,
    note_life,
    reference_policies,
    seed_order,
    seed_statistics,
    train_command,
    training_episodes,
)
from overtake.trainers.experiment.command import hours_estimate
from overtake.trainers.experiment.files import LOCK_NAME, lock
from overtake.trainers.experiment.launcher import LocalLauncher
from overtake.trainers.learning.learner import DQNConfig
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import COMMAND as TRAIN
from overtake.trainers.train import TrainConfig
from overtake.viz.recording import RecordingConfig

from tests.support.remote import wait_until

ROOT = Path(__file__).resolve().parents[2]
# The killed-experiment fixture (``tiny``), which the first test to use it pays for, takes 20-40 s
# on an idle machine, and took more than the suite's 300 s beside a training run on both cores.
pytestmark = pytest.mark.timeout(600)

# --- the registry and the checks ---------------------------------------------------------------


def test_min2018_table3_lists_the_papers_rows_densities_and_references():
    experiment = EXPERIMENTS["min2018-table3"]
    rows = {(row.label, row.algo, row.inputs, row.seeds) for row in experiment.rows}
    # The sensor rows with the paper's algorithm (Double + Dueling), and DQN and Double DQN
    # beside them for the algorithm comparison, two seeds each.
    assert rows == {
        ("dqn-both", "dqn", "both", 2),
        ("ddqn-both", "ddqn", "both", 2),
        ("dueling-both", "dueling", "both", 2),
        ("dueling-camera", "dueling", "camera", 2),
        ("dueling-lidar", "dueling", "lidar", 2),
    }
    assert experiment.densities == ("light", "medium", "heavy")
    assert experiment.references == ("rule", "random", "idle", "planner")
    assert experiment.total_steps >= 200_000 and experiment.eval_episodes >= 50


def test_the_schedule_scales_the_papers_settings_to_the_budget():
    schedule = Schedule.for_budget(200_000)
    assert schedule == Schedule(
        learning_starts=10_000,
        epsilon_decay_steps=66_666,
        target_update_steps=2_000,
        replay_size=100_000,
        checkpoint_every=10_000,
    )
    # At the authors' notebook's budget (the paper states none): its settings, apart from the
    # epsilon decay (a third).
    notebook = Schedule.for_budget(1_000_000)
    defaults = DQNConfig()
    assert notebook.learning_starts == defaults.learning_starts
    assert notebook.target_update_steps == defaults.target_update_steps
    assert notebook.replay_size == defaults.replay_size


@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({"experiment": "min2019-table9"}, r"unknown experiment 'min2019-table9': expected one "
         r"of min2018-table3"),
        ({"experiment": "min2018-safe-both"}, r"experiment 'min2018-safe-both' is retired "
         r"\(issue 56\).*: overtake-experiment min2018-table3 --rows dueling-both$"),
        ({"jobs": 0}, r"--jobs must be >= 1, got 0"),
        ({"total_steps": 0}, r"--total-steps must be >= 1, got 0"),
        ({"seeds": -1}, r"--seeds must be >= 1, got -1"),
        ({"eval_episodes": 0}, r"--eval-episodes must be >= 1, got 0"),
        ({"rows": ("ddqn-radar",)}, r"unknown row\(s\) ddqn-radar of min2018-table3: expected "
         r"some of dqn-both, ddqn-both"),
        ({"references": ("rule", "psychic")}, r"reference policy psychic unknown to "
         r"overtake-eval --policy \(it has rule, random"),
    ],
)  # fmt: skip
def test_bad_options_are_refused_naming_what_was_expected(changes, expected):
    config = dataclasses.replace(
        ExperimentConfig(experiment="min2018-table3", references=("rule",)), **changes
    )
    with pytest.raises(UsageError, match=expected):
        make_plan(config)


def test_the_command_exits_with_the_message(capsys):
    with pytest.raises(SystemExit) as exit_info:
        COMMAND.run(["min2018-table3", "--jobs", "0", "--references", "rule"])
    assert exit_info.value.code == "overtake-experiment: --jobs must be >= 1, got 0"
    with pytest.raises(SystemExit) as exit_info:
        COMMAND.run(["nope"])
    assert "unknown experiment 'nope'" in str(exit_info.value.code)


def test_without_a_name_nothing_starts_and_each_experiment_says_how_long(capsys, tmp_path):
    """Hours of both cores start only when asked for by name."""
    COMMAND.run(["--out", str(tmp_path / "exp")])
    said = capsys.readouterr().out
    for name in EXPERIMENTS:
        assert name in said
    assert said.count("hours on a 2-core machine") == len(EXPERIMENTS)
    assert "name one to run it" in said
    assert not (tmp_path / "exp").exists()
    experiment = EXPERIMENTS["min2018-table3"]
    assert hours_estimate(experiment, experiment.total_steps // 10).startswith("about 42 minutes")


def test_reference_policies_are_read_from_overtake_eval():
    assert {"rule", "random"} <= set(reference_policies())


# --- the command lines --------------------------------------------------------------------------


def parse(config_type: type, args: list[str]) -> Any:
    return tyro.cli(config_type, args=args, config=(tyro.conf.OmitArgPrefixes,))


def test_each_runs_command_line_parses_back_to_its_training_configuration(tmp_path):
    config = ExperimentConfig(
        experiment="min2018-table3",
        out=tmp_path,
        jobs=3,
        set=("episode.max_decisions=40", "camera.rgb=true"),
        references=("rule",),
        record_training=True,
        where=Where(
            connect=("tcp/127.0.0.1:7447",),
            link=RemoteConfig(
                security=SecurityConfig(user="trainer", tls_root_ca=tmp_path / "ca.pem")
            ),
        ),
    )
    plan = make_plan(config)
    assert [run.name for run in plan.runs] == [
        "dqn-both-seed0",
        "dqn-both-seed1",
        "ddqn-both-seed0",
        "ddqn-both-seed1",
        "dueling-both-seed0",
        "dueling-both-seed1",
        "dueling-camera-seed0",
        "dueling-camera-seed1",
        "dueling-lidar-seed0",
        "dueling-lidar-seed1",
    ]
    for run in plan.runs:
        assert parse(TrainConfig, command_args(run.train, TrainConfig())) == run.train
        assert TRAIN.parse(train_command(run.train)[3:]) == run.train
    train = plan.runs[5].train
    assert (train.algo, train.inputs, train.seed, train.run_dir) == (
        "dueling",
        "both",
        1,
        tmp_path / "dueling-both-seed1",
    )
    assert train.resume_if_found and not train.progress and train.where == config.where
    assert train.dqn.learning_starts == Schedule.for_budget(200_000).learning_starts
    assert train.recording == RecordingConfig(sink="file", record_every=10)


def test_ho2018_table8_runs_train_ho_s_networks_with_the_presets_settings(tmp_path):
    plan = make_plan(ExperimentConfig(experiment="ho2018-table8", out=tmp_path, seeds=1))
    assert [run.name for run in plan.runs] == [
        "baseline-seed0",
        "proposed-lr0.0001-seed0",
        "proposed-lr0.00025-seed0",
        "proposed-lr0.0005-seed0",
        "proposed-lr0.00075-seed0",
    ]
    for run in plan.runs:
        # The command names the preset, whose training is overtake-train's default then.
        command = train_command(run.train)[3:]
        assert command[:2] == ["--preset", "ho2018"]
        assert TRAIN.parse(command) == run.train
        assert (run.train.algo, run.train.inputs) == ("dqn", "grid")
        dqn = run.train.dqn
        assert dqn.optimizer == "tf-rmsprop" and dqn.loss == "mse" and dqn.train_every == 1
        assert (dqn.rmsprop_alpha, dqn.rmsprop_eps, dqn.rmsprop_centered) == (0.9, 1e-10, False)
    assert [run.train.dqn.network for run in plan.runs] == ["baseline"] + ["proposed"] * 4
    assert [run.train.dqn.learning_rate for run in plan.runs] == [
        0.0005, 0.0001, 0.00025, 0.0005, 0.00075
    ]  # fmt: skip
    assert plan.eval_episodes == 200 and "planner" not in plan.references
    # Table 6's schedule as it is, with his budget of 2,000 episodes of 1,000 decisions; a
    # smaller --total-steps stops it early and changes nothing else.
    for total in (None, 500_000):
        config = ExperimentConfig(experiment="ho2018-table8", out=tmp_path, total_steps=total)
        dqn = make_plan(config).runs[0].train.dqn
        assert (dqn.learning_starts, dqn.epsilon_decay_steps) == (100_000, 2_000_000)
        assert (dqn.target_update_steps, dqn.replay_size) == (10_000, 1_000_000)
    assert EXPERIMENTS["ho2018-table8"].total_steps == 2_000_000
    assert all(row.seeds == 2 for row in EXPERIMENTS["ho2018-table8"].rows)


def test_an_evaluations_command_line_parses_back_to_its_configuration(tmp_path):
    evaluation = EvalConfig(
        checkpoint=tmp_path / "run" / CHECKPOINT_NAME,
        episodes=50,
        seed=1_000,
        json_out=tmp_path / "out.json",
        name="ddqn-both",
        scenario=Scenario(traffic="heavy", set=("episode.max_decisions=30",), max_decisions=30),
    )
    assert parse(EvalConfig, command_args(evaluation, EvalConfig())) == evaluation


# --- curves and statistics ----------------------------------------------------------------------


def episode(step: int, speed: float) -> dict[str, Any]:
    return {"kind": "episode", "step": step, "avg_speed_kmh": speed, "return": speed / 10}


def append(path: Path, records: list[dict[str, Any]], cut: str = "") -> None:
    with open(path, "a", encoding="utf-8") as handle:
        handle.writelines(json.dumps(r) + "\n" for r in records)
        handle.write(cut)


def test_the_curves_leave_out_the_episodes_a_resume_redid(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    metrics = run / "metrics.jsonl"
    note_life(run, 0)
    # First life: checkpoints at 100; episodes up to 150, and a line cut by the kill.
    append(metrics, [episode(50, 1), {"kind": "train", "step": 100}, episode(100, 2)])
    append(metrics, [episode(120, 3), episode(150, 4)], cut='{"kind": "epis')
    note_life(run, 100)
    append(metrics, [episode(130, 5), episode(200, 6)])
    # A third life that starts over (no checkpoint was left): everything before goes.
    assert [e["avg_speed_kmh"] for e in training_episodes(run)] == [1, 2, 5, 6]
    note_life(run, 0)
    append(metrics, [episode(60, 7)])
    assert [e["avg_speed_kmh"] for e in training_episodes(run)] == [7]
    assert len((run / LIVES_NAME).read_text().splitlines()) == 3


def test_a_run_not_started_by_an_experiment_keeps_all_its_episodes(tmp_path):
    append(tmp_path / "metrics.jsonl", [episode(10, 1), episode(20, 2)])
    assert [e["step"] for e in training_episodes(tmp_path)] == [10, 20]


def test_learning_curves_average_each_bin_over_the_rows_runs():
    curves = learning_curves(
        {
            "a": [episode(10, 40), episode(20, 50), episode(90, 60)],
            "b": [episode(30, 70)],
        },
        total_steps=100,
        bins=2,
    )
    assert curves["bin_end_step"] == [50, 100]
    speed = curves["avg_speed_kmh"]
    assert speed["mean"] == [pytest.approx(160 / 3), 60.0]
    assert speed["run_min"] == [45.0, 60.0] and speed["run_max"] == [70.0, 60.0]
    empty = learning_curves({"a": []}, total_steps=100, bins=2)
    assert empty["return"]["mean"] == [None, None]


def metrics(speed: float, collisions: float, decisions: float) -> dict[str, float]:
    return {
        "avg_speed_kmh": speed,
        "lane_changes": 1.0,
        "overtakes": 2.0,
        "collisions": collisions,
        "emergency_brakes": 0.0,
        "distance_m": 100.0,
        "return": 3.0,
        "decisions": decisions,
        "traffic_cars": 10.0,
    }


def test_statistics_of_episodes_and_of_seeds():
    stats = episode_statistics([metrics(50, 0, 1000), metrics(60, 1, 500)])
    assert stats["avg_speed_kmh"] == {"mean": 55.0, "std": 5.0}
    assert stats["collisions_per_1000_decisions"] == {"mean": 1.0, "std": 1.0}
    assert stats["pooled_collisions_per_1000_decisions"] == pytest.approx(1000 / 1500)
    assert stats["episodes"] == 2
    other = episode_statistics([metrics(40, 0, 1000)])
    seeds = seed_statistics([stats, other])
    assert seeds["avg_speed_kmh"] == {"means": [55.0, 40.0], "std": 7.5}


# --- a tiny experiment, end to end --------------------------------------------------------------

BUDGET = 400
NUM_ENVS = 2
ROWS = ("dueling-lidar", "dqn-both")
TINY = (
    [
        "min2018-table3",
        "--rows",
        *ROWS,
        "--seeds",
        "1",
        "--total-steps",
        str(BUDGET),
        "--num-envs",
        str(NUM_ENVS),
    ]
    + ["--learning-starts", "32", "--replay-size", "400", "--checkpoint-every", "50"]
    + ["--references", "rule", "random", "--densities", "light", "--jobs", "2"]
    + ["--eval-episodes", "2", "--eval-max-decisions", "30", "--curve-bins", "8"]
    # Short episodes, so that the training logs some; a small camera and LIDAR, so that a
    # step costs little.
    + ["--set", "episode.max_decisions=30", "camera.width_px=36", "camera.height_px=36"]
    + ["lidar.ray_count=36", "--progress-every-s", "600"]
)


def alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, exited but not yet reaped, does not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def end(pid: int) -> None:
    """Kill ``pid`` if it still runs."""
    if alive(pid):
        os.kill(pid, signal.SIGKILL)


def partial_checkpoint(out: Path) -> bool:
    for row in ROWS:
        path = out / f"{row}-seed0" / CHECKPOINT_NAME
        if path.exists() and 0 < load_checkpoint(path).step < BUDGET:
            return True
    return False


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Any]:
    """The tiny experiment: started as a command and killed once a run has a checkpoint short
    of the budget, started again in this process (it finishes), and once more."""
    out = tmp_path_factory.mktemp("experiment") / "table"
    args = ["--out", str(out), *TINY]
    command = [sys.executable, "-m", "overtake.trainers.experiment", *args]
    killed = subprocess.Popen(
        command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    children: list[int] = []
    try:
        wait_until(lambda: partial_checkpoint(out), 120, "a checkpoint short of the budget")
        os.kill(killed.pid, signal.SIGKILL)
        killed.wait(timeout=30)
        children = [int(p.read_text()) for p in out.rglob("*.pid")]
        # The trainers die with the experiment (they get SIGTERM when it dies).
        wait_until(lambda: not any(alive(pid) for pid in children), 30, "the trainers to end")
    finally:
        end(killed.pid)
        killed.wait(timeout=30)
        for pid in children:
            end(pid)
    at_kill = {
        row: load_checkpoint(path).step
        for row in ROWS
        if (path := out / f"{row}-seed0" / CHECKPOINT_NAME).exists()
    }
    config = parse(ExperimentConfig, args)
    second = main(config)
    third = main(config)
    return {"out": out, "at_kill": at_kill, "second": second, "third": third, "config": config}


def test_a_killed_experiment_continues_each_run_from_its_checkpoint(tiny):
    out, at_kill = tiny["out"], tiny["at_kill"]
    assert any(0 < step < BUDGET for step in at_kill.values())
    assert sorted(tiny["second"]["trained"]) == sorted(f"{row}-seed0" for row in ROWS)
    # Every run ends at its budget exactly, however its episodes and its resume fell.
    final = {row: load_checkpoint(out / f"{row}-seed0" / CHECKPOINT_NAME).step for row in ROWS}
    assert all(step == BUDGET for step in final.values())
    for row, step in at_kill.items():
        run = out / f"{row}-seed0"
        if step < BUDGET:
            resumed = json.loads((run / "run-resume-1.json").read_text())
            assert resumed["resumed_at_step"] == step
        lives = [json.loads(line) for line in (run / LIVES_NAME).read_text().splitlines()]
        assert [life["from_step"] for life in lives] == [0, step]
    assert sorted(tiny["second"]["evaluated"]) == [
        f"dqn-both-seed0@{BUDGET} light",
        f"dueling-lidar-seed0@{BUDGET} light",
        "random light",
        "rule light",
    ]


def test_running_it_again_trains_and_evaluates_nothing(tiny):
    assert tiny["third"]["trained"] == [] and tiny["third"]["evaluated"] == []
    assert not list(tiny["out"].rglob("*.pid")) and not list(tiny["out"].rglob("*.tmp"))


def test_the_table_holds_every_row_and_reference_with_finite_figures(tiny):
    out = tiny["out"]
    result = json.loads((out / "table.json").read_text())
    assert result["experiment"] == "min2018-table3"
    assert result["config"]["total_steps"] == BUDGET
    assert result["versions"]["torch"] and result["versions"]["matplotlib"]
    assert result["commit"]
    [light] = result["densities"].values()
    assert [row["label"] for row in light["rows"]] == ["dqn-both", "dueling-lidar"]
    assert [ref["policy"] for ref in light["references"]] == ["rule", "random"]
    for entry in light["rows"] + light["references"]:
        assert entry["summary"]["episodes"] == 2
        for name in ("avg_speed_kmh", "lane_changes", "collisions_per_1000_decisions", "return"):
            assert math.isfinite(entry["summary"][name]["mean"])
            assert math.isfinite(entry["summary"][name]["std"])
    for row in light["rows"]:
        [run] = row["runs"]
        assert run["checkpoint_step"] == BUDGET
        assert row["seeds"]["avg_speed_kmh"]["means"] == [run["summary"]["avg_speed_kmh"]["mean"]]
    table = (out / "table.md").read_text()
    assert "## Light traffic" in table
    for name in (
        "| dqn-both | DQN | camera + LIDAR | 1 |",
        "| dueling-lidar | Dueling DQN | LIDAR |",
    ):
        assert name in table
    assert "| rule | reference policy |" in table and "| random | reference policy |" in table
    assert "nan" not in table.lower()


def test_every_evaluation_keeps_its_episodes_and_the_table_names_the_collisions(tiny):
    from overtake.client.episodes.records import read_records
    from overtake.trainers.episode_replay import ReplayConfig
    from overtake.trainers.episode_replay import main as replay

    out = tiny["out"]
    [light] = json.loads((out / "table.json").read_text())["densities"].values()
    table = (out / "table.md").read_text()
    entries = [run for row in light["rows"] for run in row["runs"]] + light["references"]
    if any(entry["collision_episodes"] for entry in entries):
        assert "<summary>Episodes with collisions, and the command that replays them" in table
    else:
        assert "Episodes with collisions: none." in table
    for entry in entries:
        # Named within the experiment's directory, so that its kept copy names them too.
        assert not Path(entry["episodes_record"]).is_absolute()
        _, episodes = read_records(out / entry["episodes_record"])
        assert len(episodes) == 2
        crashed = [e.episode for e in episodes if e.collisions]
        assert crashed == entry["collision_episodes"]
        if crashed:
            assert f"overtake-replay {entry['episodes_record']} --collisions" in table
    # A checkpoint's episodes replay with its Q-values, each of its choices checked.
    [run] = light["rows"][1]["runs"]
    rrd = out.parent / "replayed.rrd"
    replayed = replay(
        ReplayConfig(
            record=out / run["episodes_record"], recording=RecordingConfig(sink="file", rrd=rrd)
        )
    )
    assert replayed["episodes"] == [0, 1]
    import rerun as rr

    logged = {c.entity_path for c in rr.chunk.RrdReader(str(rrd)).stream().to_chunks()}
    assert {
        "/episode/car/q/keep",
        "/episode/car/lidar/hits",
        "/world/episode/arena0/road/cars",
    } <= logged
    from tests.support.remote import blueprint_texts

    reader = rr.chunk.RrdReader(str(rrd))
    views = set().union(*(blueprint_texts(reader, store) for store in reader.blueprints()))
    assert any(name.endswith(": Q-values") for name in views)


def test_the_curves_are_a_png_and_a_rerun_recording_of_every_row(tiny):
    import rerun as rr

    out = tiny["out"]
    png = (out / "curves.png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 10_000
    curves = json.loads((out / "table.json").read_text())["curves"]
    for row in ROWS:
        assert any(v is not None for v in curves[row]["avg_speed_kmh"]["mean"])
    reader = rr.chunk.RrdReader(str(out / "curves.rrd"))
    entities = {c.entity_path for c in reader.stream().to_chunks() if not c.is_static}
    assert {f"/curves/{m}/{row}" for m in ("avg_speed_kmh", "return") for row in ROWS} <= entities
    # A row is drawn in one colour in every plot, and rows in different colours.
    colors: dict[str, set[int]] = {}
    for chunk in rr.chunk.RrdReader(str(out / "curves.rrd")).stream().to_chunks():
        if chunk.is_static and chunk.entity_path.startswith("/curves/"):
            batch = chunk.to_record_batch().to_pydict()
            row = chunk.entity_path.rsplit("/", 1)[1]
            colors.setdefault(row, set()).update(batch["SeriesLines:colors"][0])
    assert set(colors) == set(ROWS)
    assert all(len(c) == 1 for c in colors.values()), colors
    assert len({next(iter(c)) for c in colors.values()}) == len(ROWS)


def test_a_directory_refuses_a_run_with_other_training_settings(tiny):
    config = dataclasses.replace(tiny["config"], total_steps=BUDGET * 2)
    with pytest.raises(UsageError, match=rf"total_steps {BUDGET} then, {BUDGET * 2} now"):
        main(config)


def test_the_curves_plot_has_content(tiny):
    # More than a blank canvas: many distinct colours.
    from matplotlib.image import imread

    image = imread(tiny["out"] / "curves.png")
    assert len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 50


def test_work_another_invocation_did_meanwhile_is_not_done_again(tiny, capsys):
    # As if this invocation had planned while another one held every lock: its pending tasks
    # are those of a fresh start, and the other invocation has since finished all of them.
    config = tiny["config"]
    experiment = ExperimentRun(config, make_plan(config))
    pending = [experiment.train_task((run,)) for run in experiment.plan.runs]
    pending += experiment.reference_tasks()
    launcher = LocalLauncher(progress_every_s=600)
    experiment._start_ready(pending, launcher)
    assert launcher.running() == 0 and pending == []
    said = capsys.readouterr().err
    assert said.count("by another invocation") == len(ROWS) + 2


def test_a_second_invocation_in_a_running_experiments_directory_is_refused(tiny):
    # docs/experiments.md: one invocation works in a directory at a time. Held here as a
    # running invocation holds it; the second says so and touches nothing.
    out = tiny["out"]
    before = (out / "table.md").stat().st_mtime_ns
    held = lock(out / LOCK_NAME)
    assert held is not None
    try:
        refused = f"another overtake-experiment is running in {re.escape(str(out))}"
        with pytest.raises(ExperimentError, match=refused):
            main(tiny["config"])
    finally:
        os.close(held)
    assert (out / "table.md").stat().st_mtime_ns == before


def test_the_kept_evidence_is_the_table_and_curves_without_the_calm_episodes(tiny, tmp_path):
    # A record an earlier keep left there, which this table does not name, goes.
    stale = tmp_path / "kept" / "evaluations" / "gone-seed0" / "light-step1.episodes" / "x.jsonl"
    stale.parent.mkdir(parents=True)
    stale.write_text("{}\n")
    keep_evidence(tiny["out"], tmp_path / "kept")
    assert not (tmp_path / "kept" / "evaluations" / "gone-seed0").exists()
    kept = sorted(p.name for p in (tmp_path / "kept").iterdir() if p.name != "evaluations")
    assert kept == ["curves.png", "table.json", "table.md"]
    table = json.loads((tmp_path / "kept" / "table.json").read_text())
    assert table["commit"]
    # The summaries, not the episodes: each run and reference names the evaluation that
    # holds those.
    [light] = table["densities"].values()
    runs = [run for row in light["rows"] for run in row["runs"]]
    for entry in light["rows"] + light["references"] + runs:
        assert "episodes" not in entry
    for entry in light["references"] + runs:
        assert (tiny["out"] / entry["evaluation"]).exists()


def _strings(value: Any) -> list[str]:
    if isinstance(value, dict):
        return [s for item in value.values() for s in _strings(item)]
    if isinstance(value, list):
        return [s for item in value for s in _strings(item)]
    return [value] if isinstance(value, str) else []


def test_the_table_says_how_each_run_was_made_and_names_no_machine_s_directories(tiny):
    out, at_kill = tiny["out"], tiny["at_kill"]
    table = json.loads((out / "table.json").read_text())
    [light] = table["densities"].values()
    runs = {run["run"]: run for row in light["rows"] for run in row["runs"]}
    for row in ROWS:
        lives = runs[f"{row}-seed0"]["provenance"]
        # The lives cover the budget, each on this machine's CPU, from this checkout's code.
        assert lives[0]["from_step"] == 0 and lives[-1]["to_step"] == BUDGET
        assert all(a["to_step"] == b["from_step"] for a, b in itertools.pairwise(lives))
        assert {life["device"] for life in lives} == {"cpu"}
        assert all(life["commit"] == table["commit"] for life in lives)
        step = at_kill.get(row, 0)
        if 0 < step < BUDGET:  # killed part-way: a second life resumed from the checkpoint
            assert [life["from_step"] for life in lives] == [0, step]
            assert lives[1]["target_restored"] and lives[1]["optimizer_restored"]
            # Exactly: the replay's files and the episodes under way were put back too.
            assert lives[1]["replay_restored"] and lives[1]["arenas_restored"]
            assert f"- {row}-seed0: 0–{step:,} on cpu" in (out / "table.md").read_text()
            assert f"; resumed exactly {step:,}–" in (out / "table.md").read_text()
    # Each evaluation names the code that drove it (its episode record's header): this
    # checkout's, as the table's header line says.
    for entry in [*runs.values(), *light["references"]]:
        assert entry["evaluated_by"] == table["commit"]
    markdown = (out / "table.md").read_text()
    assert f"; evaluated by code {table['commit']};" in markdown
    assert "## How each run was made" in markdown
    assert "- dqn-both-seed0: 0–" in markdown and " on cpu (fp32), commit " in markdown
    # No absolute path anywhere: the run directories and the command's own are relative.
    assert not [text for text in _strings(table) if text.startswith("/")]
    assert table["plan"]["runs"]["dqn-both-seed0"]["run_dir"] == "dqn-both-seed0"


def test_the_kept_copy_holds_the_collision_episodes_of_each_record_its_table_names(tmp_path):
    from overtake.client.episodes.records import (
        EpisodeRecord,
        PolicySource,
        RecordHeader,
        read_records,
        write_records,
    )
    from overtake.protocol.vocabulary import METRIC_FIELDS

    out, keep = tmp_path / "out", tmp_path / "kept"
    header = RecordHeader("min2018", {}, {}, PolicySource("checkpoint", "x.pt", 5), "abc")

    def record(path: str, collisions: list[int]) -> str:
        episodes = [
            EpisodeRecord(
                i,
                100 + i,
                "0" * 3,
                {
                    **dict.fromkeys(METRIC_FIELDS, 0.0),
                    "decisions": 3.0,
                    "collisions": float(i in collisions),
                },
            )
            for i in range(4)
        ]
        write_records(out / path, header, episodes)
        return path

    run = {
        "run": "a-seed0",
        "episodes_record": record("evaluations/a/m.episodes/a.jsonl", [1, 3]),
        "collision_episodes": [1, 3],
    }
    calm = {
        "policy": "rule",
        "episodes_record": record("evaluations/r/m.episodes/r.jsonl", []),
        "collision_episodes": [],
    }
    table = {"densities": {"medium": {"rows": [{"runs": [run]}], "references": [calm]}}}
    (out / "table.json").write_text(json.dumps(table))
    for name in ("table.md", "curves.png"):
        (out / name).write_text(name)
    keep_evidence(out, keep)
    kept_header, kept = read_records(keep / run["episodes_record"])
    assert kept_header == header and [e.episode for e in kept] == [1, 3]
    # A checkpoint named by an absolute path within the experiment is kept relative to it.
    absolute = dataclasses.replace(
        header, policy=PolicySource("checkpoint", str(out / "a-seed0" / "checkpoint.pt"), 5)
    )
    write_records(
        out / run["episodes_record"], absolute, read_records(out / run["episodes_record"])[1]
    )
    keep_evidence(out, keep)
    assert read_records(keep / run["episodes_record"])[0].policy.name == "a-seed0/checkpoint.pt"
    assert [e.seed for e in kept] == [101, 103]
    assert not (keep / calm["episodes_record"]).exists()


def seeded_row(label: str, means: list[float]) -> dict[str, Any]:
    runs = [{"run": f"{label}-seed{i}"} for i in range(len(means))]
    return {"label": label, "runs": runs, "seeds": {"avg_speed_kmh": {"means": means}}}


def test_the_order_of_rows_is_judged_against_the_seed_spread():
    rows = [
        seeded_row("camera", [70.0, 74.0]),
        seeded_row("both", [75.0, 76.0]),
        seeded_row("lidar", [72.0, 73.0]),
        seeded_row("one-seed", [90.0]),  # a single seed has no spread: not judged
    ]
    order = {(p["higher"], p["lower"]): p["beyond_seed_spread"] for p in seed_order(rows)}
    assert order == {
        ("both", "lidar"): True,  # 75 and 76 both above 72 and 73
        ("both", "camera"): True,
        ("lidar", "camera"): False,  # means 72.5 > 72.0, but camera's 74 beats lidar's 73
    }


def test_min2018_safe_trains_the_paper_row_and_the_options_each_alone_and_together(tmp_path):
    plan = make_plan(ExperimentConfig(experiment="min2018-safe", out=tmp_path))
    trained = {
        run.name: (
            run.train.shield,
            run.train.dqn.prioritized,
            run.train.dqn.n_step,
            run.train.shield_watch,
            run.train.dqn.store_applied,
        )
        for run in plan.runs
    }
    assert trained == {
        f"{label}-seed{seed}": options
        for label, options in {
            "paper": (False, False, 1, False, False),
            "shield": (True, False, 1, False, False),
            "per-3step": (False, True, 3, False, False),
            "all": (True, True, 3, False, False),
            # Issue 46: the shield with lane changes watched through, the applied actions
            # stored; alone and with everything else.
            "watch": (True, False, 1, True, True),
            "all-watch": (True, True, 3, True, True),
        }.items()
        for seed in (0, 1)
    }
    watched = {run.name for run in plan.runs if run.train.overrides().get(WATCH_SETTING)}
    assert watched == {f"{label}-seed{s}" for label in ("watch", "all-watch") for s in (0, 1)}
    assert all((run.train.algo, run.train.inputs) == ("dueling", "lidar") for run in plan.runs)
    assert plan.total_steps == 200_000 and plan.eval_episodes == 100
    assert plan.densities == ("medium", "heavy") and plan.references == ("rule", "planner")
    # Each command line parses back to its run's configuration, options included.
    for run in plan.runs:
        assert TRAIN.parse(train_command(run.train)[3:]) == run.train
    labels = {row.label: row.options for row in EXPERIMENTS["min2018-safe"].rows}
    assert labels["all"] == "shield, prioritized replay, 3-step returns"
    assert labels["watch"] == "shield, lane changes watched through, applied actions stored"
    assert labels["paper"] == "-"


def test_min2018_notebook_trains_the_kept_dueling_row_with_three_notebook_choices(tmp_path):
    """One row: min2018-table3's dueling-both, two seeds, at its budget and schedule, with the
    notebook's Adam epsilon, squared error and update every step (and only those)."""
    plan = make_plan(ExperimentConfig(experiment="min2018-notebook", out=tmp_path))
    table3 = make_plan(
        ExperimentConfig(experiment="min2018-table3", out=tmp_path / "t3", rows=("dueling-both",))
    )
    assert [run.name for run in plan.runs] == [
        "dueling-both-notebook-seed0",
        "dueling-both-notebook-seed1",
    ]
    run, kept = plan.runs[0].train, table3.runs[0].train
    assert run.recipe == "notebook" and kept.recipe is None
    assert (run.dqn.adam_eps, run.dqn.loss, run.dqn.train_every) == (0.01, "mse", 1)
    assert dataclasses.replace(run.dqn, adam_eps=1e-8, loss="huber", train_every=4) == kept.dqn
    assert dataclasses.replace(run, recipe=None, dqn=kept.dqn, run_dir=kept.run_dir) == kept
    command = train_command(run)[3:]
    assert command[:2] == ["--recipe", "notebook"] and TRAIN.parse(command) == run
    with pytest.raises(UsageError, match="preset ho2018 has no recipes"):
        TrainConfig.for_preset("ho2018", "notebook")


def test_device_reaches_every_training_run_and_does_not_split_an_experiment_directory(tmp_path):
    from overtake.trainers.experiment import check_directory

    plan = make_plan(ExperimentConfig(experiment="min2018-table3", out=tmp_path, device="cpu"))
    assert {run.train.device for run in plan.runs} == {"cpu"}
    check_directory(plan)
    # A directory recorded when the device was part of a run's identity (ho2018-table8's runs
    # of 2026-11-25 hold "device": "cpu") accepts the same runs now.
    record = json.loads((tmp_path / "experiment.json").read_text())
    assert all("device" not in run for run in record["runs"].values())
    for run in record["runs"].values():
        run["device"] = "cpu"
    (tmp_path / "experiment.json").write_text(json.dumps(record))
    check_directory(plan)
    # Runs started on a GPU machine continue on the CPU, and the other way round; the command
    # line says where each learns.
    on_gpu = tuple(
        dataclasses.replace(run, train=dataclasses.replace(run.train, device="cuda"))
        for run in plan.runs
    )
    check_directory(dataclasses.replace(plan, runs=on_gpu))
    command = train_command(on_gpu[0].train)
    assert command[command.index("--device") + 1] == "cuda"
    assert TRAIN.parse(command[3:]) == on_gpu[0].train
    # Where what it learns changes, the directory is still refused.
    bf16 = tuple(
        dataclasses.replace(run, train=dataclasses.replace(run.train, precision="bf16"))
        for run in plan.runs
    )
    with pytest.raises(UsageError, match=r"precision 'fp32' then, 'bf16' now"):
        check_directory(dataclasses.replace(plan, runs=bf16))


@pytest.mark.parametrize("device", ["cuda", "cuda:3", "tpu"])
def test_a_device_this_machine_lacks_is_refused_before_anything_trains(tmp_path, device):
    import torch

    if device.startswith("cuda") and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(UsageError, match=rf"--device: device {device!r}"):
        make_plan(ExperimentConfig(experiment="min2018-table3", out=tmp_path, device=device))
    assert not (tmp_path / "experiment.json").exists()


def test_where_the_simulator_is_does_not_change_what_a_run_learns():
    """A restarted experiment may reach its simulator another way (every field of Where:
    endpoint, credentials, transport, the channel's spin) and still continue its runs; a
    learned setting still makes another run."""
    from overtake.trainers.config.train_config import TrainConfig
    from overtake.trainers.experiment.plan import training_identity

    base = TrainConfig()
    link = RemoteConfig(transport="zenoh", spin_s=0.0, server="sim-2", lease_s=9.0)
    elsewhere = dataclasses.replace(base, where=Where(connect=("tcp/127.0.0.1:7447",), link=link))
    assert training_identity(elsewhere) == training_identity(base)
    # A record written before the configuration held a Where keeps these settings at the top.
    from overtake.trainers.experiment.plan import learned_settings
    from overtake.trainers.run.checkpoint import plain_data

    before_where = {name: v for name, v in plain_data(base).items() if name != "where"}
    before_where |= {"connect": ["tcp/h:1"], "transport": "zenoh", "server": "sim-2", "lease_s": 9}
    assert learned_settings(before_where) == training_identity(base)
    assert training_identity(dataclasses.replace(base, num_envs=2)) != training_identity(base)
