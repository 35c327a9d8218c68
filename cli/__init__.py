"""The one door every ``overtake-*`` command goes through (:mod:`.door`)."""

from .door import CommandError, Output, check_outputs, check_viewer, enter

__all__ = ["CommandError", "Output", "check_outputs", "check_viewer", "enter"]
