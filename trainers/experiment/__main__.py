"""``python -m overtake.trainers.experiment``: the ``overtake-experiment`` command."""

from .command import cli

if __name__ == "__main__":
    cli()
