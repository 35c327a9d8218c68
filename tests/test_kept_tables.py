"""A kept experiment's table copied into a page's Markdown source (so that GitHub shows it
too, not only the built site): between ``<!-- kept: PATH -->`` and ``<!-- /kept -->`` the page
holds PATH's text, its headings two levels down. The test fails where an experiment was run
again and its page not refreshed; ``python tests/test_kept_tables.py`` refreshes them."""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(r"(<!-- kept: (\S+) -->\n)(.*?)(<!-- /kept -->)", re.S)


def kept_text(path: str) -> str:
    """What a page keeps of ``path``: its text, its headings two levels down."""
    text = (ROOT / path).read_text(encoding="utf-8").strip()
    return re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + 2) + " ", text, flags=re.M)


def refreshed(page: str) -> str:
    """``page`` with every kept block holding its file as it is now."""
    return BLOCK.sub(lambda m: f"{m.group(1)}\n{kept_text(m.group(2))}\n\n{m.group(4)}", page)


def _pages() -> list[Path]:
    return [p for p in sorted((ROOT / "docs").rglob("*.md")) if BLOCK.search(p.read_text())]


def test_every_kept_table_in_the_pages_is_its_file_as_it_is_now():
    pages = _pages()
    assert ROOT / "docs" / "highway-env.md" in pages
    stale = [str(p.relative_to(ROOT)) for p in pages if refreshed(p.read_text()) != p.read_text()]
    assert not stale, f"refresh with `python tests/test_kept_tables.py`: {stale}"


def test_a_kept_block_is_refreshed_from_its_file():
    page = "a\n<!-- kept: bench/results/highway-env-equivalence/table.md -->\nold\n<!-- /kept -->\n"
    text = refreshed(page)
    assert "old" not in text and "#### Fixed drivers" in text and "| overtake | overtake |" in text


if __name__ == "__main__":
    for path in _pages():
        path.write_text(refreshed(path.read_text()))
        print(f"refreshed {path.relative_to(ROOT)}", file=sys.stderr)
