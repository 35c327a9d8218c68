"""``python -m overtake.server``: the same as ``overtake-server``."""

from .cli import COMMAND

if __name__ == "__main__":
    COMMAND.run()
