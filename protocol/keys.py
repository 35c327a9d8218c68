"""Every Zenoh key expression overtake uses, built and parsed here and nowhere else.

```
overtake/server/<server>/request              queryable: status, open, join, reset, close
overtake/server/<server>/actions/<trainer>     trainer puts Actions (blocking congestion control)
overtake/trainer/<trainer>/steps/<server>      server puts Steps (blocking) or ErrorReply
overtake/server/<server>/world/<arena>         server puts WorldFrame (dropping)
overtake/alive/server/<server>                 liveliness token of a server
overtake/alive/trainer/<trainer>               liveliness token of a trainer
```

Names are checked by :func:`~overtake.protocol.messages.check_name`, so they never hold
``/`` or wildcards.
"""

from __future__ import annotations

from .errors import DecodeError
from .messages import check_name

ROOT = "overtake"

ALL_SERVER_REQUESTS = f"{ROOT}/server/*/request"
ALL_TRAINERS_ALIVE = f"{ROOT}/alive/trainer/*"
ALL_SERVERS_ALIVE = f"{ROOT}/alive/server/*"
ALL_SERVER_ACTIONS = f"{ROOT}/server/*/actions/*"
# A trainer's name begins with a prefix of at most this many characters (its usrpwd user, or
# what it chose), then "-": what a router's access control matches (users_trainer_keys).
TRAINER_PREFIX_CHARS = 16


def server_request(server: str) -> str:
    check_name("server", server)
    return f"{ROOT}/server/{server}/request"


def server_actions(server: str, trainer: str) -> str:
    check_name("server", server)
    check_name("trainer", trainer)
    return f"{ROOT}/server/{server}/actions/{trainer}"


def server_actions_all(server: str) -> str:
    check_name("server", server)
    return f"{ROOT}/server/{server}/actions/*"


def trainer_steps(trainer: str, server: str) -> str:
    check_name("trainer", trainer)
    check_name("server", server)
    return f"{ROOT}/trainer/{trainer}/steps/{server}"


def trainer_steps_all(trainer: str) -> str:
    check_name("trainer", trainer)
    return f"{ROOT}/trainer/{trainer}/steps/*"


def world(server: str, arena: int | None = None) -> str:
    """One arena's world frames, or (``arena`` None) every arena's of ``server``."""
    check_name("server", server)
    return f"{ROOT}/server/{server}/world/{'*' if arena is None else int(arena)}"


def world_all() -> str:
    return f"{ROOT}/server/*/world/*"


def users_trainer_keys(prefix: str) -> tuple[str, str, str]:
    """Key expressions of every trainer whose name begins with ``prefix`` and "-": its
    actions to any server, its steps from any server, its liveliness token."""
    check_name("trainer prefix", prefix)
    own = f"{prefix}-$*"
    return (
        f"{ROOT}/server/*/actions/{own}",
        f"{ROOT}/trainer/{own}/steps/*",
        f"{ROOT}/alive/trainer/{own}",
    )


def server_alive(server: str) -> str:
    check_name("server", server)
    return f"{ROOT}/alive/server/{server}"


def trainer_alive(trainer: str) -> str:
    check_name("trainer", trainer)
    return f"{ROOT}/alive/trainer/{trainer}"


def _parts(key: str, shape: tuple[str | None, ...]) -> list[str]:
    """The segments of ``key`` where ``shape`` has None; the others must match literally."""
    segments = str(key).split("/")
    if len(segments) != len(shape) or any(
        want is not None and got != want for got, want in zip(segments, shape, strict=True)
    ):
        pattern = "/".join("<name>" if s is None else s for s in shape)
        raise DecodeError(f"expected a key like {pattern}, got {key!r}")
    names = [got for got, want in zip(segments, shape, strict=True) if want is None]
    for name in names:
        check_name("key segment", name)
    return names


def parse_server_actions(key: str) -> tuple[str, str]:
    """(server, trainer) of an actions key."""
    server, trainer = _parts(key, (ROOT, "server", None, "actions", None))
    return server, trainer


def parse_trainer_alive(key: str) -> str:
    return _parts(key, (ROOT, "alive", "trainer", None))[0]


def parse_server_alive(key: str) -> str:
    return _parts(key, (ROOT, "alive", "server", None))[0]


def parse_server_request(key: str) -> str:
    return _parts(key, (ROOT, "server", None, "request"))[0]


def parse_world(key: str) -> tuple[str, int]:
    server, arena = _parts(key, (ROOT, "server", None, "world", None))
    if not arena.isdigit():
        raise DecodeError(f"expected an arena number in world key, got {key!r}")
    return server, int(arena)
