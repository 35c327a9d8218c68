"""The command layer's usage error: what a request that cannot be carried out raises.

Library functions and the commands' ``main(config)`` raise typed exceptions, because they are
called from Python too (tests, benchmarks, notebooks) and exiting there would end the caller.
Only a command exits, through the one door every command goes through
(:class:`overtake.cli.Command`), which prints ``<prog>: <message>``.
"""

from __future__ import annotations

from overtake.cli import CommandError


class UsageError(CommandError, ValueError):
    """The user asked for something that cannot be done (an option out of range, options that
    exclude each other, a file that is not what the option names); the message says what was
    expected and what came."""
