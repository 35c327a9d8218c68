"""Training and evaluation runs on the real simulator: each algorithm in process and against a
real server, overlapped remote training, baselines, the loop's budget, the evaluation table,
recordings, SIGTERM and overlap's core count.
"""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from overtake.cli import UsageError
from overtake.client.episodes.scenario import Scenario, Where
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.evaluate import main as evaluate
from overtake.trainers.learning.learner import DQNConfig
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import TrainConfig
from overtake.trainers.train import main as train
from overtake.viz.recording import RecordingConfig

from tests.support.tiny_learning import PickTheFreeLane, WatchEnvZero, tiny_dqn

torch.set_num_threads(1)


SMOKE_DQN = dict(
    learning_starts=60, replay_size=2000, target_update_steps=100, epsilon_decay_steps=200
)


@pytest.mark.parametrize("algo", ["dqn", "ddqn", "dueling", "qr"])
def test_each_algorithm_trains_in_process_and_its_checkpoint_evaluates(tmp_path, algo):
    run_dir = tmp_path / algo
    summary = train(
        TrainConfig(
            algo=algo,
            inputs="both",
            num_envs=2,
            total_steps=240,
            run_dir=run_dir,
            progress=False,
            log_every=80,
            # A small camera, so that an update costs little (about half this test's time at
            # 80 px); the preset's own network trains in test_export.
            dqn=DQNConfig(**SMOKE_DQN),
            scenario=Scenario(
                set=("episode.max_decisions=60", "camera.width_px=36", "camera.height_px=36")
            ),
        )
    )
    assert summary["steps"] >= 240 and summary["updates"] >= 40 and summary["episodes"] >= 2
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    episodes = [r for r in records if r["kind"] == "episode"]
    assert episodes and all(r["decisions"] == 60 or r["terminated"] for r in episodes)
    assert any(r["kind"] == "train" and r["loss"] is not None for r in records)
    run = json.loads((run_dir / "run.json").read_text())
    assert run["algo"]["name"] == algo and run["sim_config"]["episode"]["max_decisions"] == 60
    assert run["versions"]["torch"].startswith("2.13") and run["commit"]
    result = evaluate(
        EvalConfig(
            checkpoint=run_dir / CHECKPOINT_NAME,
            episodes=2,
            json_out=tmp_path / "eval.json",
            scenario=Scenario(max_decisions=30, traffic="light"),
        )
    )
    assert result["summary"]["episodes"] == 2
    assert result["summary"]["decisions"]["mean"] == 30
    assert result["overrides"]["traffic.density"] == "light"
    assert json.loads((tmp_path / "eval.json").read_text())["name"].startswith(f"{algo}/both")


@pytest.mark.parametrize("algo", ["dqn", "ddqn", "dueling", "qr"])
def test_each_algorithm_trains_against_a_real_server(tmp_path, shared_server, algo):
    server = shared_server
    summary = train(
        TrainConfig(
            algo=algo,
            inputs="lidar",
            num_envs=2,
            total_steps=200,
            run_dir=tmp_path / algo,
            progress=False,
            dqn=DQNConfig(**SMOKE_DQN),
            scenario=Scenario(set=("episode.max_decisions=50",)),
            where=Where(connect=(server.endpoint,)),
        )
    )
    assert summary["steps"] >= 200 and summary["updates"] >= 30 and summary["episodes"] >= 2
    run = json.loads((tmp_path / algo / "run.json").read_text())
    # lidar-only: the server was asked for the LIDAR and the ego vector, and rendered no camera
    assert not run["sim_config"]["camera"]["enabled"] and "camera.enabled" not in run["overrides"]
    assert run["config"]["where"]["connect"] == [server.endpoint]


