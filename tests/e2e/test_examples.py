"""The third-party trainers under examples/, run as their users run them, with tiny budgets:
Stable-Baselines3's DQN and the CleanRL-style DQN, in process and against a real server."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.remote import child_env

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
SHORT_EPISODES = "episode.max_decisions=30"


def run_example(script: str, *args: str, tmp_dir: Path | None = None) -> str:
    """Run ``examples/<script>``; its output (the test fails, showing it, unless it exits 0).

    ``tmp_dir``: the temporary directory it is given (TMPDIR), to see what it leaves there."""
    env = child_env()
    if tmp_dir is not None:
        tmp_dir.mkdir(parents=True, exist_ok=True)
        env["TMPDIR"] = str(tmp_dir)
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        capture_output=True,
        text=True,
        timeout=240,
        env=env,
        cwd=ROOT,
    )
    output = done.stdout + done.stderr
    assert done.returncode == 0, output[-4000:]
    return output


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    # The remote path of the examples is the CleanRL example's (below); SB3's on a server
    # (8 s) runs with -m slow.
    "where",
    ["in-process", pytest.param("remote", marks=pytest.mark.slow)],
)
def test_stable_baselines3_dqn_trains_and_evaluates(where, start_server, tmp_path):
    pytest.importorskip("stable_baselines3", reason="stable-baselines3 is not installed")
    connect = [] if where == "in-process" else ["--connect", start_server("sb3").endpoint]
    model = tmp_path / "sb3-dqn.zip"
    output = run_example(
        "sb3_dqn.py",
        *connect,
        "--total-timesteps",
        "150",
        "--learning-starts",
        "100",
        "--buffer-size",
        "300",
        "--eval-episodes",
        "1",
        "--set",
        SHORT_EPISODES,
        "--save",
        str(model),
        tmp_dir=tmp_path / "tmp",
    )
    # It says how learning goes as it goes (SB3's table), and leaves nothing behind (SB3's
    # default logger left an empty SB3-<date> folder in the temporary directory every run).
    assert "total_timesteps" in output, output[-2000:]
    assert not list((tmp_path / "tmp").glob("SB3-*"))
    # Every step of a 30-decision episode pays at least the speed term, so a return came back.
    found = re.search(r"greedy return over 1 episode\(s\): (-?[\d.]+)", output)
    assert found, output[-2000:]
    assert model.stat().st_size > 10_000  # the trained model, in SB3's format


@pytest.mark.timeout(300)
@pytest.mark.parametrize("where", ["in-process", "remote"])
def test_cleanrl_style_dqn_learns_over_a_vector_env(where, start_server):
    connect = [] if where == "in-process" else ["--connect", start_server("cleanrl").endpoint]
    output = run_example(
        "cleanrl_dqn.py",
        *connect,
        "--num-envs",
        "4",
        "--total-timesteps",
        "800",
        "--learning-starts",
        "200",
        "--log-every",
        "400",
        "--set",
        SHORT_EPISODES,
    )
    logs = re.findall(r"step (\d+): epsilon [\d.]+, (\d+) episodes", output)
    assert [int(step) for step, _ in logs] == [400], output[-2000:]
    # 4 arenas x 100 steps of 30-decision episodes (plus the reset steps): 12 episodes ended.
    assert int(logs[-1][1]) >= 8


@pytest.mark.timeout(300)
def test_cleanrl_style_dqn_says_how_it_goes_on_a_short_run_too():
    """Without --log-every, a line every tenth of the run (it printed nothing under 5,000)."""
    output = run_example(
        "cleanrl_dqn.py",
        "--num-envs",
        "2",
        "--total-timesteps",
        "200",
        "--learning-starts",
        "100",
        "--set",
        SHORT_EPISODES,
    )
    assert output.startswith("training 200 steps on 2 environment(s)"), output[:500]
    steps = [int(step) for step in re.findall(r"step (\d+): epsilon", output)]
    assert steps == list(range(20, 200, 20)), output[-2000:]
