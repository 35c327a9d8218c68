"""The one door every ``overtake-*`` command goes through (:mod:`.door`)."""

from .door import Command, CommandError, Output, UsageError, check_outputs, check_viewer

__all__ = [
    "Command",
    "CommandError",
    "Output",
    "UsageError",
    "check_outputs",
    "check_viewer",
]