def test_overlapped_remote_training_is_deterministic_and_lock_step_stays(tmp_path, start_server):
    """With --overlap on the learner updates while the server simulates (one group), or with
    --overlap-parts 2 the 4 arenas are two groups stepped in turn; two runs of one seed store
    the same episodes and learn the same losses either way; --overlap off is one group again,
    stepped and then learned from."""
    server = start_server("train-overlap")

    def run(name: str, overlap: str, parts: int = 1) -> tuple[dict, list[dict]]:
        summary = train(
            TrainConfig(
                algo="ddqn",
                inputs="lidar",
                num_envs=4,
                total_steps=240,
                seed=9,
                run_dir=tmp_path / name,
                progress=False,
                overlap=overlap,
                overlap_parts=parts,
                log_every=40,
                dqn=DQNConfig(**SMOKE_DQN),
                scenario=Scenario(set=("episode.max_decisions=25",)),
                where=Where(connect=(server.endpoint,)),
            )
        )
        lines = [
            {
                k: v
                for k, v in json.loads(line).items()
                if k not in ("wall_s", "steps_per_s") and not k.startswith("time_")
            }
            for line in (tmp_path / name / "metrics.jsonl").read_text().splitlines()
        ]
        return summary, lines

    one, one_lines = run("one-a", overlap="on")
    assert one["parts"] == 1 and one["steps"] == 240 and one["updates"] >= 30
    # One send per vector step, plus the last one in flight when the run ended.
    assert one["env_steps_called"] >= 240 // 4 + 1
    assert run("one-b", overlap="on")[1] == one_lines
    halves, halves_lines = run("two-a", overlap="on", parts=2)
    assert halves["parts"] == 2 and halves["steps"] == 240 and halves["updates"] >= 30
    # Every send was a round of one of the two groups; two parts of 2 arenas each.
    assert halves["env_steps_called"] >= 240 // 2
    episodes = [line for line in halves_lines if line["kind"] == "episode"]
    assert len(episodes) >= 4 and {line["env"] for line in episodes} == {0, 1, 2, 3}
    again, again_lines = run("two-b", overlap="on", parts=2)
    assert again_lines == halves_lines
    assert again["updates"] == halves["updates"]
    assert halves_lines != one_lines
    lock, lock_lines = run("lock", overlap="off", parts=2)
    assert lock["parts"] == 1 and lock["steps"] == 240
    # The learner updated at other times: before the step's transitions were stored.
    assert lock_lines != one_lines and lock_lines != halves_lines


def test_baselines_evaluate_on_the_same_seeds(tmp_path):
    rule = evaluate(
        EvalConfig(policy="rule", episodes=2, seed=5, scenario=Scenario(max_decisions=40))
    )
    again = evaluate(
        EvalConfig(policy="rule", episodes=2, seed=5, scenario=Scenario(max_decisions=40))
    )
    assert rule["episodes"] == again["episodes"]
    random = evaluate(
        EvalConfig(policy="random", episodes=2, seed=5, scenario=Scenario(max_decisions=40))
    )
    assert random["summary"]["lane_changes"]["mean"] > rule["summary"]["lane_changes"]["mean"]
    with pytest.raises(UsageError, match="exactly one"):
        evaluate(EvalConfig(policy="rule", checkpoint=tmp_path / "x.pt"))


# --- the loop's budget: what a run stores and counts ---------------------------------------------


class CountingEnv(PickTheFreeLane):
    """Frames that name themselves (LIDAR = env, episode, step, 0, 0); episodes of random
    length end by termination or truncation, with Gymnasium's next-step autoreset."""

    def __init__(self, num_envs: int, seed: int = 0) -> None:
        super().__init__(num_envs, seed=seed)
        self.episode = np.zeros(num_envs, dtype=int)

    def _obs(self):
        lidar = np.zeros((self.num_envs, 5), np.float32)
        lidar[:, 0], lidar[:, 1], lidar[:, 2] = np.arange(self.num_envs), self.episode, self.t
        self.lidar = lidar
        return {"ego": np.zeros((self.num_envs, 6), np.float32), "lidar": lidar.copy()}

    def step(self, actions):
        resetting = self.autoreset.copy()
        self.episode = self.episode + resetting
        self.t = np.where(resetting, 0, self.t + 1)
        ended = ~resetting & (self.rng.random(self.num_envs) < 0.15)
        terminated = ended & (self.rng.random(self.num_envs) < 0.5)
        truncated = ended & ~terminated
        info = self._info()
        if ended.any():
            info["metrics"] = {
                "return": np.zeros(self.num_envs),
                "avg_speed_kmh": np.zeros(self.num_envs),
            }
            info["_metrics"] = ended
        self.autoreset = ended
        return self._obs(), np.where(resetting, 0.0, 1.0), terminated, truncated, info


