"""``facewire send``, ``receive`` and ``call`` as a user types them, each end its own process.

Real processes, real sockets on 127.0.0.1, real CURVE keys made by ``facewire keys``, real
rendering and recording. Bad use must end with one line on stderr and exit status 1.
"""

from __future__ import annotations

import itertools
import json
import signal
import socket
from pathlib import Path

import pytest
from cli_call import (
    Facewire,
    all_end_well,
    count_frames,
    free_ports,
    hang_up,
    run_facewire,
    sent_frames,
    wait_for_file,
)

from facewire.call import summary
from facewire.quality import read_frames, score_frames, track_all
from facewire.receiver.session import ReceiverReport
from facewire.sender.capture import demo_clip_path

FRAMES = 120
#: Mean face-region SSIM of a call's recording against the bundled clip, frame i against i.
#: Measured: an aligned call 0.72; the recording 10 frames late 0.56; the first frame held
#: throughout 0.50.
MIN_FACE_SSIM = 0.65


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    folder = tmp_path / "keys"
    folder.mkdir()
    for name in ("alice", "bob"):
        made = run_facewire("keys", "--out", str(folder), "--name", name)
        assert made.returncode == 0, made.stderr
    return folder


def face_ssim(recording: Path, frames: int) -> float:
    inputs = list(itertools.islice(read_frames(demo_clip_path()), frames))
    outputs = list(read_frames(recording))
    return score_frames(inputs, outputs, track_all(inputs)).mean_ssim("face")


def one_line_error(result_stderr: str) -> str:
    lines = result_stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("facewire: error: "), result_stderr
    assert "Traceback" not in result_stderr
    return lines[0]


@pytest.mark.parametrize("sender_binds", [False, True], ids=["receiver-binds", "sender-binds"])
def test_call_between_two_processes_with_keys(
    tmp_path: Path, keys: Path, sender_binds: bool
) -> None:
    port = free_ports(2)
    bound, connected = f"tcp://127.0.0.1:{port}", f"tcp://127.0.0.1:{port}"
    record, stats = tmp_path / "call.mp4", tmp_path / "stats.json"
    receiver = Facewire(
        "receive",
        *(("--connect", connected) if sender_binds else ("--bind", bound)),
        *("--record", str(record), "--stats", str(stats), "--once"),
        *("--key", str(keys / "bob.key_secret"), "--peer", str(keys / "alice.key")),
    )
    sender = Facewire(
        "send",
        *(("--bind", bound) if sender_binds else ("--connect", connected)),
        *("--frames", str(FRAMES)),
        *("--key", str(keys / "alice.key_secret"), "--peer", str(keys / "bob.key")),
    )
    try:
        assert sender.wait() == 0, sender.output()
        assert receiver.wait() == 0, receiver.output()
    finally:
        sender.kill()
        receiver.kill()
    # On two busy cores a frame can wait 50 ms on loopback, and the receiver then asks for
    # the second path (receiver/lateness.py): a notice of the designed response, not part of
    # what this test checks.
    said = [line for line in sender.lines if not line.startswith("the receiver sees late")]
    assert said[-2] == "a receiver joined; sending"
    assert sent_frames(said[-1]) == (FRAMES, "end of input"), said[-1]
    assert f"session ended (bye) after {FRAMES} frames" in receiver.lines, receiver.output()
    report = json.loads(stats.read_text())
    assert report["frames_out"] == FRAMES and report["ended_by"] == "bye"
    assert report["malformed"] == 0 and report["sessions"] == 1
    # A conversation wants the least latency: frames are drawn as they arrive unless asked.
    assert report["playout"]["mode"] == "on arrival"
    assert count_frames(record) == FRAMES
    assert face_ssim(record, FRAMES) > MIN_FACE_SSIM


