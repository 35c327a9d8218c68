"""Why a server or router could not start (its command turns this into an exit message)."""

from overtake.cli import CommandError


class StartError(CommandError, RuntimeError):
    """The process cannot serve: the port is taken, the address is not this host's, the router
    is unreachable or refuses us. The message says which, and what to check."""
