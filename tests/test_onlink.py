"""facewire/onlink.py: a real call across a veth pair of its own, its cost read from the
link's counters. Checks what the counts must be, not how large: both directions carried
packets, bytes agree with packets (no IP packet under 28 bytes, none over the MTU: segments,
not GSO bursts), both ends of the pair saw the same traffic, the receiver showed frames, and
a shaped link is shaped. Skipped, with the reason, where namespaces cannot be made.
"""

from __future__ import annotations

from typing import Any

import pytest

from facewire import onlink
from facewire.onlink import (
    ETHERNET_HEADER,
    MIN_PACKET,
    Counters,
    measure_call,
    span,
    tbf_args,
    unavailable,
)

REASON = unavailable()
needs_namespaces = pytest.mark.skipif(REASON is not None, reason=f"no link: {REASON}")
MTU = 1500


def test_span_counts_ip_bytes_per_direction() -> None:
    first = Counters(at=10.0, tx_bytes=1000, tx_packets=10, rx_bytes=500, rx_packets=5)
    last = Counters(at=12.0, tx_bytes=3000, tx_packets=30, rx_bytes=1500, rx_packets=15)
    s = span(first, last)
    assert s["seconds"] == 2.0
    assert s["up"]["packets"] == 20 and s["up"]["bytes"] == 2000
    assert s["up"]["ip_bytes"] == 2000 - 20 * ETHERNET_HEADER
    assert s["up"]["kbps"] == pytest.approx((2000 - 280) * 8 / 1000 / 2)
    assert s["up"]["pps"] == 10.0
    assert s["down"]["ip_bytes"] == 1000 - 10 * ETHERNET_HEADER
    assert s["total"]["packets"] == 30
    assert s["total"]["ip_bytes"] == s["up"]["ip_bytes"] + s["down"]["ip_bytes"]


def test_tbf_words_name_the_rate_bucket_and_queue() -> None:
    assert tbf_args(48) == ["tbf", "rate", "48kbit", "burst", "1600", "latency", "400ms"]
    assert onlink.TBF_BURST >= MTU + ETHERNET_HEADER  # a full-size frame fits the bucket


def _check_counts(direction: dict[str, Any]) -> None:
    assert direction["packets"] > 0 and direction["bytes"] > 0
    assert direction["ip_bytes"] >= MIN_PACKET * direction["packets"]
    assert direction["ip_bytes"] <= MTU * direction["packets"]


@needs_namespaces
@pytest.mark.timeout(90)
def test_a_call_on_a_clean_link_is_counted_both_ways() -> None:
    r = measure_call(None, seconds=3.0, rate_kbit=None, sound=False, settle_s=1.0)
    assert r["problem"] is None, r.get("output")
    for name in ("steady", "call"):
        for direction in ("up", "down"):
            _check_counts(r[name][direction])
    # The whole call holds the snapshot (tens of KB) sent as segments of at most the MTU.
    assert r["call"]["up"]["ip_bytes"] > r["steady"]["up"]["ip_bytes"]
    snapshot = r["sender"]["bytes_sent"]["snapshot"]
    assert r["call"]["up"]["packets"] >= snapshot / MTU
    # Both ends of the pair counted the same packets, each from its side.
    other = r["receiving_end_call"]
    for mine, theirs in (("up", "down"), ("down", "up")):
        assert r["call"][mine]["bytes"] == other[theirs]["bytes"]
        assert r["call"][mine]["packets"] == other[theirs]["packets"]
    assert r["qdisc"]["up"].get("drops", 0) == 0
    assert r["frames_shown"] > 0 and r["frames_sent"] > 0
    assert r["receiver"]["ended_by"] == "bye"
    assert r["first_picture_s"] is not None and r["first_picture_s"] > 0
    assert r["offered_s"] < r["snapshot_s"]
    # The bundled clip's snapshot takes over a second at the default budget: a draft comes
    # first and the full one behind the media; the steady window waits for it.
    assert r["receiver"]["refined"] == 1
    assert r["full_snapshot_s"] is not None and r["full_snapshot_s"] > r["snapshot_s"]


@needs_namespaces
@pytest.mark.skipif(
    REASON is None and unavailable(shaping=True) is not None, reason="tc tbf unavailable"
)
@pytest.mark.timeout(90)
def test_a_shaped_link_carries_no_more_than_its_rate() -> None:
    rate = 48.0
    r = measure_call(None, seconds=2.0, rate_kbit=rate, sound=False, settle_s=0.0)
    assert r["qdisc"]["up"]["kind"] == "tbf" and r["qdisc"]["down"]["kind"] == "tbf"
    assert r["qdisc"]["up"]["packets"] > 0
    # tbf counts Ethernet frames against the rate; a bucket's worth may pass at once.
    slack = onlink.TBF_BURST * 8 / 1000
    for name in ("steady", "call"):
        if name in r:  # a call that collapses on a thin link has no steady window
            s = r[name]
            assert s["up"]["kbps_ethernet"] <= rate + slack / s["seconds"] + 0.5
            _check_counts(s["up"])
    assert r["snapshot_s"] is not None, r.get("output")