def test_sigterm_on_either_end_ends_cleanly_and_the_other_end_waits(
    tmp_path: Path, keys: Path
) -> None:
    port = free_ports(2)
    record = tmp_path / "first.mp4"
    receive_keys = ("--key", str(keys / "bob.key_secret"), "--peer", str(keys / "alice.key"))
    send_keys = ("--key", str(keys / "alice.key_secret"), "--peer", str(keys / "bob.key"))
    sender = Facewire("send", "--bind", f"tcp://127.0.0.1:{port}", "--loop", *send_keys)
    first = second = None
    try:
        first = Facewire(
            "receive", "--connect", f"tcp://127.0.0.1:{port}", "--record", str(record),
            *receive_keys, name="first receiver",
        )  # fmt: skip
        sender.expect("a receiver joined; sending")
        wait_for_file(record, 100_000, first)
        # The receiver is stopped mid-call: its recording is closed with its index, and the
        # sender says so and waits for another receiver.
        first.signal(signal.SIGTERM)
        assert first.wait() == 0, first.output()
        summary = first.lines[-1]
        assert summary.startswith("received 1 session(s), ") and "(stopped)" in summary, summary
        recorded = int(summary.split(", ")[1].split()[0])
        assert recorded > 0 and count_frames(record) == recorded
        sender.expect("the receiver left; waiting for another")
        # A new receiver is taken on; then the sender is stopped: it says bye, and the
        # receiver says so in one line and waits for a new session.
        stats = tmp_path / "second.json"
        second = Facewire(
            "receive", "--connect", f"tcp://127.0.0.1:{port}", "--record",
            str(tmp_path / "second.mp4"), "--stats", str(stats), *receive_keys,
            name="second receiver",
        )  # fmt: skip
        second.expect("session ")
        sender.expect("a receiver joined")
        wait_for_file(tmp_path / "second.mp4", 50_000, second)
        sender.signal(signal.SIGINT)
        assert sender.wait() == 0, sender.output()
        assert sent_frames(sender.lines[-1])[1] == "stopped", sender.lines[-1]
        line = second.expect("session ended (bye) after")
        assert line.endswith("; waiting for a new session")
        assert second.process.poll() is None  # still waiting
        second.signal(signal.SIGTERM)
        assert second.wait() == 0, second.output()
        report = json.loads(stats.read_text())
        assert report["ended_by"] == "stopped" and report["sessions"] == 1
        assert count_frames(tmp_path / "second.mp4") == report["frames_out"] > 0
    finally:
        for process in (sender, first, second):
            if process is not None:
                process.kill()


def test_a_large_input_is_sent_at_the_capped_size(tmp_path: Path) -> None:
    port = free_ports(2)
    stats = tmp_path / "stats.json"
    receiver = Facewire(
        "receive", "--bind", f"tcp://127.0.0.1:{port}", "--plain", "--once",
        "--record", str(tmp_path / "small.mp4"), "--stats", str(stats),
    )  # fmt: skip
    sender = Facewire(
        "send", "--connect", f"tcp://127.0.0.1:{port}", "--plain", "--frames", "20",
        "--max-size", "320x200",
    )  # fmt: skip
    try:
        assert sender.wait() == 0, sender.output()
        assert receiver.wait() == 0, receiver.output()
    finally:
        sender.kill()
        receiver.kill()
    assert "(266x200 at 30 fps, scaled from 640x480)" in sender.lines[0]
    assert "session" in receiver.lines[1] and "266x200 at 30 fps" in receiver.lines[1]
    first = next(read_frames(tmp_path / "small.mp4"))
    assert first.shape == (200, 266, 3)


def test_the_size_cap_is_turned_the_way_the_input_is() -> None:
    from facewire.sender.session import capped_size

    assert capped_size(720, 1280, 1280, 720) == (720, 1280)  # a phone held upright
    assert capped_size(1080, 1920, 1280, 720) == (720, 1280)
    assert capped_size(1920, 1080, 1280, 720) == (1280, 720)
    assert capped_size(1920, 1080, 720, 1280) == (1280, 720)
    assert capped_size(640, 480, 320, 200) == (266, 200)


