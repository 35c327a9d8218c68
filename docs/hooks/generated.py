"""MkDocs hook: what the documentation site takes from the repository instead of copying it.

- ``<!-- generated: protocol-history -->`` (and ``-messages``, ``-keys``, ``-limits``) in a
  page becomes that section of :mod:`overtake.protocol.describe`, read from the protocol's
  own dataclasses when the site is built.
- ``<!-- generated: experiment NAME -->`` becomes the table an experiment left in
  ``bench/results/NAME/table.md`` with its curves, or a line saying none is recorded there.
- ``bench/RESULTS.md`` and ``bench/RELIABILITY.md`` become pages under ``results/``, and each
  experiment's ``curves.png`` an image beside them. Pages link the files where they are in the
  repository (``../bench/RESULTS.md``, which GitHub follows); the links are pointed at those
  pages when the site is built.
- The ``overtake.*`` namespace is laid out as folders under ``build/docs-api`` (links to the
  repository's ``client/``, ``server/``, ...) for mkdocstrings, since pyproject.toml maps
  those folders to the namespace and griffe looks for it by name on disk.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "bench" / "results"
# The package folders pyproject.toml maps into overtake.* (one list, read from there).
PACKAGES = tuple(
    sorted(
        tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"][
            "package-dir"
        ].values()
    )
)
MARKER = re.compile(r"<!-- generated: ([a-z0-9-]+)(?: ([A-Za-z0-9_.-]+))? -->")
PAGES = {
    "results/benchmarks.md": ROOT / "bench" / "RESULTS.md",
    "results/reliability.md": ROOT / "bench" / "RELIABILITY.md",
}
# bench/RESULTS.md links its history, the dated journals in bench/journal/, as journal/NAME.md.
PAGES.update(
    {f"results/journal/{p.name}": p for p in sorted((ROOT / "bench" / "journal").glob("*.md"))}
)


def _link_api_sources() -> None:
    namespace = ROOT / "build" / "docs-api" / "overtake"
    namespace.mkdir(parents=True, exist_ok=True)
    for package in PACKAGES:
        link = namespace / package
        if link.is_symlink() and link.resolve() == (ROOT / package).resolve():
            continue
        if link.is_symlink() or link.exists():
            link.unlink()
        link.symlink_to(ROOT / package, target_is_directory=True)


# At import, before mkdocstrings reads its configuration (hooks load with mkdocs.yml).
_link_api_sources()


def on_files(files: Files, config: Any) -> Files:
    for uri, source in PAGES.items():
        text = source.read_text(encoding="utf-8")
        note = (
            f"*This page is `{source.relative_to(ROOT)}` as it stands in the repository, "
            "each figure with the command that produced it.*\n\n"
        )
        heading, _, rest = text.partition("\n")
        files.append(File.generated(config, uri, content=f"{heading}\n\n{note}{rest}"))
    for curves in sorted(RESULTS.glob("*/curves.png")):
        uri = f"results/{curves.parent.name}/curves.png"
        files.append(File.generated(config, uri, abs_src_path=str(curves)))
    return files


def _experiment(name: str, page_uri: str) -> str:
    folder = RESULTS / name
    table = folder / "table.md"
    if not table.exists():
        return (
            f"*No results of `{name}` are recorded in `bench/results/{name}/` yet: "
            f"`overtake-experiment {name} --keep bench/results/{name}` makes them.*\n"
        )
    # The experiment's headings sit below the page's (## becomes ####).
    text = re.sub(
        r"^(#+) ", lambda m: "#" * (len(m.group(1)) + 2) + " ", table.read_text(), flags=re.M
    )
    depth = page_uri.count("/")
    prefix = "../" * depth
    parts = [f"From `bench/results/{name}/table.md`:\n", text.strip(), ""]
    if (folder / "curves.png").exists():
        parts.append(f"![Learning curves of {name}]({prefix}results/{name}/curves.png)\n")
    return "\n".join(parts)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Files) -> str:
    from overtake.protocol import describe

    def replace(match: re.Match[str]) -> str:
        kind, argument = match.group(1), match.group(2)
        if kind in describe.SECTIONS:
            return describe.SECTIONS[kind]()
        if kind == "experiment" and argument:
            return _experiment(argument, page.file.src_uri)
        raise PluginError(f"{page.file.src_uri}: unknown generated section {match.group(0)}")

    markdown = MARKER.sub(replace, markdown)
    prefix = "../" * page.file.src_uri.count("/")
    for uri, source in PAGES.items():
        in_repository = f"]({prefix}../{source.relative_to(ROOT)}"
        markdown = markdown.replace(in_repository, f"]({prefix}{uri}")
    return markdown


# Docstrings cross-reference in Sphinx's roles (:class:`~overtake.protocol.messages.Steps`),
# which mkdocstrings renders as they are written: the role's name, then the target as code.
_SPHINX_ROLE = re.compile(
    r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const):<code>(~?)([^<]+)</code>"
)


def _role_as_code(match: re.Match[str]) -> str:
    shortened, target = match.groups()
    target = target.lstrip(".")
    if shortened:  # Sphinx's "~": the last part only
        target = target.rsplit(".", 1)[-1]
    return f"<code>{target}</code>"


def on_page_content(html: str, page: Any, config: Any, files: Files) -> str:
    """The API reference's Sphinx roles as the code they name (``Steps``, not
    ``:class:`~overtake.protocol.messages.Steps```)."""
    return _SPHINX_ROLE.sub(_role_as_code, html)
