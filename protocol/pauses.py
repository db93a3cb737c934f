"""Python's cyclic garbage collector kept from pausing a call's frames.

A full collection looks at every object the process holds. The receiver holds about 170,000
(pyrender, trimesh, PyOpenGL and the decoder's own), so each one stopped it for 65-90 ms: four
in a 10 s loopback call, one of them mid-call, a picture 90 ms late (measured with gc's
callbacks). Almost all of those objects live as long as the session. :func:`settle`, called
once a session is built and before its frames flow, collects what is garbage then and sets
the rest aside (``gc.freeze``): later collections look only at what came after, and take a
millisecond or two. Reference counting still frees what is set aside; only cycles among those
objects would wait for the next settle, which every new session (a scene cut, a rejoin) makes.

The receiver only: the sender's full collection took 13-27 ms, at start-up, and settled, a
sender sharing its core with a busy process sent its sound worse (test_audio's sender-behind
case: voice correlation 0.82-0.94, under the 0.9 asked in 4 runs of 5; 0.96 in 3 of 3 without).
"""

from __future__ import annotations

import gc
import logging
import time

logger = logging.getLogger(__name__)


def settle() -> None:
    """Collect, then leave the objects alive now out of every later collection."""
    start = time.perf_counter()
    gc.unfreeze()
    collected = gc.collect()
    gc.freeze()
    logger.debug(
        "garbage collected: %d objects freed, %d set aside, %.0f ms",
        collected,
        gc.get_freeze_count(),
        (time.perf_counter() - start) * 1000,
    )