def test_two_way_call_ends_when_one_end_hangs_up(tmp_path: Path, keys: Path) -> None:
    port = free_ports(4)
    ends = []
    # alice sends 60 frames and hangs up; bob sends until then (as a camera would).
    for name, where, key, peer, length in (
        ("alice", ("--bind", f"tcp://127.0.0.1:{port}"), "alice", "bob", ("--frames", "60")),
        ("bob", ("--connect", f"tcp://127.0.0.1:{port}"), "bob", "alice", ("--loop",)),
    ):
        ends.append(
            Facewire(
                "call",
                *where,
                *length,
                "--record",
                str(tmp_path / f"{name}.mp4"),
                "--stats",
                str(tmp_path / f"{name}.json"),
                "--key",
                str(keys / f"{key}.key_secret"),
                "--peer",
                str(keys / f"{peer}.key"),
                name=name,
            )  # fmt: skip
        )
    all_end_well(*ends)
    alice, bob = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("alice", "bob"))
    # Frames read: sent, or left out by a machine too busy for them (as a camera does).
    read = {
        n: s["sent"]["frames_in"] + s["sent"]["frames_dropped"]
        for n, s in (("alice", alice), ("bob", bob))
    }
    assert read["alice"] == 60 and not alice["sent"]["stopped"]
    assert bob["received"]["frames_out"] == 60 and bob["received"]["ended_by"] == "bye"
    # bob's end stopped sending when alice hung up, and alice received all it sent.
    assert bob["sent"]["stopped"] and bob["sent"]["frames_in"] > 0
    assert alice["received"]["ended_by"] == "bye"
    assert abs(alice["received"]["frames_out"] - read["bob"]) <= 1
    for name, stats in (("alice", alice), ("bob", bob)):
        assert count_frames(tmp_path / f"{name}.mp4") == stats["received"]["frames_out"]
    assert ends[0].lines[-1].startswith("receive: received 1 session(s)")


def test_two_way_call_with_frames_on_both_ends_sends_them_all(tmp_path: Path, keys: Path) -> None:
    """Each end sends its --frames: the end that finishes first keeps showing the other until
    it is done (the first to finish used to hang up the other's half too)."""
    port = free_ports(4)
    ends = [
        Facewire(
            "call",
            *where,
            "--frames",
            str(frames),
            "--no-sound",
            "--stats",
            str(tmp_path / f"{name}.json"),
            "--key",
            str(keys / f"{name}.key_secret"),
            "--peer",
            str(keys / f"{peer}.key"),
            name=name,
        )  # fmt: skip
        for name, peer, where, frames in (
            ("alice", "bob", ("--bind", f"tcp://127.0.0.1:{port}"), 45),
            ("bob", "alice", ("--connect", f"tcp://127.0.0.1:{port}"), 120),
        )
    ]
    all_end_well(*ends)
    alice, bob = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("alice", "bob"))
    # Every frame of each half was read: sent, or left out by a machine too busy for it.
    read = [side["sent"]["frames_in"] + side["sent"]["frames_dropped"] for side in (alice, bob)]
    assert read == [45, 120]
    assert not alice["sent"]["stopped"] and not bob["sent"]["stopped"]
    assert alice["received"]["ended_by"] == bob["received"]["ended_by"] == "bye"
    assert alice["received"]["frames_out"] == 120 and bob["received"]["frames_out"] == 45


def _free(port: int) -> bool:
    for kind in (socket.SOCK_STREAM, socket.SOCK_DGRAM):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def _busy_port() -> tuple[socket.socket, int]:
    """A listening socket on a port whose two ports below are free: a call bound two below
    must get as far as this one (another test's socket may hold the port just below the
    kernel's pick)."""
    for _ in range(100):
        s = socket.socket()
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        if port > 2 and _free(port - 1) and _free(port - 2):
            return s, port
        s.close()
    raise RuntimeError("no listening port with two free ports below it")


