"""The documentation names no experiment the catalogue lacks (issue 68): every
``overtake-experiment NAME`` in README.md and docs/ runs an experiment of
:data:`overtake.trainers.experiment.EXPERIMENTS`, and every experiment's name they mention (a
paper preset's name, a dash and more: ``min2018-table3``; not a path's part) is one of them, or
a retired one (:data:`overtake.trainers.experiment.RETIRED`) in a paragraph that says it is
retired and never as a command."""

from __future__ import annotations

import re
from pathlib import Path

from overtake.trainers.experiment import EXPERIMENTS, RETIRED

ROOT = Path(__file__).resolve().parents[2]
PREFIXES = sorted({experiment.preset for experiment in EXPERIMENTS.values()})
# An experiment's name: a preset's, a dash, words joined by dashes; not part of a path, a file
# name or a longer word (bench/results/min2018-table3, min2018-safe-both-all-both-medium.jsonl).
NAME = re.compile(
    rf"(?<![\w/.-])(?:{'|'.join(map(re.escape, PREFIXES))})(?:-[a-z0-9]+)+(?![\w/.-])"
)
COMMAND = re.compile(r"overtake-experiment\b(?!-)")
DASHED = re.compile(r"[a-z][a-z0-9]*(?:-[a-z0-9]+)+")
# Where a command's words end: the end of an inline code span, a comment, a shell operator.
COMMAND_END = re.compile(r"[`#|;&<>]")


def pages() -> list[Path]:
    """README.md and every page of the documentation."""
    return [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]


def command_names(text: str) -> list[tuple[int, str]]:
    """(line, name) for each ``overtake-experiment`` command in ``text`` that names an
    experiment: its first word that is not an option, a number or a path, where that word is
    a name (words joined by dashes; a placeholder, ``NAME``, or prose, "overtake-experiment is
    running", names none); backslash-continued lines are read on."""
    lines = text.splitlines()
    found = []
    for number, line in enumerate(lines, 1):
        for match in COMMAND.finditer(line):
            rest, following = line[match.end() :], number
            while rest.rstrip().endswith("\\") and following < len(lines):
                rest = rest.rstrip()[:-1] + " " + lines[following]
                following += 1
            end = COMMAND_END.search(rest)
            words = (rest[: end.start()] if end else rest).split()
            for word in words:
                if word.startswith("-") or word.replace(".", "").isdigit() or "/" in word:
                    continue
                if DASHED.fullmatch(word):
                    found.append((number, word))
                break
    return found


def paragraphs(text: str) -> list[tuple[int, str]]:
    """(first line, text) of each paragraph (lines between blank lines)."""
    found, start, lines = [], 1, []
    for number, line in enumerate(text.splitlines() + [""], 1):
        if line.strip():
            if not lines:
                start = number
            lines.append(line)
        elif lines:
            found.append((start, "\n".join(lines)))
            lines = []
    return found


def unknown_names(text: str) -> list[str]:
    """What ``text`` (a page) names that the catalogue lacks, one line each."""
    problems = []
    for number, name in command_names(text):
        if name in RETIRED:
            problems.append(f"line {number}: overtake-experiment {name}, {RETIRED[name]}")
        elif name not in EXPERIMENTS:
            problems.append(f"line {number}: overtake-experiment {name}, not in the catalogue")
    for start, paragraph in paragraphs(text):
        for match in NAME.finditer(paragraph):
            name = match.group(0)
            line = start + paragraph.count("\n", 0, match.start())
            if name in EXPERIMENTS:
                continue
            if name in RETIRED:
                if "retired" not in paragraph:
                    problems.append(
                        f"line {line}: {name} is retired, and its paragraph does not say so"
                    )
                continue
            problems.append(f"line {line}: {name}, not in the catalogue")
    return problems


def test_the_documentation_names_no_experiment_the_catalogue_lacks():
    problems = {
        str(page.relative_to(ROOT)): found
        for page in pages()
        if (found := unknown_names(page.read_text(encoding="utf-8")))
    }
    assert not problems, problems


def test_the_pages_name_the_experiments_this_test_reads():
    # The test reads what it should: the commands and the names of the pages as they are.
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    experiments = (ROOT / "docs" / "experiments.md").read_text(encoding="utf-8")
    assert "ho2018-table8" in [name for _, name in command_names(readme)]
    names = {match.group(0) for match in NAME.finditer(experiments)}
    assert set(EXPERIMENTS) <= names, set(EXPERIMENTS) - names


def test_a_name_the_catalogue_lacks_is_found_where_it_stands():
    page = "\n".join(
        [
            "Run it:",
            "",
            "```bash",
            ".venv/bin/overtake-experiment min2018-table4 --jobs 2 \\",
            "    --keep bench/results/min2018-table4      # a typo",
            ".venv/bin/overtake-experiment --jobs 2 ho2018-table9",
            ".venv/bin/overtake-experiment NAME --out runs/x",
            "```",
            "",
            "`overtake-experiment min2018-safe-both` was a table; so was `fayjie2018-fig7`.",
            "",
            "`min2018-safe-both` (retired, issue 56) and bench/results/min2018-gone/ are fine.",
        ]
    )
    assert unknown_names(page) == [
        "line 4: overtake-experiment min2018-table4, not in the catalogue",
        "line 6: overtake-experiment ho2018-table9, not in the catalogue",
        f"line 10: overtake-experiment min2018-safe-both, {RETIRED['min2018-safe-both']}",
        "line 4: min2018-table4, not in the catalogue",
        "line 6: ho2018-table9, not in the catalogue",
        "line 10: min2018-safe-both is retired, and its paragraph does not say so",
        "line 10: fayjie2018-fig7, not in the catalogue",
    ]
    assert unknown_names("`overtake-experiment min2018-table3 --rows dueling-both`") == []
