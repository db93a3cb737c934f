"""Room keys from the participants' CURVE keypairs (protocol/sender_keys.py): boxes between
real keypairs made by protocol/keys.py, and a room through a real nats-server where only the
peers each one named hear it."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest

from facewire.protocol.keys import write_keypair
from facewire.protocol.sender_keys import (
    KeyUnavailable,
    SenderKeys,
    box_name,
    load_peers,
    open_sender_key,
    seal_sender_key,
)
from facewire.protocol.sframe import SFrameError
from facewire.relay import Relay, RelayConfig, free_port
from tests.cli_call import Facewire, kill_all, run_facewire

SMALL = ("--max-size", "176x144", "--no-sound")


@pytest.fixture
def keys(tmp_path: Path) -> Path:
    folder = tmp_path / "keys"
    for name in ("alice", "bob", "carol"):
        write_keypair(folder, name)
    return folder


def _sender(keys: Path, name: str, *peers: str) -> SenderKeys:
    files = [str(keys / f"{peer}.key") for peer in peers]
    return SenderKeys("standup", name, keys / f"{name}.key_secret", load_peers(files))


def test_a_box_opens_for_its_recipient_only(keys: Path) -> None:
    alice = _sender(keys, "alice", "bob", "carol")
    bob = _sender(keys, "bob", "alice")
    carol = _sender(keys, "carol", "alice", "bob")
    in_bucket = {**alice.boxes(), **bob.boxes()}
    assert set(in_bucket) == {"alice.to.bob", "alice.to.carol", "bob.to.alice"}
    for reader in (bob, carol):
        reader.fetch = in_bucket.get
        assert reader.base_key("alice", alice.kid) == alice.own_key
    alice.fetch = in_bucket.get
    assert alice.base_key("bob", bob.kid) == bob.own_key
    with pytest.raises(KeyUnavailable, match="bob sealed no key to carol"):
        carol.base_key("bob", bob.kid)
    with pytest.raises(KeyUnavailable, match="carol is not among bob's --peer keys"):
        bob.base_key("carol")
    # The box of another run of alice's (she restarted and her new box is not in yet).
    with pytest.raises(SFrameError, match="for another run"):
        bob.base_key("alice", alice.kid ^ 1)


def test_a_box_is_bound_to_its_room_sender_and_recipient_and_every_byte(keys: Path) -> None:
    alice, bob = _sender(keys, "alice", "bob"), _sender(keys, "bob", "alice")
    secret_a, secret_b = alice._secret, bob._secret
    sealed = seal_sender_key(secret_a, bob.public, "standup", "alice", "bob", 7, bytes(16))
    assert open_sender_key(secret_b, alice.public, "standup", "alice", "bob", sealed) == (
        7,
        bytes(16),
    )
    for room, sender, recipient in [("other", "alice", "bob"), ("standup", "bob", "alice"),
                                    ("standup", "alice", "carol")]:  # fmt: skip
        with pytest.raises(KeyUnavailable, match="does not open"):
            open_sender_key(secret_b, alice.public, room, sender, recipient, sealed)
    for i in range(len(sealed)):
        altered = bytearray(sealed)
        altered[i] ^= 0x01
        with pytest.raises(KeyUnavailable):
            open_sender_key(secret_b, alice.public, "standup", "alice", "bob", bytes(altered))
    # Sealed by carol, claiming to be alice: it does not open with alice's public key.
    carol = _sender(keys, "carol", "bob")
    forged = seal_sender_key(carol._secret, bob.public, "standup", "alice", "bob", 7, bytes(16))
    with pytest.raises(KeyUnavailable, match="not sealed by the key in alice.key"):
        open_sender_key(secret_b, alice.public, "standup", "alice", "bob", forged)
    with pytest.raises(SFrameError, match="expected"):
        open_sender_key(secret_b, alice.public, "standup", "alice", "bob", sealed[:-1])
    assert box_name("alice", "bob") == "alice.to.bob"


def test_peers_are_named_by_their_files(keys: Path, tmp_path: Path) -> None:
    assert set(load_peers([str(keys)])) == {"alice", "bob", "carol"}
    assert set(load_peers([str(keys / "bob.key")])) == {"bob"}
    (tmp_path / "two words.key").write_text((keys / "bob.key").read_text())
    with pytest.raises(ValueError, match="'two words'"):
        load_peers([str(tmp_path / "two words.key")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no public key files"):
        load_peers([str(tmp_path / "empty")])


@pytest.mark.timeout(300)
def test_only_the_peers_named_hear_each_other(keys: Path, tmp_path: Path) -> None:
    """Alice and Bob name each other; Carol names them both, but neither names her: they see
    each other, she sees no one and says why, once each."""
    with Relay(RelayConfig(port=free_port())) as relay:

        def join(name: str, *extra: str) -> Facewire:
            return Facewire(
                "room", "--room", "standup", "--name", name, "--server",
                relay.config.client_url(), "--key", str(keys / f"{name}.key_secret"),
                "--stats", str(tmp_path / f"{name}.json"), *SMALL, *extra, name=name,
            )  # fmt: skip

        alice = bob = carol = None
        try:
            carol = join("carol", "--peer", str(keys / "alice.key"), "--peer",
                         str(keys / "bob.key"), "--receive-only")  # fmt: skip
            carol.expect("receiving only")
            alice = join("alice", "--peer", str(keys / "bob.key"), "--frames", "60")
            bob = join("bob", "--peer", str(keys / "alice.key"), "--frames", "60")
            unsealed = {"alice", "bob"}  # each says so once, in whatever order
            while unsealed:
                line = carol.expect(" sealed no key to carol: is carol's public key among ")
                unsealed.discard(line.split(" ", 1)[0])
            for person in (alice, bob):
                assert person.wait(240) == 0, person.output()
            carol.signal(signal.SIGTERM)  # no one came: she would wait
            assert carol.wait(60) == 0, carol.output()
        finally:
            kill_all(alice, bob, carol)
    stats = {n: json.loads((tmp_path / f"{n}.json").read_text()) for n in ("alice", "bob", "carol")}
    assert stats["alice"]["peers"]["bob"]["frames"] > 0
    assert stats["bob"]["peers"]["alice"]["frames"] > 0
    assert all(p["frames"] == 0 for p in stats["carol"]["peers"].values())
    assert sum("sealed no key" in line for line in carol.lines) == 2, carol.output()


def test_a_curve_key_without_peers_is_one_line(keys: Path) -> None:
    done = run_facewire("room", "--room", "standup", "--name", "alice",
                        "--key", str(keys / "alice.key_secret"))  # fmt: skip
    assert done.returncode == 1
    assert done.stderr == (
        f"facewire: error: {keys / 'alice.key_secret'} is a CURVE secret key: name the peers "
        "with --peer\n"
    )
    public = str(keys / "alice.key")
    done = run_facewire("room", "--room", "standup", "--name", "alice", "--key", public,
                        "--peer", str(keys / "bob.key"))  # fmt: skip
    assert done.returncode == 1 and done.stderr.count("\n") == 1
    assert "has no secret-key line (that is a public key file)" in done.stderr
