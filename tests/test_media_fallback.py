"""The media's fallback: a firewall closes UDP in the middle of a call between two namespaces,
and the call goes on over ZeroMQ/TCP within 3 s, each end saying so in one line.

The link is tests/link_emulator.py's (two TUN devices and a user-space relay), which drops every
UDP packet once a given number have passed, while TCP still passes: the processes, sockets and
kernel are real. Skipped, with the reason, where namespaces cannot be made.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cli_call import Facewire, kill_all, run_facewire
from netns_pair import ADDRESS_B, Netem, TwoHosts, unavailable

REASON = unavailable()
pytestmark = pytest.mark.skipif(REASON is not None, reason=f"no network namespaces: {REASON}")

PORT = 5557
FRAMES = 360  # 12 s at 30 fps
#: UDP packets let through (about 6 s of the call: 15 datagrams a second up, 4 reports down)
BLOCK_AFTER = 120
#: The longest the picture may stand still: the path's 1.5 s timeout, a keyframe request's
#: round trip, and room for a busy machine (the issue allows 3 s for the switch).
MAX_FREEZE_FRAMES = round(3.0 * 30)


def _keys(folder: Path) -> Path:
    keys = folder / "keys"
    keys.mkdir()
    for name in ("alice", "bob"):
        assert run_facewire("keys", "--out", str(keys), "--name", name).returncode == 0
    return keys


def _said(process: Facewire, text: str) -> list[str]:
    return [line for line in process.lines + process.stderr if text in line]


def _call(
    hosts: TwoHosts, keys: Path, frames: int, stats: Path, *send_extra: str
) -> tuple[Facewire, Facewire]:
    """``receive --bind`` in host b (its stats to ``stats``) and ``send --connect --loop`` of
    ``frames`` frames in host a, both ended well; (sender, receiver)."""
    sender = receiver = None
    try:
        receiver = Facewire(
            "receive", "--bind", f"tcp://{ADDRESS_B}:{PORT}", "--once",
            "--stats", str(stats), "--key", str(keys / "bob.key_secret"),
            "--peer", str(keys / "alice.key"), prefix=hosts.command(hosts.b),
            name="receiver in b",
        )  # fmt: skip
        sender = Facewire(
            "send", "--connect", f"tcp://{ADDRESS_B}:{PORT}", "--loop", "--frames", str(frames),
            "--no-sound", *send_extra, "--key", str(keys / "alice.key_secret"),
            "--peer", str(keys / "bob.key"), prefix=hosts.command(hosts.a),
            name="sender in a",
        )  # fmt: skip
        assert sender.wait() == 0, sender.output()
        assert receiver.wait() == 0, receiver.output()
    finally:
        kill_all(sender, receiver)
    return sender, receiver


def test_udp_closed_mid_call_goes_on_over_tcp(tmp_path: Path) -> None:
    keys = _keys(tmp_path)
    stats, sent = tmp_path / "receiver.json", tmp_path / "sender.json"
    with TwoHosts(Netem(delay_ms=5, jitter_ms=0, loss=0), block_udp_after=BLOCK_AFTER) as hosts:
        sender, receiver = _call(hosts, keys, FRAMES, stats, "--stats", str(sent))
    print(hosts.relayed)
    report = json.loads(stats.read_text())
    media = report["media"]
    print("receiver:", media, "freezes:", report["freezes"])
    # The call began on UDP, then each end said once that the media went over TCP.
    assert media["udp"] and media["datagrams_received"] > BLOCK_AFTER / 2, media
    assert len(_said(sender, "its media go by ZeroMQ over TCP")) == 1, sender.output()
    assert len(_said(receiver, "media over ZeroMQ/TCP")) == 1, receiver.output()
    assert "UDP blocked" in hosts.relayed and " 0" not in hosts.relayed.split("UDP blocked")[1]
    # Every frame shown, the call ended by the sender's Bye, and no freeze past the switch.
    assert report["frames_out"] == FRAMES and report["ended_by"] == "bye", report
    longest = max((length for _first, length in report["freezes"]), default=0)
    assert longest <= MAX_FREEZE_FRAMES, report["freezes"]


def test_udp_closed_from_the_start_the_call_goes_over_tcp(tmp_path: Path) -> None:
    """No datagram ever passes: the media go on PUB from the first frame, and each end says
    so once, the sender 1.5 s after the receiver said it had the snapshot (its path could not
    open before: on a thin link the snapshot takes seconds). The call is 5 s: a sender that
    waited READY_WAIT_S (8 s) for the receiver's word would never say it."""
    keys = _keys(tmp_path)
    stats = tmp_path / "receiver.json"
    frames = 150
    with TwoHosts(Netem(delay_ms=5, jitter_ms=0, loss=0), block_udp_after=0) as hosts:
        sender, receiver = _call(hosts, keys, frames, stats)
    report = json.loads(stats.read_text())
    assert report["media"]["datagrams_received"] == 0, report["media"]
    assert len(_said(sender, "its media go by ZeroMQ over TCP")) == 1, sender.output()
    assert len(_said(receiver, "media over ZeroMQ/TCP")) == 1, receiver.output()
    assert report["frames_out"] == frames and report["ended_by"] == "bye", report
