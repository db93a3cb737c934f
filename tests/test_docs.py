"""The documents a new user reads: short enough to read, and true to each other and the code.

README.md fits in one read and BENCHMARKS.md holds today's figures, not a diary; every link
between the documents leads somewhere; every quoted section ("BENCHMARKS.md, "Playout"") in
the code and the docs names a section that exists; every facewire command the README and the
user guide show is one the command line takes.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from facewire.cli import build_parser

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", ROOT / "BENCHMARKS.md", *sorted((ROOT / "docs").glob("*.md"))]
#: "BENCHMARKS.md, "Title"" or "what-we-tried.md "Title"", and "... and "Other title"".
_SECTION_REF = re.compile(
    r'(BENCHMARKS\.md|what-we-tried\.md),?\s+"([^"]+)"(?:\s+and\s+"([^"]+)")?'
)
_LINK = re.compile(r"\]\(([^)\s]+)\)")


def _headings(path: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", path.read_text(), flags=re.S)
    return [m.group(1).strip() for m in re.finditer(r"^#{1,6}\s+(.+)$", text, re.M)]


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading."""
    return re.sub(r"[^\w\- ]", "", heading.lower()).replace(" ", "-")


def test_the_readme_fits_in_one_read_and_the_benchmarks_hold_todays_figures() -> None:
    assert (ROOT / "README.md").stat().st_size <= 12 * 1024
    assert (ROOT / "BENCHMARKS.md").stat().st_size <= 40 * 1024


def test_the_readme_picture_is_there() -> None:
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", (ROOT / "README.md").read_text())
    assert pictures and all((ROOT / p).is_file() for p in pictures), pictures


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_links_lead_somewhere(doc: Path) -> None:
    for target in _LINK.findall(doc.read_text()):
        if re.match(r"[a-z]+:", target):
            continue  # http://, mailto: and the like
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        assert path.exists(), f"{doc.name}: {target}"
        if anchor:
            slugs = {_slug(h) for h in _headings(path)}
            assert anchor in slugs, f"{doc.name}: {target} (anchors: {sorted(slugs)})"


def test_quoted_sections_exist() -> None:
    headings = {
        "BENCHMARKS.md": _headings(ROOT / "BENCHMARKS.md"),
        "what-we-tried.md": _headings(ROOT / "docs" / "what-we-tried.md"),
    }
    sources = [*DOCS, *ROOT.glob("*/*.py"), *ROOT.glob("*/*/*.py")]
    checked = 0
    for source in sources:
        if ".venv" in source.parts or source == Path(__file__).resolve():
            continue
        # Comments wrap: a title may run over "#: " or "# " at a line's start.
        text = re.sub(r"\s*\n\s*(#:?\s*)?", " ", source.read_text())
        for match in _SECTION_REF.finditer(text):
            doc = match.group(1)
            for title in filter(None, match.group(2, 3)):
                checked += 1
                assert any(h == title or h.startswith(title) for h in headings[doc]), (
                    f"{source.relative_to(ROOT)}: {doc}, {title!r} is no section of it"
                )
    assert checked >= 20  # the pattern still finds the references


def _shown_commands() -> list[tuple[str, str]]:
    """Every complete facewire command in a shell block of the README and the user guide
    (a synopsis, with its [options] and alternatives, is not one)."""
    commands = []
    for doc in (ROOT / "README.md", ROOT / "docs" / "guide.md"):
        for block in re.findall(r"```sh\n(.*?)```", doc.read_text(), flags=re.S):
            for line in block.splitlines():
                line = line.split("  #")[0].strip()
                program = line.split(maxsplit=1)[0] if line else ""
                if program.endswith("facewire") and not re.search(r"[\[|]", line):
                    commands.append((doc.name, line))
    return commands


def test_the_commands_shown_are_ones_facewire_takes() -> None:
    commands = _shown_commands()
    assert len(commands) >= 10
    parser = build_parser()
    for doc, line in commands:
        try:
            parser.parse_args(shlex.split(line)[1:])
        except SystemExit:
            pytest.fail(f"{doc}: {line}")
