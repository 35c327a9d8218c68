"""The end-to-end fixtures that start (and stop, by PID) servers and trainer processes, and the
deployment tests' (tests/e2e/test_deploy_*.py): commands run in the background, and an
environment without inherited credentials."""

from tests.support.deploy import background, no_inherited_credentials  # noqa: F401
from tests.support.remote import shared_server, start_server, start_trainer  # noqa: F401