def test_training_loop_stores_no_transition_across_an_autoreset(tmp_path):
    config = TrainConfig(
        inputs="lidar",
        num_envs=3,
        total_steps=400,
        run_dir=tmp_path,
        progress=False,
        dqn=tiny_dqn(learning_starts=50),
    )
    summary = train(config, envs=CountingEnv(3))
    assert summary["episodes"] > 10
    saved = saved_replay(tmp_path)
    frames, has_next = saved["frame_lidar"], saved["has_next"]
    ep_step, count = saved["ep_step"], saved["count"]
    assert has_next.sum() == summary["steps"]
    for env in range(3):
        for j in range(int(count[env]) - 1):
            now, nxt = frames[env, j], frames[env, j + 1]
            assert now[0] == env and ep_step[env, j] == now[2]
            if has_next[env, j]:  # a transition: same episode, the next step
                assert nxt[1] == now[1] and nxt[2] == now[2] + 1
            else:  # an episode's end: the next frame starts the next one
                assert nxt[1] == now[1] + 1 and nxt[2] == 0 and ep_step[env, j + 1] == 0


def saved_replay(run_dir: Path) -> dict[str, np.ndarray]:
    """A run's replay as its files and its last checkpoint hold it."""
    saved = {path.stem: np.load(path) for path in (run_dir / "replay").glob("*.npy")}
    state = load_checkpoint(run_dir / CHECKPOINT_NAME).resume["replay"]
    return {**saved, "count": state["count"].numpy(), "pos": state["pos"].numpy()}


def _last_train_line(run_dir: Path) -> dict:
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [line for line in lines if line["kind"] == "train"][-1]


def test_a_run_stores_exactly_its_budget_when_the_last_step_would_pass_it(tmp_path):
    """Three environments and a budget of 100: the 34th vector step plays 3 transitions where
    1 is left. It stores that one (environment 0's), and the summary, the checkpoint, the
    last log line and the replay all say 100."""
    config = TrainConfig(
        inputs="lidar",
        num_envs=3,
        total_steps=100,
        run_dir=tmp_path,
        progress=False,
        log_every=40,
        dqn=tiny_dqn(learning_starts=50),
    )
    summary = train(config, envs=PickTheFreeLane(3, length=1000))
    assert summary["steps"] == 100 and summary["unstored"] == 2
    assert summary["env_steps_called"] == 34
    assert load_checkpoint(tmp_path / CHECKPOINT_NAME).step == 100
    assert _last_train_line(tmp_path)["step"] == 100
    saved = saved_replay(tmp_path)
    assert saved["has_next"].sum() == 100
    assert saved["has_next"].sum(axis=1).tolist() == [34, 33, 33]
    # A resume to a larger budget carries on from exactly 100.
    more = train(replace(config, total_steps=131, resume=True), envs=PickTheFreeLane(3))
    assert more["steps"] == 131 and more["resumed_at_step"] == 100


def test_an_episode_ending_past_the_budget_is_not_counted(tmp_path):
    """Episodes of 4 decisions on 2 environments, a budget of 7: the fourth step's second
    transition ends environment 1's episode, but is past the budget: one episode, not two."""
    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=7,
        run_dir=tmp_path,
        progress=False,
        dqn=tiny_dqn(learning_starts=50),
    )
    summary = train(config, envs=PickTheFreeLane(2, length=4))
    assert summary["steps"] == 7 and summary["unstored"] == 1 and summary["episodes"] == 1
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [line["env"] for line in lines if line["kind"] == "episode"] == [0]


@pytest.mark.parametrize("bootstrap", [True, False])
def test_an_episode_cut_by_its_time_limit_is_stored_as_terminal_only_without_bootstrap(
    tmp_path, bootstrap
):
    """Episodes of 4 decisions, each ended by its time limit (truncated): with
    ``bootstrap_time_limit`` the replay stores no terminal; without it (Ho's code) each
    episode's last transition is terminal, and only that one."""
    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=24,
        run_dir=tmp_path,
        progress=False,
        dqn=tiny_dqn(learning_starts=50, bootstrap_time_limit=bootstrap),
    )
    summary = train(config, envs=PickTheFreeLane(2, length=4))
    assert summary["steps"] == 24 and summary["episodes"] == 6
    saved = saved_replay(tmp_path)
    stored = saved["has_next"].astype(bool)
    terminal = saved["terminated"].astype(bool) & stored
    last = stored & (saved["ep_step"] == 3)  # the transition into the episode's 4th step
    assert last.sum() == 6
    assert terminal.tolist() == (np.zeros_like(last) if bootstrap else last).tolist()


