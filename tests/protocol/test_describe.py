"""The protocol's description (docs/protocol.md is built from it) says what the code defines:
every message, part and field, the version and its history, the keys and the limits."""

from __future__ import annotations

import dataclasses
import re

from overtake.protocol import describe, keys, records
from overtake.protocol.messages import MESSAGE_TYPES
from overtake.protocol.version import PROTOCOL_HISTORY, PROTOCOL_VERSION


def _sections(markdown: str, level: str) -> dict[str, str]:
    """Heading title -> the text under it, for headings of exactly ``level`` (``###``)."""
    parts = re.split(rf"^{level} (.+)$", markdown, flags=re.M)
    return {title: body for title, body in zip(parts[1::2], parts[2::2], strict=True)}


def test_every_message_and_field_is_described_with_what_it_is() -> None:
    text = describe.describe_messages()
    sections = _sections(text, "###")
    parts = _sections(text, "####")
    for tag, cls in MESSAGE_TYPES.items():
        title = f"`{cls.__name__}` (type `{tag}`)"
        assert title in sections, f"{title} missing from the description"
    described = {**sections, **{title.strip("`"): body for title, body in parts.items()}}
    classes = [*MESSAGE_TYPES.values(), *describe._parts_used(list(MESSAGE_TYPES.values()))]
    assert {cls.__name__ for cls in classes} >= {"BehaviourSpec", "ObservationSpec", "RoadSpec"}
    for cls in classes:
        body = next(
            b
            for title, b in described.items()
            if title.startswith(f"`{cls.__name__}`") or title == cls.__name__
        )
        for field in dataclasses.fields(cls):
            rows = [line for line in body.splitlines() if line.startswith(f"| `{field.name}` |")]
            assert len(rows) == 1, f"{cls.__name__}.{field.name}: {len(rows)} rows"
            what = rows[0].rstrip("|").rsplit("|", 1)[-1].strip()
            # Every field says what it is (a comment or an attribute docstring in the source):
            # a default alone is not a description.
            assert what and not what.startswith("Default"), f"{cls.__name__}.{field.name}"


def test_fields_added_by_a_minor_version_say_since_when() -> None:
    text = describe.describe_messages()
    row = next(line for line in text.splitlines() if line.startswith("| `retire` |"))
    assert "| 1.3 |" in row
    row = next(line for line in text.splitlines() if line.startswith("| `queued_actions` |"))
    assert "| 1.4 |" in row


def test_version_history_keys_and_limits_come_from_the_code() -> None:
    major, minor = PROTOCOL_VERSION
    history = describe.describe_history()
    assert f"**{major}.{minor}**" in history
    for version, _ in PROTOCOL_HISTORY:
        assert f"| {version} |" in history
    assert f"| {major}.{minor} |" in history

    # The documented key expressions are the ones the code builds.
    documented = {
        line.split()[0]
        .replace("<server>", "srv")
        .replace("<trainer>", "trn")
        .replace("<arena>", "7")
        for line in describe.describe_keys().strip("`\n").splitlines()
        if line.startswith("overtake/")
    }
    built = {
        keys.server_request("srv"),
        keys.server_actions("srv", "trn"),
        keys.trainer_steps("trn", "srv"),
        keys.world("srv", 7),
        keys.server_alive("srv"),
        keys.trainer_alive("trn"),
    }
    assert documented == built

    limits = describe.describe_limits()
    assert f"{records.MAX_FRAME_BYTES:,} bytes" in limits
    for dtype in records.WIRE_DTYPES:
        assert f"`{dtype}`" in limits


def test_the_whole_description_has_each_section_once() -> None:
    text = describe.describe()
    assert [line for line in text.splitlines() if line.startswith("## ")] == [
        "## Version",
        "## Limits",
        "## Keys",
        "## Messages",
    ]
