"""facewire room end to end: real participants (child processes) through a real nats-server on
loopback, the bundled clip scaled down so that three fit on two cores; two of them speaking
(the bundled speech, Opus through the relay) where the test is about sound."""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from facewire.protocol.constants import AUDIO_RATE
from facewire.protocol.packets import KeyframeRequest
from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.receiver.audio import read_audio
from facewire.relay import Relay, RelayConfig, free_port
from facewire.room_sender import RoomSender
from tests.cli_call import Facewire, count_frames, kill_all, run_facewire
from tests.voices import talking_clip, talking_voice, voice_match

pytest.importorskip("nats")
SMALL = ("--max-size", "320x240", "--no-sound")
SPEAKING = ("--max-size", "320x240")


@pytest.fixture
def relay() -> Iterator[Relay]:
    with Relay(RelayConfig(port=free_port())) as running:
        yield running


@pytest.fixture
def key(tmp_path: Path) -> Path:
    path = tmp_path / "standup.room"
    RoomKey.generate("standup").write(path)
    return path


def _join(
    relay: Relay, key: Path, name: str, *extra: str, tmp: Path, size: tuple[str, ...] = SMALL
) -> Facewire:
    return Facewire(
        "room", "--room", "standup", "--name", name, "--key", str(key),
        "--server", relay.config.client_url(), "--stats", str(tmp / f"{name}.json"),
        *size, *extra, name=name,
    )  # fmt: skip


def _expect_joined(person: Facewire, *names: str) -> None:
    """Until ``person`` has said each of ``names`` joined, in whatever order."""
    missing = set(names)
    while missing:
        missing.discard(person.expect(" joined: ").split(" joined: ")[0])


def _stats(tmp: Path, name: str) -> dict:
    return json.loads((tmp / f"{name}.json").read_text())


@pytest.mark.timeout(400)
def test_three_in_a_room_one_joining_late(relay: Relay, key: Path, tmp_path: Path) -> None:
    alice = bob = carol = None
    try:
        # 15 s each: under a full suite's load Carol's process took longer to start than the
        # 8 s Alice once streamed, and Alice had left before Carol came.
        alice = _join(relay, key, "alice", "--loop", "--frames", "450", tmp=tmp_path)
        bob = _join(relay, key, "bob", "--loop", "--frames", "450", tmp=tmp_path)
        alice.expect("bob joined")
        bob.expect("alice joined")
        # Carol comes when both are well into their streams: their snapshots come from the
        # relay's bucket, their pictures once a keyframe she asked for comes.
        record = tmp_path / "carol-rec"
        carol = _join(relay, key, "carol", "--frames", "30", "--record-dir", str(record),
                      tmp=tmp_path)  # fmt: skip
        _expect_joined(carol, "alice", "bob")
        alice.expect("carol joined")
        for person in (alice, bob, carol):
            assert person.wait(300) == 0, person.output()
    finally:
        kill_all(alice, bob, carol)
    stats = {name: _stats(tmp_path, name) for name in ("alice", "bob", "carol")}
    for name, mine in stats.items():
        others = {"alice", "bob", "carol"} - {name}
        assert set(mine["peers"]) == others, mine
        for other in others:
            peer = mine["peers"][other]
            assert peer["frames"] > 0, (name, other, peer)
            assert peer["malformed"] == 0 and peer["left"] == "said bye"
            assert {"p50", "p99", "max"} <= set(peer["latency_ms"]) and peer["kbps"]["nats"] > 0
        assert mine["rejected"] == {}
    asked = sum(stats["carol"]["peers"][n]["keyframe_requests"] for n in ("alice", "bob"))
    answered = sum(stats[n]["sent"]["keyframe_requests"] for n in ("alice", "bob"))
    assert asked >= 1 and answered >= 1, (asked, answered)
    for other in ("alice", "bob"):
        assert count_frames(record / f"{other}.mp4") > 0


