"""How ``--help`` says an option that may be left unset (a field ``X | None = None``): the
value's own name (PATH, NAME, N, the choices) where tyro would print ``{None}|STR``, and
``(default: unset)`` where it would print ``(default: None)``; the field's docstring says what
unset means. A field opts in by its annotation::

    json_out: Annotated[Path | None, unset("PATH")] = None
    \"\"\"also write the table as JSON here\"\"\"

A default other than None (a command that starts from a preset's settings) is said as ever.
"""

from __future__ import annotations

from typing import Any

import tyro


def _default_hint(default: str) -> str:
    return "(default: unset)" if default == "None" else f"(default: {default})"


def unset(metavar: str) -> Any:
    """The marker of an option that may be left unset, shown as ``metavar``."""
    return tyro.conf.arg(metavar=metavar, help_behavior_hint=_default_hint)


__all__ = ["unset"]
