"""Coverage-guided fuzzing of the wire codec with atheris (libFuzzer for Python).

Every frame the server and the clients receive goes through ``overtake.protocol.codec.decode``
first; ``bench/fuzz/fuzz_wire.py`` throws Hypothesis-made frames at a live server, this throws
libFuzzer's mutations, guided by which lines of the codec and the message classes they reach,
at the decoder itself, millions a minute. The property checked on every input:

- ``decode`` either returns a message or raises the protocol's own errors (``DecodeError``,
  ``VersionMismatch``: the "what was expected, what came" messages the server logs and
  answers with); anything else (a ``KeyError``, a ``ValueError`` from numpy, a crash) is a
  finding, and libFuzzer stops with the input saved as ``crash-*`` in the working directory;
- what it returns encodes again, and decoding that gives the same bytes once more (one
  normalisation at most: a peer's frame and ours mean the same message).

The seed corpus is real: messages of every type made by the server's own code in-process
(``server.groups.Group``: an opened group's Opened reply, its Steps, a world frame, its
status) and the requests a trainer sends, written to ``--corpus``.

    .venv/bin/python -m bench.fuzz.fuzz_codec [--runs 1000000] [--corpus runs/fuzz-corpus]

atheris is an optional install (``pip install atheris``; wheels for Linux x86-64, CPython
3.11), not part of the project's dependencies: it is needed here only.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import tyro


@dataclass(frozen=True)
class CodecFuzzConfig:
    runs: int = 1_000_000
    """inputs to try"""
    corpus: Path = Path("runs/fuzz-corpus")
    """the seed corpus is written here; libFuzzer adds what reaches new lines"""
    max_len: int = 65536
    """bytes per input at most (libFuzzer's -max_len)"""
    preset: str = "ho2018"
    """the preset of the seed messages (its observations are small)"""
    seed: int = 1


def seed_messages(preset: str) -> list[bytes]:
    """Frames of every message type, made by the server's and the client's own code."""
    import numpy as np

    from overtake.protocol import codec
    from overtake.protocol.messages import (
        Ack,
        Actions,
        CloseRequest,
        ErrorReply,
        JoinRequest,
        Opened,
        OpenRequest,
        ResetRequest,
        StatusReply,
        StatusRequest,
    )
    from overtake.server.engine.world import group_world_frame
    from overtake.server.service.groups import Group

    group = Group.open(7, "srv", [3, 4], preset, {}, 2, seed=1)
    group.claim("alice", 0, 2, fresh=True)
    group.claim("bob", 1, 1, fresh=True)
    ticket = group.members["alice"].ticket
    first = group.current_steps("alice")
    opened = Opened(
        server="srv", group=7, arenas=(3, 4), ticket=ticket, spec=group.spec, steps=first
    )
    actions = Actions(
        trainer="alice",
        ticket=ticket,
        group=7,
        round=group.round,
        agents=first.agents[:-1],
        actions=np.ones(first.agents.size - 1, dtype=np.int64),
        trainer_step=12,
        retire=first.agents[-1:],
    )
    group.accept(actions, deadline_s=1.0)
    bob = group.members["bob"].ticket
    group.accept(
        Actions(
            trainer="bob",
            ticket=bob,
            group=7,
            round=group.round,
            agents=group.current_steps("bob").agents,
            actions=np.zeros(1, dtype=np.int64),
        ),
        deadline_s=1.0,
    )
    stepped = group.step()
    world = group_world_frame(group, 0, group.latest_observations())
    messages = [
        StatusRequest(),
        StatusReply(
            server="srv",
            package_version="0.0",
            max_arenas=256,
            arenas_used=2,
            step_deadline_s=0.5,
            uptime_s=3.0,
            groups=(group.status(),),
        ),
        OpenRequest(
            trainer="alice",
            preset=preset,
            overrides={"traffic.cars": 20, "reward.collision": -1.0, "name": "x", "on": True},
            arenas=2,
            agents_per_arena=2,
            claim=2,
            seed=1,
        ),
        JoinRequest(trainer="carol", arena=4, agents=1),
        opened,
        stepped["alice"],
        actions,
        ResetRequest(trainer="alice", ticket=ticket, group=7, arenas=(0, 1), seeds=(5, None)),
        CloseRequest(trainer="alice", ticket=ticket, group=7),
        Ack(message="closed group 7"),
        ErrorReply(code="server_busy", message="server srv is busy", group=7),
        world,
    ]
    return [codec.encode(m) for m in messages]


def main(config: CodecFuzzConfig) -> None:
    import atheris

    # Imported first, so that only overtake's own modules are instrumented below.
    import msgpack  # noqa: F401
    import numpy  # noqa: F401

    with atheris.instrument_imports(include=["overtake.protocol"]):
        from overtake.protocol import codec, errors, messages  # noqa: F401

    config.corpus.mkdir(parents=True, exist_ok=True)
    for index, frame in enumerate(seed_messages(config.preset)):
        (config.corpus / f"seed-{index:02d}").write_bytes(frame[: config.max_len])
    found = {"decoded": 0, "refused": 0}
    started = time.monotonic()

    def one_input(data: bytes) -> None:
        try:
            message = codec.decode(data)
        except errors.ProtocolError:
            found["refused"] += 1
        else:
            found["decoded"] += 1
            again = codec.encode(message)
            if codec.encode(codec.decode(again)) != again:
                raise AssertionError(f"{type(message).__name__} does not encode the same twice")
        finally:
            if sum(found.values()) % 100_000 == 0 or sum(found.values()) == config.runs:
                report()

    def report() -> None:
        elapsed = time.monotonic() - started
        total = found["decoded"] + found["refused"]
        print(
            f"fuzz_codec: {total} inputs in {elapsed:.0f} s ({total / max(elapsed, 1e-9):.0f}/s):"
            f" {found['decoded']} decoded to a message, {found['refused']} refused with the "
            "protocol's errors, nothing else raised",
            flush=True,
        )

    atheris.Setup(
        [
            sys.argv[0],
            f"-runs={config.runs}",
            f"-max_len={config.max_len}",
            f"-seed={config.seed}",
            "-print_final_stats=1",
            str(config.corpus),
        ],
        one_input,
    )
    atheris.Fuzz()


if __name__ == "__main__":
    main(tyro.cli(CodecFuzzConfig))
