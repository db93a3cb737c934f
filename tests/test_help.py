"""Every command's --help is plain text: no reStructuredText from the docstrings."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator

from facewire.cli import build_parser

#: ``literal``, `role`, :mod:`x`, *emphasis* as reStructuredText writes them.
MARKUP = re.compile(r"``|`[^`]+`|:(mod|func|class|meth|attr):|(?<![\w*])\*[A-Za-z][^*]*\*(?!\w)")


def parsers(parser: argparse.ArgumentParser, name: str) -> Iterator[tuple[str, str]]:
    yield name, parser.format_help()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from parsers(sub, f"{name} {sub_name}")


def test_help_texts_have_no_markup() -> None:
    helps = dict(parsers(build_parser(), "facewire"))
    assert {"facewire keys", "facewire wires extract", "facewire call"} <= set(helps)
    for name, text in helps.items():
        assert not MARKUP.search(text), f"{name} --help: {MARKUP.search(text)}\n{text}"
