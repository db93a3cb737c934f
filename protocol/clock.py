"""The clock frames are stamped with (``Frame.capture_us``)."""

import time


def now_us() -> int:
    """CLOCK_MONOTONIC in microseconds: shared by all processes of one Linux host, so a
    receiver on the sender's machine can subtract ``capture_us`` from it (glass-to-glass)."""
    return time.monotonic_ns() // 1000