@pytest.mark.parametrize("overlap, parts", [("off", 1), ("on", 1), ("on", 2)])
def test_a_remote_run_stores_exactly_its_budget(tmp_path, shared_server, overlap, parts):
    server = shared_server
    run_dir = tmp_path / "run"
    summary = train(
        TrainConfig(
            inputs="lidar",
            num_envs=3,
            total_steps=100,
            seed=2,
            overlap=overlap,
            overlap_parts=parts,
            run_dir=run_dir,
            progress=False,
            log_every=30,
            dqn=DQNConfig(**SMOKE_DQN),
            scenario=Scenario(set=("episode.max_decisions=500",)),
            where=Where(connect=(server.endpoint,)),
        )
    )
    assert summary["steps"] == 100 and summary["parts"] == parts
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == 100
    assert _last_train_line(run_dir)["step"] == 100


# --- evaluation, recordings, SIGTERM, overlap ---------------------------------------------------


def test_eval_table_joins_earlier_results_and_refuses_other_files(tmp_path, capsys):
    for seed in (3, 4):
        evaluate(
            EvalConfig(
                policy="random",
                episodes=1,
                seed=seed,
                name=f"random-{seed}",
                json_out=tmp_path / f"r{seed}.json",
                scenario=Scenario(max_decisions=20),
            )
        )
    capsys.readouterr()
    evaluate(EvalConfig(table=(tmp_path / "r3.json", tmp_path / "r4.json")))
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].split()[0] == "random-3" and lines[3].split()[0] == "random-4"
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(UsageError, match="not an overtake-eval result"):
        evaluate(EvalConfig(table=(tmp_path / "bad.json",)))


def test_evaluation_does_not_import_the_training_command():
    """overtake-eval reads the library modules, not another command's module."""
    code = (
        "import json, sys, overtake.trainers.evaluate; "
        "print(json.dumps([m for m in sys.modules if m.startswith('overtake.')]))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    loaded = set(json.loads(done.stdout))
    assert "overtake.trainers.run.observations" in loaded
    assert (
        "overtake.trainers.train" not in loaded and "overtake.client.episodes.drive" not in loaded
    )


def test_training_writes_a_rerun_recording_of_its_episodes_and_learning(tmp_path):
    import rerun as rr

    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=300,
        run_dir=tmp_path / "run",
        progress=False,
        log_every=100,
        dqn=tiny_dqn(learning_starts=50),
        recording=RecordingConfig(record_every=3),
    )
    envs = WatchEnvZero(PickTheFreeLane(2, length=16))
    train(config, envs=envs)
    records = [
        json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    ]
    reader = rr.chunk.RrdReader(str(tmp_path / "run" / "trainer.rrd"))
    assert reader.recordings() and reader.blueprints()

    def series(entity: str) -> tuple[list[int], list[float]]:
        """The scalars logged at ``entity`` (or, ending in ``/*``, any entity under it)."""
        steps, values = [], []
        for chunk in reader.stream().to_chunks():
            path = chunk.entity_path
            wanted = path.startswith(entity[:-1]) if entity.endswith("/*") else path == entity
            if not wanted or chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            steps += batch.column("step").to_pylist()
            values += [v[0] for v in batch.column("Scalars:scalars").to_pylist()]
        order = np.argsort(steps, kind="stable")
        return [steps[i] for i in order], [values[i] for i in order]

    returns = [r for r in records if r["kind"] == "episode"]
    # Metric first, run second: runs sharing a recording fall into the same plots.
    steps, values = series("/training/episode/return/run")
    assert steps == [r["step"] for r in returns]
    assert values == pytest.approx([r["return"] for r in returns])
    trained = [r for r in records if r["kind"] == "train" and r["loss"] is not None]
    steps, values = series("/training/learning/loss/run")
    assert steps == [r["step"] for r in trained] and len(steps) >= 2
    assert values == pytest.approx([r["loss"] for r in trained])
    _, epsilons = series("/training/learning/epsilon/run")
    assert epsilons == sorted(epsilons, reverse=True) and epsilons[0] <= 1.0

    # Environment 0's view, every 3rd step of the vector env, skipping autoreset steps: the
    # LIDAR it was shown, the action it took and the reward it got for it.
    expected = [
        (seen, action, reward)
        for i, (seen, action, reward, resetting) in enumerate(envs.log)
        if i % 3 == 0 and not resetting
    ]
    _, rewards = series("/trainer/run/env0/reward/total")
    _, actions = series("/trainer/run/env0/action/*")  # a series per action, its index the value
    _, chosen_q = series("/trainer/run/env0/q_chosen")
    hits = []
    for chunk in reader.stream().to_chunks():
        if chunk.entity_path == "/trainer/run/env0/lidar/hits" and not chunk.is_static:
            batch = chunk.to_record_batch()
            hits += zip(
                batch.column("step").to_pylist(), batch.column("Points2D:positions").to_pylist()
            )
    hits = [np.asarray(points) for _, points in sorted(hits, key=lambda h: h[0])]
    assert len(expected) == len(rewards) == len(actions) == len(hits) == len(chosen_q) > 30
    assert rewards == pytest.approx([r for _, _, r in expected])
    assert actions == [a for _, a, _ in expected]
    angles = np.arange(5) * (2 * np.pi / 5)
    for points, (seen, _, _) in zip(hits, expected):
        assert np.hypot(points[:, 0], points[:, 1]) == pytest.approx(seen, rel=1e-5)
        # Drawn as a map: x ahead, the car's left up (Rerun's +y points down).
        assert np.allclose(
            points, np.stack([seen * np.cos(angles), -seen * np.sin(angles)], 1), atol=1e-4
        )


