"""The trainer's side of Steps through shared memory (protocol 1.6,
:mod:`overtake.protocol.shared_memory`): attach to the segment a server offers, and rebuild
each round's Steps from the notice that names where its arrays lie."""

from __future__ import annotations

import logging
from typing import Literal

from overtake.protocol import errors
from overtake.protocol.messages import ShmOffer, Steps, StepsInShm
from overtake.protocol.shared_memory import Segment
from overtake.protocol.shm_messages import OBSERVATION_PREFIX, STEPS_ARRAYS

log = logging.getLogger("overtake.client")

Transport = Literal["auto", "shm", "zenoh"]
"""How a trainer's Steps travel: ``shm`` through shared memory (the server must be on this host,
sharing its ``/dev/shm``), ``zenoh`` always over Zenoh, ``auto`` through shared memory where the
server's segment can be attached and the Steps are large enough to gain by it
(:data:`AUTO_SHM_MIN_BYTES`), over Zenoh otherwise."""

# ``auto`` reads Steps through shared memory from this segment size on. Measured on the 2-core
# VM (bench/RESULTS.md, issue 36): a round through the segment costs its notice (a Zenoh
# message of its own) plus a copy in and out, which is more than msgpack's for small Steps
# (1 and 8 arenas of min2018, 8.5 and 65 KB: 0.33x and 0.42x of in-process against 0.39x and
# 0.48x over Zenoh) and less for large ones (64 arenas, 513 KB: 0.54x against 0.50x).
AUTO_SHM_MIN_BYTES = 256 * 1024


def attach(server: str, offer: ShmOffer | None, transport: Transport) -> Segment | None:
    """The offered segment, mapped; None where Steps go over Zenoh. With ``transport="shm"``
    a missing or unreachable segment is an error (:class:`~overtake.protocol.errors.ConnectError`)
    that says why."""
    if transport == "zenoh":
        return None
    if offer is None:
        if transport == "shm":
            raise errors.ConnectError(
                f"transport shm: server {server} offered no shared memory (it runs with "
                "--no-shared-memory, speaks protocol 1.5 or older, or could not make a segment)"
            )
        return None
    try:
        return Segment.attach(offer.name, offer.nonce, offer.size_bytes)
    except (OSError, errors.DecodeError) as error:
        if transport == "shm":
            raise errors.ConnectError(
                f"transport shm: cannot attach server {server}'s segment {offer.name} ({error}); "
                "is the server on this host, sharing its /dev/shm (not another container)?"
            ) from None
        log.info(
            "server %s is not on this host's shared memory (%s): Steps over Zenoh", server, error
        )
        return None


def reads_through(segment: Segment | None, transport: Transport) -> bool:
    """Whether Steps come through ``segment`` (an attached one): always with ``shm``, with
    ``auto`` where it is large enough to gain (:data:`AUTO_SHM_MIN_BYTES`). A segment attached
    but not read is kept all the same: a trainer that finds its server dead removes it."""
    if segment is None:
        return False
    return transport == "shm" or segment.size >= AUTO_SHM_MIN_BYTES


def steps_from_notice(segment: Segment, notice: StepsInShm) -> Steps:
    """The Steps a notice announces, copied out of the segment and checked like a decoded
    frame; :class:`~overtake.protocol.errors.DecodeError` where the notice and the segment
    disagree."""
    arrays = segment.read(
        notice.generation, ((a.name, a.offset, a.dtype, a.shape) for a in notice.arrays)
    )
    observations = {
        name.removeprefix(OBSERVATION_PREFIX): value
        for name, value in arrays.items()
        if name.startswith(OBSERVATION_PREFIX)
    }
    fields = {name: arrays[name] for name in STEPS_ARRAYS}
    return Steps(
        server=notice.server,
        group=notice.group,
        round=notice.round,
        observations=observations,
        **fields,
    )
