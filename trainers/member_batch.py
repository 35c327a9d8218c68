"""Training runs given as ``overtake-train`` command lines, trained in one process as members of
one learner (:mod:`.members_run`): what ``overtake-experiment`` starts for the runs of one
network, ``python -m overtake.trainers.member_batch --members '[ARGS...]' '[ARGS...]' ...``, each
a JSON list of one run's ``overtake-train`` arguments (its run directory among
them). SIGTERM or SIGINT stops every member at its last whole step, with a checkpoint each."""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass
from typing import Any

import torch

from overtake.cli import Command, UsageError
from overtake.cli.allocator import keep_freed_memory

from .config.train_config import TrainConfig
from .train import COMMAND as TRAIN
from .train import _say_stopping, train_members


@dataclass(frozen=True)
class MemberBatchConfig:
    """Train several runs, each given as its overtake-train arguments, as members of one
    learner in this process."""

    members: tuple[str, ...] = ()
    """the runs, each its overtake-train arguments as one JSON list (its --run-dir among
    them)"""


def member_config(text: str) -> TrainConfig:
    """A member's configuration from its ``overtake-train`` arguments (a JSON list)."""
    try:
        argv = json.loads(text)
    except ValueError as error:
        raise UsageError(
            f"--members takes JSON lists of arguments, got {text!r}: {error}"
        ) from None
    if not isinstance(argv, list) or not all(isinstance(a, str) for a in argv):
        raise UsageError(f"--members takes JSON lists of strings, got {text!r}")
    config = TRAIN.parse(argv)
    if config.seeds:
        raise UsageError("--members: a member is one run (no --seeds)")
    return config


def main(config: MemberBatchConfig, stop: threading.Event | None = None) -> list[dict[str, Any]]:
    """Train the members; returns each member's summary."""
    configs = [member_config(text) for text in config.members]
    if not configs:
        raise UsageError("give the runs to train: --members, a JSON list of arguments each")
    keep_freed_memory()
    threads = {c.torch_threads for c in configs}
    if len(threads) == 1 and (count := threads.pop()) is not None:
        torch.set_num_threads(count)
    return train_members(configs, stop)


def _report(_config: MemberBatchConfig, summaries: list[dict[str, Any]]) -> None:
    print(json.dumps(summaries, indent=2))


COMMAND = Command(
    "overtake-member-batch",
    MemberBatchConfig,
    main,
    report=_report,
    stopping="event",
    stopped_hint="each member continues with --resume from its last checkpoint",
    on_stop=_say_stopping,
)


if __name__ == "__main__":
    COMMAND.run()