@contextlib.contextmanager
def _long_ho2018_run(run_dir: Path, *options: str) -> Iterator[tuple[subprocess.Popen, Path]]:
    """An overtake-train run of ho2018 too long to end by itself, logging every 40 steps and
    checkpointing only when stopped (its replay in memory: a small replay on disk asks for a
    checkpoint whenever its spare slots are taken), once it has logged twice; with the file
    its stderr goes to (read while it runs). Killed on the way out if still running."""
    from tests.support.remote import child_env, wait_until

    errors_file = run_dir.parent / "trainer.err"
    with errors_file.open("w") as errors_out:
        trainer = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "overtake.trainers.train",
                *("--preset", "ho2018", "--total-steps", "1000000", *options),
                *("--run-dir", str(run_dir), "--no-progress", "--log-every", "40"),
                *("--checkpoint-every", "1000000", "--learning-starts", "64"),
                *("--replay-size", "500", "--hidden-units", "32", "--torch-threads", "1"),
                "--no-replay-on-disk",
            ],
            stdout=subprocess.PIPE,
            stderr=errors_out,
            text=True,
            env=child_env(),
        )
    metrics = run_dir / "metrics.jsonl"
    try:
        wait_until(
            lambda: metrics.exists() and metrics.read_text().count("\n") >= 2, 90, "two log lines"
        )
        yield trainer, errors_file
    finally:
        if trainer.poll() is None:
            trainer.kill()
            trainer.wait()


def _sigterm(trainer: subprocess.Popen, errors_file: Path, timeout_s: float) -> tuple[str, str]:
    """SIGTERM to ``trainer``; its stdout and stderr once it has ended."""
    import signal

    trainer.send_signal(signal.SIGTERM)
    out, _ = trainer.communicate(timeout=timeout_s)
    return out, errors_file.read_text()


@pytest.mark.timeout(120)
def test_sigterm_ends_a_remote_run_whose_server_is_gone_with_its_checkpoint(tmp_path, start_server):
    """docker compose stop after the server died: the step under way waits on a server that is
    gone (its round, then a server to reopen the arenas on, for the reconnect timeout); the
    stop ends that wait and the run ends as a stopped run does, with its checkpoint, status 0.
    Without it the trainer waited out the reconnect timeout and failed, checkpoint unwritten."""
    from tests.support.remote import wait_until

    server = start_server("gone")
    run_dir = tmp_path / "run"
    with _long_ho2018_run(run_dir, "--connect", server.endpoint) as (trainer, errors_file):
        server.kill()  # gone without a word
        # The stop must find the trainer waiting for a server to reopen its arena on.
        wait_until(lambda: "reopening" in errors_file.read_text(), 60, "the trainer to notice")
        out, err = _sigterm(trainer, errors_file, 90)
    assert trainer.returncode == 0, err
    assert "the run ends at its last whole step" in err
    summary = json.loads(out[out.index("{") :])
    assert summary["stopped"] is True
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == summary["steps"] > 0


