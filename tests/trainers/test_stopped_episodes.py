"""Ctrl-C and SIGTERM in ``overtake-eval`` and ``overtake-drive`` (issue 67): the drive ends
before the next decision, and the table and the JSON hold the episodes that ended, said as
partial, with no traceback."""

from __future__ import annotations

import json
import os
import signal
import threading

import numpy as np
import pytest

from overtake.client.episodes import drive as drive_command
from overtake.client.episodes import runner
from overtake.trainers import evaluate

in_main_thread = pytest.mark.skipif(
    threading.current_thread() is not threading.main_thread(),
    reason="signals are handled in the main thread only",
)


def _signalled_when_one_ends(monkeypatch, module, signum: int) -> list[int]:
    """The reference policy of ``module``, wrapped to send this process ``signum`` as soon as
    the first episode has ended (the step after it is that arena's autoreset); the decisions
    it was asked for, counted."""
    calls: list[int] = []
    made = runner.baseline_policy

    def policy(*args, **kwargs):
        act = made(*args, **kwargs)

        def signalling(obs, info, starting):
            calls.append(1)
            if len(calls) > 1 and np.any(starting):
                os.kill(os.getpid(), signum)
            return act(obs, info, starting)

        return signalling

    monkeypatch.setattr(module, "baseline_policy", policy)
    return calls


# The episodes end at different decisions: always keeping lane and speed on highway-fast, the
# car runs into a slower car sooner or later, or not at all in 30 decisions.
ARGS = ["--preset", "highway-fast", "--policy", "idle", "--episodes", "8", "--seed", "3"]


@in_main_thread
def test_ctrl_c_in_overtake_eval_reports_the_episodes_that_ended(monkeypatch, tmp_path, capsys):
    calls = _signalled_when_one_ends(monkeypatch, evaluate, signal.SIGINT)
    out = tmp_path / "e.json"
    evaluate.COMMAND.run([*ARGS, "--json-out", str(out)])  # returns: no SystemExit, status 0
    printed = capsys.readouterr()
    result = json.loads(out.read_text())
    ended = len(result["episodes"])
    assert result["partial"] is True and result["episodes_planned"] == 8
    assert 1 <= ended < 8 and result["summary"]["episodes"] == ended
    assert f"partial: stopped after {ended} of 8 episodes ended" in printed.out
    assert "idle" in printed.out and "Traceback" not in printed.err
    # It stopped before the next decision: the policy was asked for the first episode's
    # decisions, its autoreset step and the decision the signal came in, and none after.
    assert len(calls) == min(row["decisions"] for row in result["episodes"]) + 2


@in_main_thread
def test_sigterm_in_overtake_drive_reports_the_episodes_that_ended(monkeypatch, tmp_path, capsys):
    _signalled_when_one_ends(monkeypatch, drive_command, signal.SIGTERM)
    out = tmp_path / "d.json"
    drive_command.COMMAND.run([*ARGS, "--json-out", str(out)])
    printed = capsys.readouterr().out
    result = json.loads(out.read_text())
    ended = len(result["episodes"])
    assert result["partial"] is True and 1 <= ended < 8
    assert f"partial: stopped after {ended} of 8 episodes ended" in printed
    # The table's rows are the episodes that ended, by their seeds.
    rows = [line.split()[0] for line in printed.splitlines() if line.strip()[:1].isdigit()]
    assert len(rows) == ended and set(rows) <= {str(3 + i) for i in range(8)}


@in_main_thread
def test_a_stop_before_any_episode_ended_is_one_line(monkeypatch, tmp_path):
    made = runner.baseline_policy

    def policy(*args, **kwargs):
        act = made(*args, **kwargs)

        def signalling(obs, info, starting):
            os.kill(os.getpid(), signal.SIGINT)
            return act(obs, info, starting)

        return signalling

    monkeypatch.setattr(evaluate, "baseline_policy", policy)
    out = tmp_path / "e.json"
    with pytest.raises(SystemExit) as exited:
        evaluate.COMMAND.run([*ARGS, "--json-out", str(out)])
    assert exited.value.code == (
        "overtake-eval: stopped before any of the 8 episodes ended: no table, nothing written"
    )
    assert not out.exists()