@pytest.mark.timeout(400)
def test_each_voice_is_heard_and_recorded_with_its_face(
    relay: Relay, key: Path, tmp_path: Path
) -> None:
    """Alice and Bob speak (two clips, two voices); Carol only listens and records each. Each
    recording carries that one's voice, not the other's, beside the same frames it was sent
    with; everyone played everyone's sound (mixed into the device, or a null sink where there is
    none, as on this machine)."""
    # Three times over (12 s): with one 4 s clip, Alice once said all and left before Bob's
    # process had joined, and Carol, with no one left, left before Bob came.
    voices = {"alice": np.tile(talking_voice(), 3), "bob": np.tile(talking_voice(swapped=True), 3)}
    record = tmp_path / "carol-hears"
    alice = bob = carol = None
    try:
        carol = _join(relay, key, "carol", "--receive-only", "--record-dir", str(record),
                      tmp=tmp_path, size=())  # fmt: skip
        carol.expect("receiving only")
        speakers = []
        for name, voice in voices.items():
            clip = talking_clip(tmp_path / f"{name}-says.mp4", voice, times=3)
            speakers.append(
                _join(relay, key, name, "--input", str(clip), tmp=tmp_path, size=SPEAKING)
            )
        alice, bob = speakers
        _expect_joined(carol, "alice", "bob")
        for person in (alice, bob, carol):
            assert person.wait(300) == 0, person.output()
    finally:
        kill_all(alice, bob, carol)
    # Said once for the room, not once a peer (a machine with a device says nothing).
    no_device = sum("no sound device" in line for line in carol.lines)
    assert no_device <= 1, carol.output()
    heard = _stats(tmp_path, "carol")["peers"]
    matches = {}
    for name, voice in voices.items():
        (other,) = set(voices) - {name}
        sound = heard[name]["sound"]
        assert sound["played"] > 0, (name, sound)
        assert (
            sound["sink"] == "no sound device" if no_device else sound["sink"].endswith(", mixed")
        ), (name, sound)
        # The recording starts with the first frame Carol decoded: the voice from there on.
        start = heard[name]["recorded_from"] * AUDIO_RATE // 30
        recorded = read_audio(record / f"{name}.mp4")
        own, lag_ms = voice_match(recorded, voice[start:])
        others, _ = voice_match(recorded, voices[other][start:])
        matches[name] = (round(own, 2), lag_ms, round(others, 2))
    print("each recording: (its own voice, at ms, the other's voice):", matches)
    for own, lag_ms, others in matches.values():
        # Not the two-party test's 0.9 and 20 ms: on this loaded machine the senders fall
        # behind (6-9 fps) and send their sound in bursts, and what came too late to be played
        # is not in the recording either (0.69-0.83 measured, at +5 to +20 ms; the two-party
        # test measured 0.51 at +30 ms on main at the same load). The two voices match at
        # -0.26. 45 ms: where a voice ahead of its lips starts to show (ITU-R BT.1359).
        assert own > 0.5 and abs(lag_ms) <= 45 and others < 0.2, matches
    for name in voices:  # the speakers heard each other too
        (other,) = set(voices) - {name}
        assert _stats(tmp_path, name)["peers"][other]["sound"]["played"] > 0


@pytest.mark.timeout(400)
def test_wrong_key_sees_no_one_and_a_vanished_peer_leaves(
    relay: Relay, key: Path, tmp_path: Path
) -> None:
    wrong = tmp_path / "wrong.room"
    RoomKey.generate("standup").write(wrong)  # the same room's name, another secret
    alice = mallory = eve = None
    try:
        alice = _join(relay, key, "alice", "--loop", tmp=tmp_path)
        alice.expect("sending")
        mallory = Facewire(
            "room", "--room", "standup", "--name", "mallory", "--key", str(wrong),
            "--server", relay.config.client_url(), "--stats", str(tmp_path / "mallory.json"),
            *SMALL, "--loop", name="mallory",
        )  # fmt: skip
        line = mallory.expect("alice's messages do not open")
        assert "is --key the key of room standup?" in line
        alice.expect("mallory's messages do not open")
        eve = _join(relay, key, "eve", "--loop", tmp=tmp_path)
        alice.expect("eve joined")
        eve.kill()  # no Bye: alice must notice the silence
        alice.expect("eve left (silent for 2.5 s)")
        for person in (alice, mallory):
            person.signal(signal.SIGTERM)
            assert person.wait(120) == 0, person.output()
    finally:
        kill_all(alice, mallory, eve)
    seen_by_mallory = _stats(tmp_path, "mallory")
    assert all(p["frames"] == 0 for p in seen_by_mallory["peers"].values())
    assert seen_by_mallory["rejected"].get("alice", 0) > 0
    seen_by_alice = _stats(tmp_path, "alice")
    assert seen_by_alice["peers"]["eve"]["left"] == "silent for 2.5 s"
    assert seen_by_alice["peers"]["eve"]["frames"] > 0
    assert seen_by_alice["peers"].get("mallory", {"frames": 0})["frames"] == 0


def test_relay_down_and_bad_input_are_one_line(key: Path, tmp_path: Path) -> None:
    down = f"nats://127.0.0.1:{free_port()}"
    base = ("room", "--room", "standup", "--name", "alice", "--key", str(key), *SMALL)
    done = run_facewire(*base, "--server", down)
    assert done.returncode == 1
    assert done.stderr.startswith("facewire: error: cannot reach the relay at " + down)
    assert done.stderr.count("\n") == 1, done.stderr
    other = tmp_path / "other.room"
    RoomKey.generate("other").write(other)
    done = run_facewire("room", "--room", "standup", "--name", "a", "--key", str(other))
    assert done.returncode == 1
    assert done.stderr == f"facewire: error: {other} is room other's key, not room standup's\n"
    done = run_facewire("room", "--room", "stand up", "--name", "a", "--key", str(key))
    assert done.returncode == 1 and "room name 'stand up'" in done.stderr


def test_a_sender_back_through_another_node_sends_a_keyframe_unasked() -> None:
    # What went to the node that died may be lost: the sender's loop is asked for a keyframe
    # by the link's reconnection itself, not only later by a receiver whose chain broke.
    key = RoomKey.generate("standup")
    sealer = Sealer(key.base_key("alice"), new_kid("alice"))
    sender = RoomSender(None, key, "alice", sealer, 30.0, 2000.0)  # type: ignore[arg-type]
    assert sender.poll() == []
    sender.reconnected()
    assert sender.poll() == [KeyframeRequest(0)]
    assert sender.poll() == []
