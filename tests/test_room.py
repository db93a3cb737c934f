"""facewire room end to end: real participants (child processes) through a real nats-server on
loopback, the bundled clip scaled down so that three fit on two cores."""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from facewire.protocol.sframe import RoomKey
from facewire.relay import Relay, RelayConfig, free_port
from tests.cli_call import Facewire, count_frames, kill_all, run_facewire

pytest.importorskip("nats")
SMALL = ("--max-size", "320x240", "--no-sound")


@pytest.fixture
def relay() -> Iterator[Relay]:
    with Relay(RelayConfig(port=free_port())) as running:
        yield running


@pytest.fixture
def key(tmp_path: Path) -> Path:
    path = tmp_path / "standup.room"
    RoomKey.generate("standup").write(path)
    return path


def _join(relay: Relay, key: Path, name: str, *extra: str, tmp: Path) -> Facewire:
    return Facewire(
        "room", "--room", "standup", "--name", name, "--key", str(key),
        "--server", relay.config.client_url(), "--stats", str(tmp / f"{name}.json"),
        *SMALL, *extra, name=name,
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
        alice = _join(relay, key, "alice", "--loop", "--frames", "240", tmp=tmp_path)
        bob = _join(relay, key, "bob", "--loop", "--frames", "240", tmp=tmp_path)
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
