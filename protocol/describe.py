"""The wire protocol described in Markdown, read from its own definitions: the version and its
history, every message and part with its fields (type, the minor version that added it, what
it is), the key expressions and the limits. The documentation's protocol page is built from
this, so the page cannot fall behind the dataclasses; ``python -m overtake.protocol.describe``
prints it.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import textwrap
from functools import cache

from . import keys, records, specs
from .messages import MESSAGE_TYPES
from .records import Part
from .version import PROTOCOL_HISTORY, PROTOCOL_VERSION

# Sphinx roles in docstrings (:class:`~a.b.C`, :meth:`X.check`) as code spans (`C`, `X.check`).
_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")


def _plain(text: str) -> str:
    """Docstring text as Markdown: roles become code spans, rST's double backticks single."""

    def name(match: re.Match[str]) -> str:
        target = match.group(1)
        shown = target.rsplit(".", 1)[-1] if match.group(0).count("~") else target
        return f"`{shown}`"

    return _ROLE.sub(name, text).replace("``", "`")


@dataclasses.dataclass(frozen=True)
class FieldNote:
    """What the source says about one field: its annotation as written, the comments on and
    just above its line, and the string after it (an attribute docstring)."""

    annotation: str
    comment: str
    docstring: str


@cache
def field_notes(cls: type) -> dict[str, FieldNote]:
    """Each annotated field of ``cls`` with its notes: its own in source order, then those it
    inherits from the contract's dataclasses (a Steps' rows: :mod:`.rows`), nearest first."""
    notes: dict[str, FieldNote] = {}
    for owner in cls.__mro__:
        if owner is cls or (
            dataclasses.is_dataclass(owner) and owner.__module__.startswith(__package__ or "")
        ):
            for name, note in _own_field_notes(owner).items():
                notes.setdefault(name, note)
    return notes


