"""Zenoh access control that keeps trainers apart on a shared router.

With usrpwd every session has a user name, and a Zenoh router can allow or deny each message
by its key expression, its direction and the user of the session it comes from or goes to.
:func:`isolation_rules` writes the router's ``access_control`` section for three roles:

- **servers** (``overtake-server`` users) may do anything under ``overtake/**``;
- **spectators** may ask servers for their status and watch the world frames;
- **trainers**, one user each, may ask servers for arenas, put actions and hold a liveliness
  token only under their own trainer names, and receive only their own steps: a trainer named
  ``alice-...`` (a trainer's name begins with its user name, see
  ``overtake.client.wire.remote``) neither reads ``bob-...``'s observations nor acts in his name,
  and sees no world frames. Acting in another trainer's arenas is refused by the server
  already (the ticket); this makes the attempt not reach it at all.

Everything not allowed is denied (``default_permission: deny``): a user the credentials file
lists but no role names can connect and do nothing. Trainer user names must be short and
without ``-`` (see :func:`check_trainer_user`), since the rules match a trainer's keys by the
prefix ``<user>-``.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

from overtake.protocol import keys

ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
# A trainer's name is "<user>-<host>-<pid>-<random>" with the user cut to
# keys.TRAINER_PREFIX_CHARS: a longer user name would not be the prefix of its trainers' names.
_TRAINER_USER = re.compile(rf"[A-Za-z0-9_.]{{1,{keys.TRAINER_PREFIX_CHARS}}}")

_EVERYTHING = f"{keys.ROOT}/**"
_REQUESTS = keys.ALL_SERVER_REQUESTS
_SERVERS_ALIVE = keys.ALL_SERVERS_ALIVE
_WORLD_ALL = keys.world_all()


def check_trainer_user(user: str) -> None:
    if not _TRAINER_USER.fullmatch(user):
        raise ValueError(
            f"trainer user {user!r} cannot be isolated: a trainer's user name must be 1 to "
            f"{keys.TRAINER_PREFIX_CHARS} letters, digits, '_' or '.' (no '-', which separates it "
            "from the rest of its trainers' names)"
        )


def _rule(rule_id: str, flows: Iterable[str], messages: Iterable[str], *key_exprs: str) -> dict:
    return {
        "id": rule_id,
        "permission": "allow",
        "flows": list(flows),
        "messages": list(messages),
        "key_exprs": list(key_exprs),
    }


def isolation_rules(
    servers: Iterable[str], spectators: Iterable[str], trainers: Iterable[str]
) -> dict[str, Any]:
    """The ``access_control`` section of a router's Zenoh configuration for these users."""
    servers, spectators, trainers = tuple(servers), tuple(spectators), tuple(trainers)
    if not servers:
        raise ValueError("isolating trainers needs at least one server user")
    roles = [*servers, *spectators, *trainers]
    twice = sorted({u for u in roles if roles.count(u) > 1})
    if twice:
        raise ValueError(f"user(s) {twice} named in more than one role")
    for user in trainers:
        check_trainer_user(user)
    rules = [_rule("server", ("ingress", "egress"), ALL_MESSAGES, _EVERYTHING)]
    subjects = [{"id": "servers", "usernames": list(servers)}]
    policies = [{"id": "servers", "rules": ["server"], "subjects": ["servers"]}]

    def grant(role: str, usernames: list[str], granted: list[dict[str, Any]]) -> None:
        rules.extend(granted)
        subjects.append({"id": role, "usernames": usernames})
        policies.append({"id": role, "rules": [r["id"] for r in granted], "subjects": [role]})

    if spectators:
        grant(
            "spectators",
            list(spectators),
            [
                _rule("spectator-asks", ("ingress",), ("query",), _REQUESTS),
                _rule("spectator-watches", ("ingress",), ("declare_subscriber",), _WORLD_ALL),
                _rule("spectator-receives", ("egress",), ("reply",), _REQUESTS),
                _rule("spectator-receives-world", ("egress",), ("put",), _WORLD_ALL),
                _rule(
                    "spectator-servers-alive",
                    ("ingress",),
                    ("declare_liveliness_subscriber", "liveliness_query"),
                    _SERVERS_ALIVE,
                ),
                _rule("spectator-sees-servers", ("egress",), ("liveliness_token",), _SERVERS_ALIVE),
            ],
        )
    for user in trainers:
        actions, steps, alive = keys.users_trainer_keys(user)
        grant(
            f"trainer {user}",
            [user],
            [
                # What the trainer's session sends.
                _rule(f"{user}/asks", ("ingress",), ("query",), _REQUESTS),
                _rule(f"{user}/acts", ("ingress",), ("put",), actions),
                _rule(f"{user}/listens", ("ingress",), ("declare_subscriber",), steps),
                _rule(f"{user}/is-alive", ("ingress", "egress"), ("liveliness_token",), alive),
                _rule(
                    f"{user}/watches-servers",
                    ("ingress",),
                    ("declare_liveliness_subscriber", "liveliness_query"),
                    _SERVERS_ALIVE,
                ),
                # What reaches it.
                _rule(f"{user}/answers", ("egress",), ("reply",), _REQUESTS),
                _rule(f"{user}/steps", ("egress",), ("put",), steps),
                _rule(f"{user}/servers-alive", ("egress",), ("liveliness_token",), _SERVERS_ALIVE),
                # The servers' declarations, so that its publisher matches their subscriber.
                _rule(
                    f"{user}/servers-listen",
                    ("egress",),
                    ("declare_subscriber",),
                    keys.ALL_SERVER_ACTIONS,
                ),
                _rule(f"{user}/servers-answer", ("egress",), ("declare_queryable",), _REQUESTS),
            ],
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def users_in(credentials_text: str) -> list[str]:
    """The user names of a usrpwd dictionary file (``user:password`` lines)."""
    return [
        line.split(":", 1)[0].strip()
        for line in credentials_text.splitlines()
        if line.strip() and ":" in line
    ]
