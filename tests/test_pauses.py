"""The garbage collector set aside before a session's frames (protocol/pauses.py)."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Iterator

import pytest

from facewire.protocol.pauses import settle


class Node:
    def __init__(self) -> None:
        self.other: Node | None = None


def cycle() -> tuple[weakref.ref[Node], Node]:
    a, b = Node(), Node()
    a.other, b.other = b, a
    return weakref.ref(a), a


@pytest.fixture(autouse=True)
def unfrozen() -> Iterator[None]:
    yield
    gc.unfreeze()


def test_settle_frees_garbage_and_sets_the_living_aside() -> None:
    dead, node = cycle()
    del node  # a cycle: only the collector frees it
    alive, kept = cycle()
    settle()
    assert dead() is None
    assert gc.get_freeze_count() > 1000  # this process's modules and more
    assert not gc.is_tracked(kept) or all(o is not kept for o in gc.get_objects())
    # What comes after is collected as before.
    later, node = cycle()
    assert any(o is node for o in gc.get_objects())
    del node
    gc.collect()
    assert later() is None
    assert alive() is kept


def test_a_second_settle_frees_what_the_first_set_aside() -> None:
    gone, node = cycle()
    settle()
    del node  # garbage now, but set aside: no collection sees it
    gc.collect()
    assert gone() is not None
    settle()  # the next session's
    assert gone() is None
