"""The datagram path keeps the order of REM patches: a small patch that refers to an image
never overtakes the patch that brings that image, though the image waits for the budget
(paced) and the reference would fit in the next datagram. Real sockets on loopback."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest
from transport_helpers import TIMEOUT_MS, frame, join, open_media_path, snapshot

from facewire.protocol.clock import now_us
from facewire.protocol.media_path import BUCKET_S, DATAGRAM_COST
from facewire.protocol.packets import AudioFrame, KeyFrame, KeyframeRequest, RemPatch
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint


@pytest.fixture
def ends() -> Iterator[tuple[SenderEndpoint, ReceiverEndpoint]]:
    """A sender and a receiver joined, with their media path open."""
    with SenderEndpoint(plain=True) as sender:
        sender.set_snapshot(snapshot(seq=0))
        with ReceiverEndpoint("127.0.0.1", *sender.ports, plain=True) as receiver:
            join(sender, receiver)
            open_media_path(sender, receiver)
            yield sender, receiver


def test_a_reference_never_overtakes_the_image_it_names(
    ends: tuple[SenderEndpoint, ReceiverEndpoint],
) -> None:
    sender, receiver = ends
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    image = RemPatch(1, "eye_left", "webp", _webp(), 10.0, 0.5, 0.5)
    reference = RemPatch.referring(2, "eye_left", 1, 10.0, 0.5, 0.5)
    assert len(bytes(image)) > 600 and len(bytes(reference)) < 64
    sender.publish(image)  # paced: far more than a datagram's share of the budget
    sender.publish(frame(1))
    sender.end_frame()
    sender.publish(reference)
    sender.publish(frame(2))
    sender.end_frame()
    patches: list[int] = []
    while len(patches) < 2:
        assert time.monotonic() < deadline, f"patches received: {patches}"
        sender.end_frame()
        packet = receiver.recv(30)
        if isinstance(packet, RemPatch):
            patches.append(packet.seq)
    assert patches == [1, 2]


def test_a_keyframe_request_comes_by_both_paths(
    ends: tuple[SenderEndpoint, ReceiverEndpoint],
) -> None:
    """On DEALER, and in a datagram that no TCP retransmission holds up."""
    sender, receiver = ends
    sender.poll(timeout_ms=0)
    receiver.request_keyframe(12)
    requests: list[KeyframeRequest] = []
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while len(requests) < 2:
        assert time.monotonic() < deadline, f"requests: {requests}"
        requests += [p for p in sender.poll(timeout_ms=10) if isinstance(p, KeyframeRequest)]
    assert requests == [KeyframeRequest(12)] * 2


def _webp(seed: int = 1) -> bytes:
    import cv2

    noise = np.random.default_rng(seed).integers(0, 255, (48, 64, 3), dtype=np.uint8)
    ok, data = cv2.imencode(".webp", noise, [cv2.IMWRITE_WEBP_QUALITY, 90])
    assert ok
    return data.tobytes()


def test_a_keyframe_leaves_at_once_but_brings_patches_only_within_the_budget(
    ends: tuple[SenderEndpoint, ReceiverEndpoint],
) -> None:
    """A keyframe does not wait for its datagram's turn; the patches waiting behind it still
    wait for the budget. Paid for at any cost, a full datagram of them went with every
    keyframe: 400 ms in a 24 kbit/s link's queue, every 4 s."""
    sender, receiver = ends
    for seq in range(1, 4):  # several images' worth: far more than the budget's share
        sender.publish(RemPatch(seq, "eye_left", "webp", _webp(seed=seq), 10.0, 0.5, 0.5))
    sender.publish(frame(1))
    sender.end_frame()
    before = sender.media_figures()
    keyframe = frame(2, size=40)
    sender.publish(keyframe)
    after = sender.media_figures()
    assert after["datagrams_sent"] > before["datagrams_sent"]  # it left at once
    sent = after["wire_bytes_sent"] - before["wire_bytes_sent"]
    share = sender.budget_bps() * BUCKET_S / 8  # the most the token bucket holds
    assert sent <= len(bytes(keyframe)) + share + 2 * DATAGRAM_COST


def test_each_packet_is_stamped_when_its_datagram_was_read(
    ends: tuple[SenderEndpoint, ReceiverEndpoint],
) -> None:
    """``arrival_us`` times the frames the receive loop plays out: the packets of one
    datagram share it (the playout draws a bundle's frames at their own pace), and a datagram
    that came while the caller was busy with the ones before is stamped when it was read,
    never before it was sent (the loop once stamped every packet it took in a row with the
    first one's time: frames of a call's first second seemed to come before their capture)."""
    sender, receiver = ends
    while receiver.recv(50) is not None:
        pass
    sent = now_us()
    sender.publish(AudioFrame(0, sent, b"opus"))
    sender.publish(frame(1))  # a keyframe leaves at once, with what was due before it
    got: dict[str, int] = {}
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while len(got) < 2:
        assert time.monotonic() < deadline, f"received: {got}"
        packet = receiver.recv(30)
        if isinstance(packet, (AudioFrame, KeyFrame)):
            got[type(packet).__name__] = receiver.arrival_us
    assert got["AudioFrame"] == got["KeyFrame"] >= sent
    busy = now_us()
    sender.publish(frame(2))
    time.sleep(0.05)  # the caller draws a picture meanwhile
    packet = receiver.recv(TIMEOUT_MS)
    assert isinstance(packet, KeyFrame) and packet.seq == 2
    assert busy + 50_000 <= receiver.arrival_us <= now_us()
