"""``overtake-server``: the run it starts (``main``) and the command around it (``COMMAND``)."""

from __future__ import annotations

import logging
import signal
from typing import Any

import zenoh

from overtake.cli import Command
from overtake.ipc.transport import warn_if_unconnected, warn_if_unguarded
from overtake.protocol import errors

from .errors import StartError
from .service.server import SimulatorServer
from .service.server_config import ServerConfig

log = logging.getLogger("overtake.server")


def main(config: ServerConfig) -> None:
    """Run a server until SIGINT or SIGTERM."""
    logging.basicConfig(
        level=config.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    zenoh.init_log_from_env_or("error")
    try:
        server = SimulatorServer(config)
    except zenoh.ZError as error:
        raise StartError(
            f"could not open the Zenoh session ({config.session_config().describe()}): "
            f"{error}. Is the port in use, or the router unreachable?"
        ) from None
    except (RuntimeError, errors.ProtocolError) as error:
        raise StartError(str(error)) from None
    warn_if_unconnected(server.session, config.session_config(), log)
    warn_if_unguarded(config.session_config(), log)

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("received %s, shutting down", signal.Signals(signum).name)
        server.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    server.serve()


COMMAND = Command("overtake-server", ServerConfig, main)


if __name__ == "__main__":
    COMMAND.run()
