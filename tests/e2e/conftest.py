"""The end-to-end fixtures that start (and stop, by PID) servers and trainer processes."""

from tests.support.remote import start_server, start_trainer  # noqa: F401
