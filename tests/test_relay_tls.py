"""TLS on the NATS hop: ``facewire keys --tls-for``, ``facewire relay --tls-cert/--tls-key``
and ``facewire room --tls-ca``, with a real nats-server and real participants on loopback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cryptography import x509

from facewire.protocol.sframe import RoomKey
from facewire.relay import Relay, RelayConfig, free_port
from tests.cli_call import Facewire, kill_all, run_facewire

pytest.importorskip("nats")
SMALL = ("--max-size", "176x144", "--no-sound")


def _certificate(folder: Path, host: str) -> tuple[Path, Path]:
    done = run_facewire("keys", "--tls-for", host, "--out", str(folder))
    assert done.returncode == 0, done.stderr
    return folder / f"{host}.crt", folder / f"{host}.key"


@pytest.fixture
def key(tmp_path: Path) -> Path:
    path = tmp_path / "standup.room"
    RoomKey.generate("standup").write(path)
    return path


def _room(key: Path, name: str, url: str, *extra: str) -> tuple[str, ...]:
    return ("room", "--room", "standup", "--name", name, "--key", str(key), "--server", url,
            *SMALL, *extra)  # fmt: skip


def test_the_certificate_is_for_its_host_and_its_key_is_private(tmp_path: Path) -> None:
    cert, key = _certificate(tmp_path, "127.0.0.1")
    assert oct(key.stat().st_mode & 0o777) == "0o600"
    parsed = x509.load_pem_x509_certificate(cert.read_bytes())
    names = parsed.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    named = x509.load_pem_x509_certificate(_certificate(tmp_path, "relay.example")[0].read_bytes())
    names = named.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert names.get_values_for_type(x509.DNSName) == ["relay.example"]
    again = run_facewire("keys", "--tls-for", "127.0.0.1", "--out", str(tmp_path))
    assert again.returncode == 1 and again.stderr.count("\n") == 1
    assert "exists (--force replaces it)" in again.stderr


@pytest.mark.timeout(300)
def test_a_room_over_tls(tmp_path: Path, key: Path) -> None:
    """``facewire relay`` with the certificate ``keys --tls-for`` made; two participants that
    trust it meet through it, one sending, one counting the other's frames."""
    cert, private = _certificate(tmp_path, "127.0.0.1")
    port = free_port()
    relay = Facewire("relay", "--listen", f"127.0.0.1:{port}", "--tls-cert", str(cert),
                     "--tls-key", str(private), "--token-file", str(tmp_path / "token"),
                     name="relay")  # fmt: skip
    bob = alice = None
    try:
        url = relay.expect("participants join with --server ").rsplit(" ", 1)[1]
        assert url.startswith("tls://") and url.endswith(f"@127.0.0.1:{port}")
        stats = tmp_path / "bob.json"
        bob = Facewire(*_room(key, "bob", url, "--tls-ca", str(cert), "--receive-only",
                              "--stats", str(stats)), name="bob")  # fmt: skip
        assert bob.expect("joined room").endswith(f"through tls://127.0.0.1:{port}")
        alice = Facewire(*_room(key, "alice", url, "--tls-ca", str(cert), "--frames", "60"),
                         name="alice")  # fmt: skip
        bob.expect("alice joined")
        assert alice.wait(240) == 0, alice.output()
        assert bob.wait(120) == 0, bob.output()
    finally:
        kill_all(alice, bob, relay)
    assert json.loads(stats.read_text())["peers"]["alice"]["frames"] > 0


def test_without_the_ca_or_for_another_host_it_is_one_line(tmp_path: Path, key: Path) -> None:
    cert, private = _certificate(tmp_path, "127.0.0.1")
    with Relay(RelayConfig(port=free_port(), tls=(str(cert), str(private)))) as relay:
        url = relay.config.client_url()
        where = f"tls://127.0.0.1:{relay.config.port}"
        done = run_facewire(*_room(key, "alice", url))  # the system's CAs do not know it
        assert done.returncode == 1
        assert done.stderr.startswith(f"facewire: error: cannot reach the relay at {where}: ")
        assert "certificate verify failed" in done.stderr and "--tls-ca FILE" in done.stderr
        assert done.stderr.count("\n") == 1, done.stderr
        assert run_facewire(*_room(key, "alice", url, "--tls-ca", str(cert), "--frames", "1"),
                            timeout_s=180).returncode == 0  # fmt: skip
    other, other_key = _certificate(tmp_path, "relay.example")
    with Relay(RelayConfig(port=free_port(), tls=(str(other), str(other_key)))) as relay:
        done = run_facewire(*_room(key, "alice", relay.config.client_url(), "--tls-ca", str(other)))
        assert done.returncode == 1
        assert "mismatch, certificate is not valid for '127.0.0.1'" in done.stderr, done.stderr
        assert done.stderr.count("\n") == 1, done.stderr


def test_missing_or_bad_files_are_one_line(tmp_path: Path, key: Path) -> None:
    cert, private = _certificate(tmp_path, "127.0.0.1")
    listen = ("relay", "--listen", f"127.0.0.1:{free_port()}")
    cases = [
        ((*listen, "--tls-cert", str(tmp_path / "no.crt"), "--tls-key", str(private)),
         f"facewire: error: --tls-cert {tmp_path / 'no.crt'}: No such file or directory\n"),
        ((*listen, "--tls-cert", str(cert)),
         "facewire: error: --tls-cert and --tls-key go together\n"),
        (_room(key, "a", "tls://t@127.0.0.1:1", "--tls-ca", str(tmp_path / "no.crt")),
         f"facewire: error: --tls-ca {tmp_path / 'no.crt'}: No such file or directory\n"),
        (_room(key, "a", "tls://t@127.0.0.1:1", "--tls-ca", str(key)),
         f"facewire: error: --tls-ca {key}: not a PEM certificate"),
    ]  # fmt: skip
    for args, said in cases:
        done = run_facewire(*args)
        assert done.returncode == 1 and done.stderr.startswith(said), done.stderr
        assert done.stderr.count("\n") == 1, done.stderr
    # A key that is not the certificate's: nats-server's own reason, in one line.
    _, other_key = _certificate(tmp_path, "relay.example")
    done = run_facewire(*listen, "--tls-cert", str(cert), "--tls-key", str(other_key))
    assert done.returncode == 1 and done.stderr.count("\n") == 1, done.stderr
    assert done.stderr.startswith("facewire: error: nats-server did not start: ")
    assert "private key does not match public key" in done.stderr
