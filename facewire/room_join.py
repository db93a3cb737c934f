"""A newcomer to a room, or a peer's new scene, joined on a thread of its own
(facewire/room_peer.py)."""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from pathlib import Path

    from facewire.protocol.packets import Snapshot

#: Messages kept of a peer whose decoder is being built, decoded once it is (10 s and more of
#: a stream; beyond, the oldest are dropped and the keyframe asked for starts the chain).
JOIN_BACKLOG = 512


class Joining:
    """A newcomer being joined on a thread of its own: its snapshot read from the room's
    bucket and opened, and a keyframe asked for (``build``, which leaves :attr:`snapshot` None
    when the bucket has none of it yet). Read on the receiving loop, a relay slow to answer
    froze everyone else's pictures meanwhile; the decoder is then built on that loop (GL on
    one thread). The newcomer's messages wait in :attr:`backlog` until it is ready; ``ready`` is
    called (on the joining thread) when it is, or when it failed (:attr:`error`). A peer that
    went on to a new scene's session is joined so too, its old picture shown meanwhile."""

    def __init__(
        self,
        name: str,
        kid: int,
        record: Path | None,
        build: Callable[[Joining], None],
        ready: Callable[[], None],
        session: int | None = None,
    ) -> None:
        self.name = name
        self.kid = kid
        self.record = record  # where the newcomer's recording goes
        #: The session a peer already shown went on to (its new scene: protocol.md 8.9),
        #: whose snapshot ``build`` reads; None for a newcomer.
        self.session = session
        self.backlog: deque[tuple[str, bytes, int]] = deque(maxlen=JOIN_BACKLOG)
        #: What ``build`` read: the newcomer's snapshot.
        self.snapshot: Snapshot | None = None
        self.error: Exception | None = None
        self.asked_keyframe = False  # set by ``build`` once its request is out
        self.done = threading.Event()
        self._build = build
        self._ready = ready
        self.thread = threading.Thread(target=self._run, name=f"join-{name}", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self._build(self)
        except Exception as exc:  # the receiving loop says it (or raises it)
            self.error = exc
        finally:
            self.done.set()
            self._ready()

    def discard(self) -> None:
        """Wait for the snapshot's read (the participant is leaving; nothing was built)."""
        self.thread.join()