@cache
def _own_field_notes(cls: type) -> dict[str, FieldNote]:
    """Each annotated field ``cls`` itself declares, with its notes, in source order."""
    source = textwrap.dedent(inspect.getsource(cls))
    lines = source.splitlines()
    (node,) = ast.parse(source).body
    assert isinstance(node, ast.ClassDef)
    notes: dict[str, FieldNote] = {}
    body = node.body
    for index, statement in enumerate(body):
        if not isinstance(statement, ast.AnnAssign) or not isinstance(statement.target, ast.Name):
            continue
        if "ClassVar" in ast.unparse(statement.annotation):
            continue
        comments: list[str] = []
        above = statement.lineno - 2
        while above >= 0 and lines[above].strip().startswith("#"):
            comments.insert(0, lines[above].strip().lstrip("#").strip())
            above -= 1
        end_line = lines[(statement.end_lineno or statement.lineno) - 1]
        code = ast.get_source_segment(source, statement) or ""
        trailing = end_line.split(code.splitlines()[-1], 1)[-1] if code else ""
        if "#" in trailing:
            comments.append(trailing.split("#", 1)[1].strip())
        docstring = ""
        following = body[index + 1] if index + 1 < len(body) else None
        if (
            isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docstring = inspect.cleandoc(following.value.value)
        notes[statement.target.id] = FieldNote(
            annotation=ast.unparse(statement.annotation),
            comment=" ".join(comments),
            docstring=docstring,
        )
    return notes


def _parts_used(classes: list[type]) -> list[type[Part]]:
    """The Part types (not messages) that the classes' fields hold, depth first, each once."""
    known = {
        name: value
        for module in (specs, records)
        for name, value in vars(module).items()
        if isinstance(value, type) and issubclass(value, Part)
    }
    from . import messages

    known.update(
        {
            name: value
            for name, value in vars(messages).items()
            if isinstance(value, type) and issubclass(value, Part)
        }
    )
    found: list[type[Part]] = []

    def visit(cls: type) -> None:
        for note in field_notes(cls).values():
            for word in re.findall(r"[A-Za-z_]+", note.annotation):
                part = known.get(word)
                if part is None or part in found or part in MESSAGE_TYPES.values():
                    continue
                found.append(part)
                visit(part)

    for cls in classes:
        visit(cls)
    return found


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def describe_class(cls: type, heading: str = "###") -> str:
    """One message or part: its docstring and a table of its fields."""
    tag = getattr(cls, "TYPE", None)
    title = f"{heading} `{cls.__name__}`" + (f" (type `{tag}`)" if tag else "")
    out = [title, ""]
    if cls.__doc__ and not cls.__doc__.startswith(f"{cls.__name__}("):
        out += [_plain(inspect.cleandoc(cls.__doc__)), ""]
    notes = field_notes(cls)
    declared = {f.name: f for f in dataclasses.fields(cls)}
    fields = [declared[name] for name in notes if name in declared]
    if not fields:
        out += ["No fields.", ""]
        return "\n".join(out)
    out += ["| field | type | since | what |", "|---|---|---|---|"]
    for f in fields:
        note = notes[f.name]
        since = f.metadata.get("since")
        since_text = f"1.{since}" if since is not None else ""
        what = " ".join(text for text in (note.docstring, note.comment) if text)
        if f.default is not dataclasses.MISSING:
            what = (what + " " if what else "") + f"Default `{f.default!r}`."
        out.append(
            f"| `{f.name}` | `{_cell(note.annotation)}` | {since_text} | {_cell(_plain(what))} |"
        )
    out.append("")
    return "\n".join(out)


def describe_history() -> str:
    major, minor = PROTOCOL_VERSION
    out = [
        f"This is protocol version **{major}.{minor}** (`overtake.protocol.PROTOCOL_VERSION`).",
        "",
        "| version | what it added |",
        "|---|---|",
    ]
    out += [f"| {version} | {_cell(text)} |" for version, text in PROTOCOL_HISTORY]
    return "\n".join(out) + "\n"


def describe_messages() -> str:
    messages = list(MESSAGE_TYPES.values())
    out = [describe_class(cls) for cls in messages]
    parts = _parts_used(messages)
    if parts:
        out.append("### The parts messages hold\n")
        out += [describe_class(cls, "####") for cls in parts]
    return "\n".join(out)


def describe_keys() -> str:
    doc = inspect.getdoc(keys) or ""
    block = doc.split("```")[1].strip("\n")
    return "```\n" + block + "\n```\n"


def describe_limits() -> str:
    rows = [
        ("a frame", f"{records.MAX_FRAME_BYTES:,} bytes ({records.MAX_FRAME_BYTES // 2**20} MiB)"),
        ("a text", f"{records.MAX_TEXT_CHARS:,} characters"),
        ("an array's dimensions", str(records.MAX_ARRAY_DIMS)),
        ("arenas in one open request", f"{records.MAX_ARENAS_PER_REQUEST:,}"),
        ("agents per arena", str(records.MAX_AGENTS_PER_ARENA)),
        ("a name (server, trainer, preset, observation)", f"`{records.NAME_PATTERN.pattern}`"),
        ("array dtypes", ", ".join(f"`{name}`" for name in records.WIRE_DTYPES)),
    ]
    out = ["| what | at most / allowed |", "|---|---|"]
    out += [f"| {what} | {value} |" for what, value in rows]
    return "\n".join(out) + "\n"


SECTIONS = {
    "protocol-history": describe_history,
    "protocol-messages": describe_messages,
    "protocol-keys": describe_keys,
    "protocol-limits": describe_limits,
}


def describe() -> str:
    """The whole description, every section under its own heading."""
    titles = {
        "protocol-history": "Version",
        "protocol-limits": "Limits",
        "protocol-keys": "Keys",
        "protocol-messages": "Messages",
    }
    return "\n".join(f"## {titles[name]}\n\n{SECTIONS[name]()}" for name in titles)


if __name__ == "__main__":
    print(describe())
