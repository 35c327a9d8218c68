"""--help of the commands: an option that may be left unset says its value's name and
"(default: unset)", not tyro's "{None}|STR" and "(default: None)" (cli/options.py; the
connection's security options, ipc's, are not marked: ipc imports nothing of cli)."""

from __future__ import annotations

import pytest

from overtake.client.episodes.drive import COMMAND as DRIVE
from overtake.trainers.evaluate import COMMAND as EVAL


@pytest.mark.parametrize("command", [EVAL, DRIVE], ids=["eval", "drive"])
def test_unset_options_read_as_their_values(command, capsys):
    with pytest.raises(SystemExit):
        command.parse(["--help"])
    text = capsys.readouterr().out
    options = text.split("security options")[0]  # ipc's SecurityConfig comes last
    assert "{None" not in options and "(default: None)" not in options
    assert "--preset NAME" in text and "--json-out PATH" in text and "--server NAME" in text
    assert "(default: unset)" in text
    assert "--policy {rule,random,idle,planner,idm}" in text