@pytest.mark.timeout(120)
def test_sigterm_ends_a_training_run_with_a_checkpoint_and_a_whole_recording(tmp_path):
    # docker compose stop, a cluster's preemption, Ctrl-C: the run ends after the step under
    # way as it would at --total-steps, so nothing since the last periodic checkpoint is lost
    # and the .rrd is closed with everything in it: the last log line, written at the stop
    # (a killed writer's file lacks what it had not flushed).
    run_dir = tmp_path / "run"
    with _long_ho2018_run(run_dir, "--seed", "3") as (trainer, errors_file):
        assert not (run_dir / CHECKPOINT_NAME).exists()  # none periodic: the stop writes it
        out, err = _sigterm(trainer, errors_file, 60)
    assert trainer.returncode == 0, err
    assert "SIGTERM: finishing the step under way, writing a checkpoint" in err
    summary = json.loads(out[out.index("{") :])
    assert summary["stopped"] is True and 80 <= summary["steps"] < 1_000_000
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == summary["steps"]
    # Written without a footer (a run may write for days: overtake.viz.recording, on footers).
    verified = subprocess.run(
        [
            str(Path(sys.executable).with_name("rerun")),
            "rrd",
            "verify",
            "--check-footers",
            "false",
            str(run_dir / "trainer.rrd"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert verified.returncode == 0, verified.stderr
    from overtake.viz.layout import open_reader

    epsilon_steps = [
        step
        for chunk in open_reader(run_dir / "trainer.rrd").stream().to_chunks()
        if chunk.entity_path == "/training/learning/epsilon/run" and not chunk.is_static
        for step in chunk.to_record_batch().column("step").to_pylist()
    ]
    assert max(epsilon_steps) == summary["steps"]  # the stop's own log line


def test_overlap_auto_leaves_a_core_for_the_server(monkeypatch):
    """--overlap auto learns while the server simulates only where this machine has a core
    beyond PyTorch's threads; on and off decide by themselves; in-process never overlaps."""
    remote = TrainConfig(num_envs=4, overlap_parts=2, where=Where(connect=("tcp/127.0.0.1:7447",)))
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 4)
    assert not remote.overlapped and remote.parts == 1
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    assert remote.overlapped and remote.parts == 2
    assert not replace(remote, overlap="off").overlapped
    monkeypatch.setattr(torch, "get_num_threads", lambda: 4)
    assert replace(remote, overlap="on").parts == 2
    assert not replace(remote, where=Where(), overlap="on").overlapped
    # Never more parts than environments.
    assert replace(remote, overlap="on", num_envs=1).parts == 1


def test_an_in_process_run_draws_its_first_cars_road_in_its_recording(tmp_path):
    """World frames leave only a server: in-process, the trainer draws environment 0's road
    itself (every car on it), and its layout shows the road beside the car's view."""
    import rerun as rr

    from overtake.trainers.run.run_recording import IN_PROCESS_ROAD

    from tests.support.remote import blueprint_texts

    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=60,
        run_dir=tmp_path / "run",
        progress=False,
        dqn=tiny_dqn(learning_starts=50),
        recording=RecordingConfig(record_every=5),
        scenario=Scenario(set=("episode.max_decisions=40",)),
    )
    train(config)
    reader = rr.chunk.RrdReader(str(tmp_path / "run" / "trainer.rrd"))
    cars = [
        chunk.to_record_batch()
        for chunk in reader.stream().to_chunks()
        if chunk.entity_path == f"{IN_PROCESS_ROAD}/cars" and not chunk.is_static
    ]
    # A frame every 5th step of the vector env: 60 steps of 2 envs are 30 steps, 6 frames
    # (and the same count of car views), each with the agent and the medium traffic's cars,
    # more of them as the authors' spawners fill the road from empty (issue 68).
    boxes = [len(row) for batch in cars for row in batch.column("Boxes2D:half_sizes").to_pylist()]
    assert len(boxes) == 6 and all(count >= 2 for count in boxes), boxes
    assert max(boxes) > 10, boxes
    texts = set().union(*(blueprint_texts(reader, store) for store in reader.blueprints()))
    assert IN_PROCESS_ROAD in texts and "run: road (env 0 at 0 m, left up)" in texts


def test_a_stop_before_training_began_ends_at_once(monkeypatch):
    """SIGTERM while the trainer still builds its environments and learner ends the process
    at once (nothing to checkpoint yet); once a run has opened its books, the stop finishes
    the step under way and checkpoints."""
    from overtake.trainers import train as train_module

    started = threading.Event()
    monkeypatch.setattr(train_module, "TRAINING_STARTED", started)
    with pytest.raises(SystemExit, match="SIGTERM: stopped before training began"):
        train_module._say_stopping("SIGTERM")
    started.set()
    train_module._say_stopping("SIGTERM")  # says so and returns: the loop stops
