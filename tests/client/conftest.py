"""The end-to-end fixture that starts (and stops, by PID) simulator servers."""

from tests.support.remote import shared_server, start_server  # noqa: F401
