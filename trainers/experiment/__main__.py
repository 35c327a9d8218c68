"""``python -m overtake.trainers.experiment``: the ``overtake-experiment`` command."""

from .command import COMMAND

if __name__ == "__main__":
    COMMAND.run()