@pytest.mark.parametrize(
    "case",
    [
        "address-without-scheme",
        "address-port-out-of-range",
        "address-unknown-host",
        "address-connect-to-star",
        "port-in-use",
        "port-in-use-in-a-call",
        "no-sender-comes",
        "no-receiver-comes",
        "missing-key-file",
        "missing-peer-key-file",
        "no-keys-and-not-plain",
        "camera-that-does-not-exist",
        "record-into-missing-folder",
        "stats-into-missing-folder",
        "stats-into-missing-folder-of-a-sender",
        "stats-into-missing-folder-of-a-call",
        "view-address-without-port",
        "view-host-unknown",
        "view-port-in-use",
        "view-port-in-use-in-a-call",
        "window-without-display",
        "window-without-display-in-a-call",
    ],
)
def test_bad_use_ends_with_one_line_and_status_1(
    tmp_path: Path, keys: Path, case: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)  # as on a server, or over ssh without -X
    port = free_ports(4)
    busy, busy_port = _busy_port()
    here = f"tcp://127.0.0.1:{port}"
    key = ("--key", str(keys / "bob.key_secret"), "--peer", str(keys / "alice.key"))
    commands: dict[str, tuple[list[str], str]] = {
        "address-without-scheme": (
            ["receive", "--bind", f"127.0.0.1:{port}", "--plain"],
            "invalid address '127.0.0.1:",
        ),
        "address-port-out-of-range": (
            ["receive", "--bind", "tcp://*:65535", "--plain"],
            "port 65535 outside 1..65534",
        ),
        "address-unknown-host": (
            ["send", "--connect", "tcp://no-such-host.invalid:5555", "--plain"],
            "cannot resolve host 'no-such-host.invalid'",
        ),
        "address-connect-to-star": (
            ["receive", "--connect", "tcp://*:5555", "--plain"],
            "'*' can only be bound",
        ),
        "port-in-use": (
            ["receive", "--bind", f"tcp://127.0.0.1:{busy_port}", "--plain"],
            "Address already in use",
        ),
        "port-in-use-in-a-call": (
            # The binding end receives on PORT+2: its sending side must not start first.
            ["call", "--bind", f"tcp://127.0.0.1:{busy_port - 2}", "--plain"],
            f"cannot bind tcp://127.0.0.1:{busy_port}: address already in use",
        ),
        "no-sender-comes": (
            ["receive", "--bind", here, "--plain", "--join-timeout", "1"],
            f"no sender within 1 s: no published packet on {here} (is the sender running?)",
        ),
        "no-receiver-comes": (
            ["send", "--connect", here, "--plain", "--join-timeout", "1"],
            f"no receiver joined within 1 s at {here}",
        ),
        "missing-key-file": (
            [
                "receive",
                "--bind",
                here,
                "--key",
                str(tmp_path / "nope.key_secret"),
                "--peer",
                str(keys / "alice.key"),
            ],
            f"key file {tmp_path / 'nope.key_secret'} does not exist",
        ),  # fmt: skip
        "missing-peer-key-file": (
            [
                "send",
                "--bind",
                here,
                "--key",
                str(keys / "alice.key_secret"),
                "--peer",
                str(tmp_path / "carol.key"),
            ],
            f"key file {tmp_path / 'carol.key'} does not exist",
        ),  # fmt: skip
        "no-keys-and-not-plain": (
            ["receive", "--bind", here],
            "an encrypted call needs --key (your .key_secret) and --peer",
        ),
        "camera-that-does-not-exist": (
            ["send", "--connect", here, "--camera", "9", "--plain"],
            "cannot open camera 9: no such device or it is busy",
        ),
        "record-into-missing-folder": (
            ["receive", "--bind", here, *key, "--record", str(tmp_path / "no" / "x.mp4")],
            f"folder {tmp_path / 'no'} does not exist",
        ),
        "stats-into-missing-folder": (
            ["receive", "--bind", here, "--plain", "--stats", str(tmp_path / "no" / "s.json")],
            f"cannot write the figures to {tmp_path / 'no' / 's.json'}: folder",
        ),
        "stats-into-missing-folder-of-a-sender": (
            ["send", "--bind", here, "--plain", "--stats", str(tmp_path / "no" / "s.json")],
            f"folder {tmp_path / 'no'} does not exist",
        ),
        "stats-into-missing-folder-of-a-call": (
            ["call", "--bind", here, "--plain", "--stats", str(tmp_path / "no" / "s.json")],
            f"folder {tmp_path / 'no'} does not exist",
        ),
        "view-address-without-port": (
            ["receive", "--bind", here, "--plain", "--view", "8080"],
            "invalid live view address '8080': expected HOST:PORT",
        ),
        "view-host-unknown": (
            ["receive", "--bind", here, "--plain", "--view", "no-such-host.invalid:8080"],
            "cannot serve the live view on no-such-host.invalid:8080: cannot resolve",
        ),
        "view-port-in-use": (
            ["receive", "--bind", here, "--plain", "--view", f"127.0.0.1:{busy_port}"],
            f"cannot serve the live view on 127.0.0.1:{busy_port}: address already in use",
        ),
        "view-port-in-use-in-a-call": (
            ["call", "--bind", here, "--plain", "--view", f"127.0.0.1:{busy_port}"],
            f"cannot serve the live view on 127.0.0.1:{busy_port}: address already in use",
        ),
        "window-without-display": (
            ["receive", "--bind", here, "--plain", "--window"],
            "cannot open a window: no display (DISPLAY is not set)",
        ),
        "window-without-display-in-a-call": (
            ["call", "--bind", here, "--plain", "--window"],
            "cannot open a window: no display (DISPLAY is not set)",
        ),
    }
    args, expected = commands[case]
    try:
        result = run_facewire(*args)
    finally:
        busy.close()
    assert result.returncode == 1, result.stdout + result.stderr
    line = one_line_error(result.stderr)
    assert expected in line and "(addr=" not in line, line
    assert "send: " not in result.stdout, result.stdout  # nothing started


