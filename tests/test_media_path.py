"""The media path: the Bundler's datagrams and budget, and both ends on real UDP sockets
(loopback only), with replays, forgeries and a flood of junk thrown at them."""

from __future__ import annotations

import logging
import math
import random
import socket
import time
import tracemalloc
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.protocol.bundle import (
    FRAGMENT,
    FRAGMENT_HEADER,
    HURRY,
    MAX_DATAGRAM,
    Fragment,
    Reassembly,
    Report,
    element_size,
    pack,
    unpack,
)
from facewire.protocol.datagram import IP_UDP_BYTES, OVERHEAD, RECEIVER_TO_SENDER, Opener
from facewire.protocol.media_path import (
    BUCKET_S,
    DATAGRAM_COST,
    DEFAULT_BUDGET_BPS,
    MAX_FRAMES_PER_DATAGRAM,
    PATH_TIMEOUT_S,
    READY_WAIT_S,
    Bundler,
    ReceiverMediaPath,
    SenderMediaPath,
    _is_loopback,
    frames_per_datagram,
)
from facewire.protocol.packets import (
    AudioFrame,
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    MediaKey,
    RemPatch,
    decode,
)

LOOPBACK = "127.0.0.1"
FPS = 30.0


def delta(i: int, size: int = 20) -> bytes:
    """A DeltaFrame of ``size`` bytes."""
    return bytes(DeltaFrame(i % 256, bytes([i % 251]) * (size - 2)))


