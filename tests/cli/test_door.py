"""The one door: a Command built from a typed configuration and its main, as every overtake-*
command is (its parser, its status, its signals)."""

from __future__ import annotations

import os
import signal
import threading
from dataclasses import dataclass

import pytest

from overtake.cli import Command, CommandError


@dataclass(frozen=True)
class Greeting:
    """Say hello to someone, a number of times."""

    name: str = "world"
    """who is greeted"""
    times: int = 1
    """how many times"""


def greet(config: Greeting) -> list[str]:
    if config.times < 1:
        raise CommandError(f"--times must be >= 1, got {config.times}")
    return [f"hello {config.name}"] * config.times


def test_the_parser_is_the_configurations_and_the_help_its_docstring(capsys):
    command = Command("greet", Greeting, greet)
    assert command.parse(["--name", "road", "--times", "2"]) == Greeting("road", 2)
    with pytest.raises(SystemExit) as exited:
        command.parse(["--help"])
    assert exited.value.code == 0
    shown = capsys.readouterr().out
    assert shown.startswith("usage: greet") and "Say hello to someone" in shown
    assert "who is greeted" in shown  # each option's help is its field's docstring


def test_defaults_read_from_the_command_line_and_a_status_from_the_report(capsys):
    def from_args(args: list[str]) -> Greeting:  # as overtake-train reads its preset first
        return Greeting(name="preset-" + ("b" if "--b" in args else "a"), times=3)

    def report(config: Greeting, lines: list[str]) -> int:
        print(*lines, sep="\n")
        return 0 if config.times < 3 else 4

    command = Command("greet", Greeting, greet, default=from_args, report=report)
    assert command.parse([]) == Greeting("preset-a", 3)
    with pytest.raises(SystemExit) as exited:
        command.run([])
    assert exited.value.code == 4
    assert capsys.readouterr().out.splitlines() == ["hello preset-a"] * 3
    command.run(["--times", "1"])  # status 0: returns


def test_a_refusal_is_one_line_naming_the_command():
    with pytest.raises(SystemExit) as exited:
        Command("greet", Greeting, greet).run(["--times", "0"])
    assert exited.value.code == "greet: --times must be >= 1, got 0"


# A signal reaches Python's handlers in the main thread only (where the door installs them).
in_main_thread = pytest.mark.skipif(
    threading.current_thread() is not threading.main_thread(),
    reason="signals are handled in the main thread only",
)


@in_main_thread
def test_an_interrupt_ends_in_one_line_with_the_commands_hint():
    def interrupted(config: Greeting) -> None:
        os.kill(os.getpid(), signal.SIGTERM)  # raises where main is, as Ctrl-C would
        raise AssertionError("not reached")

    command = Command(
        "greet", Greeting, interrupted, stopping="interrupt", stopped_hint="run it again"
    )
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit) as exited:
        command.run([])
    assert exited.value.code == "greet: stopped; run it again"
    assert signal.getsignal(signal.SIGTERM) is before  # the door puts the handlers back


@in_main_thread
def test_a_stop_event_is_set_by_the_first_signal_and_a_second_ends_at_once():
    said: list[str] = []
    seen: list[bool] = []

    def stoppable(config: Greeting, stop: threading.Event) -> None:
        os.kill(os.getpid(), signal.SIGINT)
        seen.append(stop.is_set())  # main finishes what is under way
        os.kill(os.getpid(), signal.SIGINT)

    command = Command(
        "greet",
        Greeting,
        stoppable,
        stopping="event",
        stopped_hint="resume it",
        on_stop=said.append,
    )
    with pytest.raises(SystemExit) as exited:
        command.run([])
    assert seen == [True] and said == ["SIGINT"]
    assert exited.value.code == "greet: stopped at once by a second SIGINT; resume it"