def test_the_summary_names_the_second_path_only_where_it_ran() -> None:
    # Over datagrams a frame may come late (one waits for the next in its datagram), but no
    # copy goes by the second path: the line said "the second path brought 0 sooner".
    report = ReceiverReport(sessions=1, frames_out=90, ended_by="stopped", latency_ms=[30.0])
    report.second_path = {"late_frames": 72, "copies": 0, "late_copies": 0, "saved": 0}
    line = summary(report, report.as_dict(), "call.mp4")
    assert line == (
        "received 1 session(s), 90 frames to call.mp4 (stopped), latency p50 30.0 ms p99 30.0 ms"
    )
    report.second_path = {"late_frames": 9, "copies": 120, "late_copies": 4, "saved": 3}
    line = summary(report, report.as_dict(), None)
    assert line.endswith("(stopped), latency p50 30.0 ms p99 30.0 ms; 9 frames came late, "
                         "the second path brought 3 sooner")  # fmt: skip


def test_a_wrong_peer_key_is_said_in_one_line(tmp_path: Path, keys: Path) -> None:
    """A receiver given the wrong key for the sender said only "handshake failed (errno 32:
    Broken pipe)" in its log, and waited in silence."""
    here = f"tcp://127.0.0.1:{free_ports(2)}"
    sender = Facewire(
        "send", "--bind", here, "--loop", "--no-sound",
        "--key", str(keys / "alice.key_secret"), "--peer", str(keys / "bob.key"),
    )  # fmt: skip
    receiver = Facewire(
        "receive", "--connect", here,
        "--key", str(keys / "bob.key_secret"), "--peer", str(keys / "bob.key"),
    )  # fmt: skip
    try:
        line = receiver.expect("cannot join")
        assert "the sender's key does not match the one this end holds for it (--peer)" in line
        hang_up(receiver, sender)
    finally:
        receiver.kill()
        sender.kill()
    assert sum("cannot join" in line for line in receiver.lines) == 1