def rem_patch(seed: int, side: int = 40) -> bytes:
    """A RemPatch of a noise PNG (about 5 KB at 40 x 40: noise does not compress)."""
    pixels = np.random.default_rng(seed).integers(0, 256, (side, side, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", pixels)
    assert ok
    return bytes(RemPatch(seed, "eye_left", "png", png.tobytes(), 10.0, 0.5, 0.5))


def packets_of(bundles: list[bytes], reassembly: Reassembly | None = None) -> list[bytes]:
    """The version-2 packets in ``bundles``, as a receiver takes them."""
    reassembly = reassembly or Reassembly()
    out = []
    for bundle in bundles:
        for element in unpack(bundle):
            if element[0] == FRAGMENT:
                whole = reassembly.add(Fragment.parse(element))
                if whole is not None:
                    out.append(whole)
            else:
                assert element[0] >> 4 == 2
                out.append(element)
    return out


def rss_bytes() -> int:
    """This process's resident set size (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise OSError("no VmRSS in /proc/self/status")


# --- frames_per_datagram -----------------------------------------------------------------------


def test_frames_per_datagram() -> None:
    assert DATAGRAM_COST == 40  # IPv4 20, UDP 8, the datagram's 12
    assert frames_per_datagram(1_000_000, FPS) == 1
    assert frames_per_datagram(38_400, FPS) == 1  # 30 x 40 bytes is a quarter of it
    assert frames_per_datagram(38_399, FPS) == 2
    assert DEFAULT_BUDGET_BPS == 32_000
    assert frames_per_datagram(DEFAULT_BUDGET_BPS, FPS) == 2
    assert frames_per_datagram(16_000, FPS) == 3
    assert frames_per_datagram(12_000, FPS) == 4
    assert frames_per_datagram(1_000, FPS) == MAX_FRAMES_PER_DATAGRAM == 4
    assert frames_per_datagram(32_000, 15.0) == 1


def test_frames_per_datagram_grows_as_the_budget_narrows() -> None:
    budgets = [1e6 / 1.1**i for i in range(80)]
    ks = [frames_per_datagram(b, FPS) for b in budgets]
    assert ks == sorted(ks)
    assert set(ks) == {1, 2, 3, 4}
    for budget, k in zip(budgets, ks, strict=True):
        if k < MAX_FRAMES_PER_DATAGRAM:  # the headers within a quarter of the budget
            assert DATAGRAM_COST * 8 * FPS / k <= 0.25 * budget


# --- Bundler -----------------------------------------------------------------------------------


def test_a_lossy_link_packs_fewer_frames_a_datagram() -> None:
    """Where datagrams are lost, the repeat comes a datagram later: one a frame at the default
    budget, while a thin budget still packs."""
    assert frames_per_datagram(DEFAULT_BUDGET_BPS, FPS, lossy=True) == 1
    assert frames_per_datagram(DEFAULT_BUDGET_BPS, FPS, lossy=False) == 2
    assert frames_per_datagram(16_000, FPS, lossy=True) == 2
    assert frames_per_datagram(8_000, FPS, lossy=True) == 3
    bundler = Bundler(FPS)
    bundler.losing = True
    for i in range(4):
        bundler.add(delta(i))
        assert len(bundler.end_frame(1000 + i / FPS, DEFAULT_BUDGET_BPS)) == 1
    assert bundler.k == 1


def test_repeats_carry_the_last_datagrams_updates_again() -> None:
    bundler = Bundler(FPS)
    bundler.redundant = True
    bundles = []
    for i in range(4):
        bundler.add(delta(i))
        bundles += bundler.end_frame(1000 + i / FPS, 1e6)
    assert [list(unpack(b)) for b in bundles] == [
        [delta(0)],
        [delta(0), delta(1)],
        [delta(1), delta(2)],
        [delta(2), delta(3)],
    ]


def test_while_losing_two_datagrams_lost_in_a_row_break_no_chain() -> None:
    """While the reports show loss, a datagram repeats the frame packets of the one before the
    last too (not its sound): the frames of any two datagrams lost in a row still come."""
    bundler = Bundler(FPS)
    bundler.redundant = bundler.losing = True
    bundles = []
    for i in range(5):
        bundler.add(delta(i), frame=True)
        bundler.add(bytes(AudioFrame(i, i * 20_000, b"opus")))
        bundles += bundler.end_frame(1000 + i / FPS, 1e6)
    assert len(bundles) == 5
    sound = [bytes(AudioFrame(i, i * 20_000, b"opus")) for i in range(5)]
    assert list(unpack(bundles[3])) == [delta(1), delta(2), sound[2], delta(3), sound[3]]
    for lost in range(3):  # datagrams lost, lost + 1 lost; lost + 2 arrives
        came = [e for b in (bundles[:lost] + bundles[lost + 2 :]) for e in unpack(b)]
        assert all(delta(i) in came for i in range(5)), lost
    # Once the loss stopped (the repeats still run), only the last datagram is repeated.
    bundler.losing = False
    bundler.add(delta(5), frame=True)
    assert list(unpack(bundler.end_frame(1000 + 5 / FPS, 1e6)[0])) == [delta(4), sound[4], delta(5)]


@pytest.mark.parametrize("budget, k", [(1e6, 1), (32_000, 2), (16_000, 3), (8_000, 4)])
def test_end_frame_sends_every_k_frames(budget: float, k: int) -> None:
    bundler = Bundler(FPS)
    sent: list[tuple[int, list[bytes]]] = []
    for i in range(24):
        bundler.add(delta(i))
        if i % 3 == 0:
            bundler.add(bytes(AudioFrame(i, i * 20_000, b"opus")))
        for bundle in bundler.end_frame(1000 + i / FPS, budget):
            sent.append((i, list(unpack(bundle))))
        assert bundler.k == k
    assert [i for i, _ in sent] == list(range(k - 1, 24, k))
    # Everything due goes in the next datagram, in order.
    assert [e for _, elements in sent for e in elements] == [
        p
        for i in range(24)
        for p in ([delta(i)] + ([bytes(AudioFrame(i, i * 20_000, b"opus"))] if i % 3 == 0 else []))
    ]


def test_nothing_due_sends_nothing() -> None:
    bundler = Bundler(FPS)
    assert all(bundler.end_frame(1000 + i / FPS, 1e6) == [] for i in range(10))
    assert bundler.flush(1001.0, math.inf) == []


def test_flush_sends_at_once() -> None:
    bundler = Bundler(FPS)
    bundler.add(delta(0))
    assert bundler.end_frame(1000.0, DEFAULT_BUDGET_BPS) == []  # k = 2: not yet
    bundler.add(bytes(Bye(7)))
    assert [list(unpack(b)) for b in bundler.flush(1000.01, math.inf)] == [
        [delta(0), bytes(Bye(7))]
    ]
    assert bundler.flush(1000.02, math.inf) == []


def test_many_due_updates_split_into_datagrams_that_fit() -> None:
    bundler = Bundler(FPS)
    due = [delta(i, size=100 + i) for i in range(40)]  # about 4.8 KB
    for packet in due:
        bundler.add(packet)
    bundles = bundler.end_frame(1000.0, 1e6)
    assert len(bundles) == 5
    assert all(len(b) + OVERHEAD <= MAX_DATAGRAM for b in bundles)
    assert packets_of(bundles) == due


def test_patch_too_large() -> None:
    with pytest.raises(ValueError, match=r"^a 65536-byte patch is too large for a datagram's"):
        Bundler(FPS).add_patch(bytes(65536))
    Bundler(FPS).add_patch(bytes(65535))


def run_bundler(
    bundler: Bundler, budget: float, seconds: float, due_size: int, t0: float = 1000.0
) -> list[tuple[float, bytes]]:
    """A frame of ``due_size`` bytes every 1/FPS s; (time, bundle) of each datagram sent."""
    out = []
    for i in range(int(seconds * FPS)):
        now = t0 + i / FPS
        bundler.add(delta(i, due_size))
        out += [(now, b) for b in bundler.end_frame(now, budget)]
    return out


@pytest.mark.parametrize("budget, due_size", [(8_000, 8), (16_000, 20), (32_000, 40), (64_000, 60)])
def test_patches_take_what_the_budget_leaves(budget: float, due_size: int) -> None:
    """Over 10 s the datagrams (headers counted) stay within the budget and one bucket; the
    patches fill what the frames leave; none exceeds MAX_DATAGRAM; the patches come back."""
    bundler = Bundler(FPS)
    # About 60 KB, more than 10 s carry; the first two small (800 bytes) to see some whole.
    patches = [rem_patch(seed, side=16 if seed < 2 else 40) for seed in range(12)]
    for patch in patches:
        bundler.add_patch(patch)
    sent = run_bundler(bundler, budget, 10.0, due_size)
    assert max(len(b) + OVERHEAD for _, b in sent) <= MAX_DATAGRAM
    wire = sum(len(b) + DATAGRAM_COST for _, b in sent)  # IPv4 and UDP headers too
    allowed = budget * 10.0 / 8 + budget * BUCKET_S / 8
    assert wire <= allowed
    assert wire > 0.85 * budget * 10.0 / 8  # the patches did use what was left
    received = packets_of([b for _, b in sent])
    rem = patches[0][0]  # a RemPatch's header byte
    got = [p for p in received if p[0] == rem]
    assert got == patches[: len(got)]
    assert len(got) >= 1
    carried = sum(
        len(e) - FRAGMENT_HEADER if e[0] == FRAGMENT else len(e)
        for _, b in sent
        for e in unpack(b)
        if e[0] in (FRAGMENT, rem)
    )
    assert bundler.patch_bytes_waiting == sum(map(len, patches)) - carried


def test_budget_respected_in_every_window() -> None:
    """Not only on average: any 2 s of datagrams cost at most 2 s of the budget plus a bucket."""
    budget = 16_000
    bundler = Bundler(FPS)
    for seed in range(6):
        bundler.add_patch(rem_patch(seed))
    sent = run_bundler(bundler, budget, 10.0, 20)
    times = [t for t, _ in sent]
    costs = [len(b) + DATAGRAM_COST for _, b in sent]
    for i, start in enumerate(times):
        window = sum(c for t, c in zip(times[i:], costs[i:], strict=True) if t < start + 2.0)
        assert window <= budget * (2.0 + BUCKET_S) / 8 + 1


def test_a_narrowed_budget_is_followed() -> None:
    bundler = Bundler(FPS)
    for seed in range(12):
        bundler.add_patch(rem_patch(seed))
    wide = run_bundler(bundler, 64_000, 5.0, 20)
    narrow = run_bundler(bundler, 12_000, 10.0, 20, t0=1005.0)
    cost = sum(len(b) + DATAGRAM_COST for _, b in narrow)
    assert cost <= 12_000 * (10.0 + BUCKET_S) / 8
    assert sum(len(b) + DATAGRAM_COST for _, b in wide) > 3 * cost / 2


def test_small_patch_goes_whole() -> None:
    bundler = Bundler(FPS)
    patch = bytes(RemPatch.referring(9, "eye_left", 3, 1.0, 0.5, 0.5))
    bundler.add_patch(patch)
    run = run_bundler(bundler, 64_000, 1.0, 20)
    assert patch in [e for _, b in run for e in unpack(b)]
    assert bundler.patch_bytes_waiting == 0


def _eye(seed: int) -> bytes:
    """A RemPatch of an eye's size on a clean link (150 bytes or so)."""
    pixels = np.random.default_rng(seed).integers(0, 256, (12, 12, 3), dtype=np.uint8)
    ok, webp = cv2.imencode(".webp", pixels, [cv2.IMWRITE_WEBP_QUALITY, 20])
    assert ok
    return bytes(RemPatch(seed, "eye_left", "webp", webp.tobytes(), 10.0, 0.5, 0.5))


def test_a_patch_the_bucket_lacks_a_little_for_goes_whole_and_is_paid_for_after() -> None:
    """A clean link's call: 20 kbit/s, two frames of 9 bytes a datagram, an eye patch of 150
    bytes every 300 ms. The bucket holds 166 bytes, the frames and headers take 60: sliced,
    each patch paid a Fragment's header twice. Whole, the bucket owes what it lacked, and the
    patches wait until it is paid: over 10 s the budget still holds."""
    budget = 20_000
    bundler = Bundler(FPS)
    patches = [_eye(n) for n in range(34)]
    assert all(130 <= len(p) <= 170 for p in patches)
    sent: list[tuple[float, bytes]] = []
    for i in range(300):
        now = 1000.0 + i / FPS
        if i % 9 == 0:
            bundler.add_patch(patches[i // 9])
        bundler.add(delta(i, 9))
        sent += [(now, b) for b in bundler.end_frame(now, budget)]
    elements = [e for _, b in sent for e in unpack(b)]
    assert FRAGMENT not in {e[0] for e in elements}
    assert [e for e in elements if e in patches] == patches
    wire = sum(len(b) + DATAGRAM_COST for _, b in sent)
    assert wire <= budget * (10.0 + BUCKET_S) / 8
    # While the rate control follows something (a queue, the call's start) nothing is owed.
    hurried = Bundler(FPS)
    hurried.hurry = True
    hurried.add_patch(patches[0])
    for i in range(30):
        hurried.add(delta(i, 9))
        for bundle in hurried.end_frame(1000.0 + i / FPS, budget):
            assert patches[0] not in unpack(bundle)


def test_patches_overtake_a_bulk_message_which_still_crosses() -> None:
    """The snapshot's full images (30 KB, a bulk message) crossing at 20 kbit/s: an eye patch
    queued after them leaves in the next datagram, not 20 s later as it did when both waited
    in one queue (the eyes stood still while the picture sharpened). The bulk message takes
    what the patches leave and comes whole."""
    bundler = Bundler(FPS)
    bulk = bytes(RemPatch(99, "eye_left", "png", rem_patch(7, side=100)[13:], 1.0, 0.5, 0.5))
    assert len(bulk) > 25_000
    bundler.add_bulk(bulk)
    eye = _eye(1)
    sent: list[tuple[float, bytes]] = []
    for i in range(900):
        now = 1000.0 + i / FPS
        if i == 30:
            bundler.add_patch(eye)
        bundler.add(delta(i, 9))
        sent += [(now, b) for b in bundler.end_frame(now, 20_000)]
    eye_at = next(t for t, b in sent if eye in unpack(b))
    assert eye_at - (1000.0 + 30 / FPS) < 0.1
    assert packets_of([b for _, b in sent]).count(bulk) == 1
    assert not bundler.holds(bulk) and bundler.bulk_bytes_waiting == 0


def test_a_bye_drops_the_bulk_messages_waiting() -> None:
    bundler = Bundler(FPS)
    bundler.add_bulk(rem_patch(3))
    bundler.drop_bulk()
    assert bundler.bulk_bytes_waiting == 0
    assert bundler.flush(1000.0, math.inf) == []


# --- both ends on real sockets -----------------------------------------------------------------


class Relay:
    """A UDP socket between the two ends (loopback): forwards both ways and keeps a copy of
    every datagram; what comes from the side named by ``hold`` is kept back in ``held``."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((LOOPBACK, 0))
        self.sock.setblocking(False)
        self.target = target
        self.client: tuple[str, int] | None = None
        self.from_client: list[bytes] = []
        self.from_target: list[bytes] = []
        self.held: list[bytes] = []
        self.hold: str | None = None  # "client", "target" or None

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def pump(self) -> None:
        while True:
            try:
                data, address = self.sock.recvfrom(4096)
            except BlockingIOError:
                return
            if address == self.target:
                side, to = "target", self.client
                self.from_target.append(data)
            else:
                side, to, self.client = "client", self.target, address
                self.from_client.append(data)
            if self.hold == side:
                self.held.append(data)
            elif to is not None:
                self.sock.sendto(data, to)

    def close(self) -> None:
        self.sock.close()


class Call:
    """A SenderMediaPath and a ReceiverMediaPath on loopback, on a clock moved by hand, with a
    Relay in between (the binding end is the relay's target)."""

    def __init__(self, sender_binds: bool = True) -> None:
        self.t = 1000.0
        self.sender_binds = sender_binds
        if sender_binds:
            self.sender = SenderMediaPath(LOOPBACK, 0, bind=True)
            self.relay = Relay(self.sender.sock.getsockname())
            self.receiver = ReceiverMediaPath(LOOPBACK, self.relay.address[1], bind=False)
        else:
            self.receiver = ReceiverMediaPath(LOOPBACK, 0, bind=True)
            self.relay = Relay(self.receiver.sock.getsockname())
            self.sender = SenderMediaPath(LOOPBACK, self.relay.address[1], bind=False)
        self.key = self.sender.offer(b"receiver-1", self.t)
        self.packets: list[bytes] = []

    @property
    def to_receiver(self) -> list[bytes]:
        """Every datagram the sender sent, as the relay saw it."""
        return self.relay.from_target if self.sender_binds else self.relay.from_client

    @property
    def to_sender(self) -> list[bytes]:
        return self.relay.from_client if self.sender_binds else self.relay.from_target

    def hold_to_receiver(self, hold: bool) -> None:
        """Keep the sender's datagrams in ``relay.held`` instead of passing them on."""
        self.relay.hold = ("target" if self.sender_binds else "client") if hold else None

    def deliver(self, datagram: bytes) -> None:
        """Pass a datagram on to the receiver (from the relay, where the sender's come from)."""
        self.relay.sock.sendto(datagram, (LOOPBACK, self.receiver.sock.getsockname()[1]))

    @property
    def ms(self) -> int:
        return round(self.t * 1000)

    def step(self, dt: float = 0.01) -> None:
        self.t += dt
        self.sender.read(self.t)
        self.sender.service(self.t)
        self.relay.pump()
        self.packets += self.receiver.read(self.t, self.ms)
        self.receiver.service(self.t, self.ms)
        self.relay.pump()

    def until(self, condition: Callable[[], bool], timeout_s: float = 2.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            assert time.monotonic() < deadline, "timed out"
            self.step()
            time.sleep(0.0005)

    def open(self) -> None:
        self.receiver.take_key(self.key, self.t)
        self.until(lambda: self.receiver.live(self.t) and bool(self.sender.live(self.t)))

    def send(self, packets: list[bytes]) -> None:
        assert self.sender.send(pack(packets), self.t) == 1

    def close(self) -> None:
        self.sender.close()
        self.receiver.close()
        self.relay.close()


@pytest.fixture(params=[True, False], ids=["sender-binds", "receiver-binds"])
def call(request: pytest.FixtureRequest) -> Iterator[Call]:
    c = Call(sender_binds=request.param)
    yield c
    c.close()


@pytest.fixture
def open_call() -> Iterator[Call]:
    c = Call(sender_binds=True)
    c.open()
    yield c
    c.close()


UPDATES = [
    bytes(KeyFrame(1, 3050556106, 42, 1_400_000, b"\x01\x02\x03" * 30)),
    bytes(DeltaFrame(2, b"\x09" * 17)),
    bytes(AudioFrame(70, 1_400_000, b"\xfc" * 40)),
    bytes(Heartbeat(3050556106, 42, 1_500_000)),
]


def test_a_receiver_is_loopback_is_told_apart(open_call: Call) -> None:
    """On loopback the headers cost no link anything (the transport then sends a datagram a
    frame and counts no headers: below); between two hosts they do."""
    assert open_call.sender.on_this_machine(open_call.t)
    assert frames_per_datagram(1_000, FPS, lossy=False, header_bytes=0) == 1
    for address in ["127.0.0.1", "127.8.0.1", "::1"]:
        assert _is_loopback((address, 5555))
    for address in ["192.0.2.2", "10.200.0.2", "fe80::1", "localhost", ""]:
        assert not _is_loopback((address, 5555))
    assert not _is_loopback(None)


def test_headers_not_counted_leave_the_patches_the_whole_budget() -> None:
    """To a receiver on this machine a datagram costs the budget its bundle alone: the patches
    take what the frames leave of it (the headers of a datagram a frame, 9.6 kbit/s at 30 fps,
    took a third of the default budget's patches there)."""
    sent = {}
    for header_bytes in (DATAGRAM_COST, 0):
        bundler = Bundler(FPS)
        bundler.header_bytes = header_bytes
        for seed in range(12):
            bundler.add_patch(rem_patch(seed))
        sent[header_bytes] = run_bundler(bundler, DEFAULT_BUDGET_BPS, 10.0, 20)
        assert bundler.k == (1 if header_bytes == 0 else 2)  # no headers: no frame waits
    bundles = sum(len(b) for _, b in sent[0])
    allowed = DEFAULT_BUDGET_BPS * (10.0 + BUCKET_S) / 8
    assert 0.9 * allowed < bundles <= allowed
    counted = sum(len(b) + DATAGRAM_COST for _, b in sent[DATAGRAM_COST])
    assert counted <= allowed and bundles > sum(len(b) for _, b in sent[DATAGRAM_COST]) + 4_000


@pytest.mark.timeout(20)
def test_a_path_that_never_opened_is_timed_from_the_snapshots_arrival(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A receiver that binds (`receive --bind`, a sender that connects) on a 16 kbit/s link:
    the snapshot's draft takes 1.2 s to cross, and the sender's hellos wait behind it. Timed
    from the key, the sender fell back to ZeroMQ just before the path opened (2 runs in 12).
    Timed from the receiver's "ready", and the receiver's own clock from the snapshot's
    arrival, neither says UDP is blocked until it is."""
    caplog.set_level(logging.WARNING, "facewire.protocol.media_path")
    call = Call(sender_binds=False)
    try:
        call.hold_to_receiver(True)
        call.receiver.take_key(call.key, call.t)
        call.step(1.2)  # the draft crossing
        call.receiver.joined(call.t)
        call.step(0.4)  # the receiver building its decoder
        call.sender.ready(b"receiver-1", call.t)
        assert not call.sender.fallback(call.t)
        call.step(1.0)
        assert not call.sender.fallback(call.t) and "UDP blocked" not in caplog.text
        call.step(0.2)
        assert "UDP blocked" in caplog.text and not call.sender.fallback(call.t)
        call.step(0.4)
        assert call.sender.fallback(call.t)
        assert caplog.text.count("UDP blocked") == 2, caplog.text  # each end says it once
    finally:
        call.close()


@pytest.mark.timeout(20)
def test_a_receiver_silent_while_it_builds_its_decoder_is_not_given_up_on(
    open_call: Call, caplog: pytest.LogCaptureFixture
) -> None:
    """The path opens with the receiver's key; then the receiver builds its decoder, reading
    nothing, for 1.7 s (a cold start). Only once it said it has the snapshot does its
    silence count."""
    caplog.set_level(logging.WARNING, "facewire.protocol.media_path")
    call = open_call
    for _ in range(170):  # the receiver busy: only the sender runs
        call.t += 0.01
        call.sender.read(call.t)
        call.sender.service(call.t)
    assert not call.sender.fallback(call.t) and "UDP blocked" not in caplog.text
    call.sender.ready(b"receiver-1", call.t)
    call.t += PATH_TIMEOUT_S - 0.1
    assert not call.sender.fallback(call.t)
    call.t += 0.2  # ready, and still silent: now it is down
    assert call.sender.fallback(call.t)


@pytest.mark.timeout(20)
def test_a_receiver_that_never_says_it_is_ready_is_given_up_on_later(call: Call) -> None:
    call.step(READY_WAIT_S + PATH_TIMEOUT_S - 0.1)
    assert not call.sender.fallback(call.t)
    call.step(0.2)
    assert call.sender.fallback(call.t)


@pytest.mark.timeout(20)
def test_hellos_open_the_path_both_ways(call: Call) -> None:
    assert not call.receiver.keyed
    assert isinstance(call.key, MediaKey) and call.key.udp == 1
    call.step()
    assert not call.sender.live(call.t)  # nothing before the key
    call.receiver.take_key(call.key, call.t)
    assert call.receiver.keyed
    call.until(lambda: call.receiver.live(call.t) and bool(call.sender.live(call.t)))
    assert not call.sender.fallback(call.t)
    assert call.sender.counts.dropped == {} and call.receiver.counts.dropped == {}
    assert call.sender.counts.datagrams_sent >= 1 and call.receiver.counts.datagrams_sent >= 1


@pytest.mark.timeout(20)
def test_bundles_arrive_as_the_same_packets(call: Call) -> None:
    call.open()
    call.send(UPDATES[:2])
    call.send(UPDATES[2:])
    call.send([])  # an empty bundle keeps the path open and carries nothing
    call.until(lambda: len(call.packets) >= 4)
    assert call.packets == UPDATES
    assert [type(decode(p)).__name__ for p in call.packets] == [
        "KeyFrame",
        "DeltaFrame",
        "AudioFrame",
        "Heartbeat",
    ]
    assert call.receiver.counts.dropped == {}


@pytest.mark.timeout(20)
def test_a_patch_comes_back_whole_from_its_fragments(call: Call) -> None:
    call.open()
    bundler = Bundler(FPS)
    patch = rem_patch(1)
    bundler.add_patch(patch)
    for i in range(300):
        bundler.add(delta(i))
        for bundle in bundler.end_frame(call.t, 64_000):
            assert len(bundle) + OVERHEAD <= MAX_DATAGRAM
            call.sender.send(bundle, call.t)
        call.step(1 / FPS)
        if patch in call.packets:
            break
    assert patch in call.packets
    frames = [p for p in call.packets if p != patch]
    assert frames == [delta(i) for i in range(len(frames))]
    assert call.receiver.patches_lost == 0
    assert call.receiver.malformed == 0


@pytest.mark.timeout(20)
def test_reports_reach_the_senders_controller(call: Call) -> None:
    call.open()
    peer = call.sender.live(call.t)[0]
    reports: list[tuple[int, ...]] = []
    on_report = peer.controller.on_report

    def spy(now: float, *fields: int) -> None:
        reports.append(fields)
        on_report(now, *fields)

    peer.controller.on_report = spy  # type: ignore[method-assign]
    for i in range(60):  # 2 s at 30 frames a second, a datagram of 120 bytes each
        call.sender.send(pack([delta(i, 100)]), call.t)
        call.step(1 / FPS)
    assert len(reports) >= 3  # one every 0.5 s
    highest, arrival_ms, received, nbytes = reports[-1]
    assert received >= 45  # the datagrams up to the last beat (the sender's hello answer too)
    datagram = element_size(100) + OVERHEAD
    assert nbytes >= 45 * datagram
    # What crossed the link: the datagrams' IP and UDP headers counted, as the budget does.
    wire = datagram + IP_UDP_BYTES
    assert peer.controller.last.received_bps == pytest.approx(30 * 8 * wire, rel=0.1)
    assert peer.controller.last.loss == 0
    assert call.sender.budget_bps(call.t, 1e6) == peer.controller.rate_bps


def test_a_keyframe_request_crosses_in_a_datagram_too(open_call: Call) -> None:
    """Over a lossy link TCP holds a lost request (and each one behind it) for a
    retransmission while the picture stays frozen: a copy goes in a datagram of its own."""
    call = open_call
    assert call.receiver.send_request(KeyframeRequest(41), call.t)
    call.until(lambda: bool(call.sender.keyframe_requests))
    assert call.sender.keyframe_requests == [KeyframeRequest(41)]
    assert call.sender.counts.dropped == {}


def test_a_receivers_datagram_with_anything_else_is_malformed(open_call: Call) -> None:
    """Reports and keyframe requests only: a frame packet the other way is refused whole."""
    call = open_call
    sealer = call.receiver._sealer
    assert sealer is not None
    call.relay.sock.sendto(
        sealer.seal(pack([bytes(KeyframeRequest(7)), delta(1)])), call.sender.sock.getsockname()
    )
    call.until(lambda: call.sender.counts.dropped.get("malformed") == 1)
    assert call.sender.keyframe_requests == []


@pytest.mark.parametrize("hurry", [False, True], ids=["steady", "hurried"])
def test_reports_on_their_beat_whenever_the_loop_comes_by(open_call: Call, hurry: bool) -> None:
    """A receiver whose loop comes by once a datagram (every 67 ms) still reports on the
    500 ms beat: 8 in 4 s, not one every eighth datagram (7). While the sender's datagrams
    ask for it (a Hurry element, here in every fourth), on the 250 ms beat: 16."""
    call = open_call
    call.step(1.0)  # the beat after the path opened
    sent = len(call.to_sender)
    for i in range(60):
        elements = [bytes([HURRY])] if hurry and i % 4 == 0 else []
        call.sender.send(pack([*elements, delta(i)]), call.t)
        call.step(1 / 15)
    assert len(call.to_sender) - sent in ((16, 17) if hurry else (8, 9))
    assert call.receiver.malformed == 0
    assert [delta(i) for i in range(60)] == call.packets[-60:]


def test_a_path_just_opened_reports_at_the_faster_beat(open_call: Call) -> None:
    """Before the sender's rate control has said anything, a thin link fills fastest: the
    first second after the path opens has four reports a second, with no Hurry element. (At
    two, a 16 kbit/s link's first queue went unseen long enough to drop datagrams, and the
    call lost frames and asked for keyframes for 26 s, 1.2 s behind.)"""
    call = open_call
    sent = len(call.to_sender)
    for i in range(14):  # 0.93 s
        call.sender.send(pack([delta(i)]), call.t)
        call.step(1 / 15)
    assert len(call.to_sender) - sent >= 3


def test_the_sender_asks_for_reports_at_most_every_quarter_second() -> None:
    """Hurry elements cost two bytes each: one in the first datagram of each 250 ms while the
    rate control wants reports (at a datagram every 67 ms: every fourth), none otherwise."""
    bundler = Bundler(FPS)
    carried = []
    for i in range(60):
        bundler.hurry = i < 30
        bundler.add(delta(i))
        for bundle in bundler.end_frame(i / FPS, 64_000):
            carried.append(bytes([HURRY]) in list(unpack(bundle)))
    assert len(carried) == 60 and sum(carried[:30]) == 4 and not any(carried[30:])


def test_arrival_is_when_the_datagram_came_not_when_the_loop_read_it(open_call: Call) -> None:
    """A receiver busy drawing reads its socket 150 ms after a datagram came: the report says
    when it came (the kernel's stamp), so the rate control sees no queue on the link."""
    call = open_call
    call.sender.send(pack([delta(0)]), call.t)
    call.relay.pump()
    came_ms = call.ms
    time.sleep(0.15)
    call.t += 0.15  # the receiver's loop comes back now
    call.packets += call.receiver.read(call.t, call.ms)
    assert call.packets == [delta(0)]
    assert came_ms - 20 <= call.receiver._arrival_ms <= came_ms + 40


@pytest.mark.timeout(20)
def test_replayed_and_forged_datagrams_are_dropped(call: Call) -> None:
    call.open()
    call.send(UPDATES[:1])
    call.until(lambda: call.packets == UPDATES[:1])
    seen = call.to_receiver[-1]
    call.hold_to_receiver(True)
    call.send(UPDATES[1:2])
    call.until(lambda: len(call.relay.held) == 1)
    fresh = call.relay.held.pop()  # not delivered yet: its index is still new
    call.hold_to_receiver(False)
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    attacker.bind((LOOPBACK, 0))
    try:
        receiver_at = (LOOPBACK, call.receiver.sock.getsockname()[1])
        attacker.sendto(seen, receiver_at)  # the very bytes again
        altered = bytearray(fresh)
        altered[10] ^= 0x01
        attacker.sendto(bytes(altered), receiver_at)
        attacker.sendto(fresh[:-1], receiver_at)  # cut: the tag fails
        attacker.sendto(fresh[:11], receiver_at)  # shorter than a header and tag
        call.until(lambda: sum(call.receiver.counts.dropped.values()) >= 4)
        assert call.receiver.counts.dropped == {"replayed": 1, "forged": 2, "malformed": 1}
        assert call.packets == UPDATES[:1]
        # The forgeries did not use up the index: the genuine datagram still opens.
        call.deliver(fresh)
        call.until(lambda: call.packets == UPDATES[:2])
        # The sender's side likewise: a receiver's datagram again, and one with a new seq.
        report = call.to_sender[-1]
        seq = int.from_bytes(report[2:4], "big")
        sender_at = (LOOPBACK, call.sender.sock.getsockname()[1])
        attacker.sendto(report, sender_at)
        attacker.sendto(
            report[:2] + ((seq + 100) % 65536).to_bytes(2, "big") + report[4:], sender_at
        )
        call.until(lambda: sum(call.sender.counts.dropped.values()) >= 2)
        assert call.sender.counts.dropped == {"replayed": 1, "forged": 1}
    finally:
        attacker.close()
    # Nothing refused moved the path: datagrams still go both ways.
    call.send(UPDATES[2:3])
    call.until(lambda: call.packets == UPDATES[:3])
    reports = len(call.to_sender)
    call.until(lambda: len(call.to_sender) > reports + 1)
    assert call.sender.live(call.t) and call.receiver.live(call.t)
    assert call.sender.counts.dropped == {"replayed": 1, "forged": 1}
    assert call.receiver.counts.dropped == {"replayed": 1, "forged": 2, "malformed": 1}


@pytest.mark.timeout(20)
def test_report_names_the_highest_index_after_reordering(call: Call) -> None:
    """docs/protocol.md 8.3: a Report's ``highest`` is the highest index accepted.

    BUG (protocol/media_path.py, ReceiverMediaPath.read: ``self._highest, self._arrival_ms =
    index, now_ms``, line 491 at 4be004d): every accepted datagram sets ``_highest`` to its own
    index, so a late one (reordered) moves it back; the next report names an older datagram
    and the sender's controller, computing ``expected`` from it, sees loss where there was
    none (the next test). Fix: take ``_highest`` and ``_arrival_ms`` only when the index is the
    highest so far (``index == self._opener.window.highest`` after ``open``)."""
    call.open()
    call.step(0.3)  # a report went; the next one comes after 0.25 s
    call.hold_to_receiver(True)
    for i in range(3):
        call.send([delta(i)])
    call.until(lambda: len(call.relay.held) == 3)
    first, second, third = call.relay.held
    call.hold_to_receiver(False)
    for datagram in (first, third, second):  # the second comes late
        call.deliver(datagram)
    call.until(lambda: len(call.packets) == 3)
    reports = len(call.to_sender)
    call.step(0.3)
    call.until(lambda: len(call.to_sender) > reports)
    opener = Opener(call.key.secret, RECEIVER_TO_SENDER, call.key.key_id)
    report = Report.parse(next(unpack(opener.open(call.to_sender[-1])[1])))
    assert report.highest & 0xFFFF == int.from_bytes(third[2:4], "big")


@pytest.mark.timeout(20)
def test_reordering_alone_does_not_cut_the_rate(open_call: Call) -> None:
    """The consequence of the bug above: one datagram late by one place, nothing lost, and
    the report after next tells the sender a quarter of its datagrams were lost; the rate is
    cut. Fails until ReceiverMediaPath.read keeps the highest index."""
    call = open_call
    peer = call.sender.live(call.t)[0]
    for late in (True, False):
        call.step(0.3)
        call.hold_to_receiver(True)
        for i in range(3):
            call.send([delta(i)])
        call.until(lambda: len(call.relay.held) == 3)
        first, second, third = call.relay.held
        call.relay.held.clear()
        call.hold_to_receiver(False)
        got = len(call.packets)
        for datagram in (first, third, second) if late else (first, second, third):
            call.deliver(datagram)
        call.until(lambda n=got + 3: len(call.packets) == n)
        reports = len(call.to_sender)
        call.step(0.3)
        call.until(lambda n=reports: len(call.to_sender) > n)
        call.step(0.001)  # the sender reads the report
        assert peer.controller.last.loss == 0
    assert peer.controller.decreases == 0


@pytest.mark.timeout(30)
def test_flood_of_junk_is_dropped_and_memory_stays_flat(open_call: Call) -> None:
    """100,000 datagrams of junk, forgeries, cut and altered copies and replays at the
    receiver's port: no exception, no packet, every one counted as dropped, memory flat; the
    sender's datagrams still get through afterwards."""
    call = open_call
    for i in range(20):
        call.send([delta(i)])
        call.step()
    call.until(lambda: len(call.packets) == 20)
    genuine = [d for d in call.to_receiver if len(d) > OVERHEAD][-20:]
    assert len(genuine) == 20
    key_id = call.key.key_id
    rng = random.Random(2024)

    def junk() -> bytes:
        kind = rng.random()
        if kind < 0.25:
            return rng.randbytes(rng.randrange(0, 1500))
        if kind < 0.5:  # well-formed header, random seq, random "ciphertext"
            head = bytes([0x30, key_id]) + rng.randbytes(2)
            return head + rng.randbytes(rng.randrange(0, 1200))
        real = rng.choice(genuine)
        if kind < 0.65:
            altered = bytearray(real)
            altered[rng.randrange(len(altered))] ^= rng.randrange(1, 256)
            return bytes(altered)
        if kind < 0.75:
            return real
        if kind < 0.85:
            return real[: rng.randrange(len(real))]
        if kind < 0.95:  # longer than a receiver reads: cut at 2048, its tag fails
            return real[:4] + rng.randbytes(rng.randrange(2045, 3000))
        return bytes([0x30, (key_id + 1) % 256]) + real[2:]

    flood = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    flood.bind((LOOPBACK, 0))
    target = (LOOPBACK, call.receiver.sock.getsockname()[1])
    counts = call.receiver.counts

    def throw(n: int) -> None:
        start = counts.datagrams_received
        thrown = 0
        while thrown < n:
            batch = min(32, n - thrown)
            for _ in range(batch):
                flood.sendto(junk(), target)
            thrown += batch
            deadline = time.monotonic() + 2.0
            while counts.datagrams_received < start + thrown:
                assert call.receiver.read(call.t, call.ms) == []
                assert time.monotonic() < deadline, "datagrams lost on loopback"

    try:
        throw(5_000)  # warm-up: every kind of drop counted once, buffers grown
        rss = rss_bytes()
        tracemalloc.start()
        try:
            before = tracemalloc.get_traced_memory()[0]
            dropped = sum(counts.dropped.values())
            received = counts.datagrams_received
            started = time.monotonic()
            throw(100_000)
            elapsed = time.monotonic() - started
            grown = tracemalloc.get_traced_memory()[0] - before
        finally:
            tracemalloc.stop()
        rss_grown = rss_bytes() - rss
    finally:
        flood.close()
    assert counts.datagrams_received - received == 100_000
    assert sum(counts.dropped.values()) - dropped == 100_000
    assert set(counts.dropped) <= {"malformed", "forged", "replayed"}
    assert counts.dropped["replayed"] > 5_000
    assert grown < 64 * 1024, f"{grown} bytes more after the flood"
    assert rss_grown < 16 * 2**20, f"resident set {rss_grown} bytes larger after the flood"
    assert call.receiver.malformed == 0 and call.receiver.patches_lost == 0
    assert elapsed < 20
    # The real sender still gets through.
    call.send([delta(100)])
    call.until(lambda: call.packets[-1:] == [delta(100)])
    assert call.packets == [delta(i) for i in range(20)] + [delta(100)]
