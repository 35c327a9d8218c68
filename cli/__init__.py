"""The one door every ``overtake-*`` command goes through (:mod:`.door`)."""

from .door import CommandError, Output, check_outputs, enter

__all__ = ["CommandError", "Output", "check_outputs", "enter"]
