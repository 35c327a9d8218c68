"""``python -m overtake.server``: the same as ``overtake-server``."""

from .cli import cli

if __name__ == "__main__":
    cli()
