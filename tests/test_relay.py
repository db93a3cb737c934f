"""facewire relay: a real nats-server with our configuration, on loopback."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from facewire.relay import (
    Relay,
    RelayConfig,
    RelayError,
    ephemeral_ports,
    free_port,
    host_port,
)

pytest.importorskip("nats")
ROOT = Path(__file__).resolve().parents[1]


async def _connect(url: str) -> str:
    import nats

    async def quiet(exc: Exception) -> None:
        pass

    try:
        nc = await nats.connect(
            url, connect_timeout=2, allow_reconnect=False, max_reconnect_attempts=0,
            error_cb=quiet,
        )  # fmt: skip
    except Exception as exc:
        return f"refused: {exc}"
    js = nc.jetstream()
    from nats.js.api import KeyValueConfig, StorageType

    kv = await js.create_key_value(KeyValueConfig(bucket="t", storage=StorageType.MEMORY))
    await kv.put("k", b"v")
    value = (await kv.get("k")).value
    await nc.close()
    return f"kv {value.decode()}"


def test_token_admits_and_jetstream_is_on() -> None:
    with Relay(RelayConfig(port=free_port())) as relay:
        url = relay.config.client_url()
        assert asyncio.run(_connect(url)) == "kv v"
        wrong = url.replace(relay.config.token, "not-the-token")
        assert "Authorization Violation" in asyncio.run(_connect(wrong))
        no_token = f"nats://127.0.0.1:{relay.config.port}"
        assert "Authorization Violation" in asyncio.run(_connect(no_token))
    assert relay.process is not None and relay.process.poll() is not None


def test_ports_picked_ahead_are_none_a_connection_could_take() -> None:
    """A cluster's ports are picked before its nodes start, and the first nodes connect to
    the others' route ports meanwhile: a port from the kernel's ephemeral range could be
    such a connection's own (a node once could not bind its route port that way)."""
    first, _ = ephemeral_ports()
    ports = {free_port() for _ in range(20)}
    assert all(p < first for p in ports), sorted(ports)
    for port in ports:
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # free indeed


def test_port_taken_is_one_line() -> None:
    with Relay(RelayConfig(port=free_port())) as first:
        second = Relay(RelayConfig(port=first.config.port))
        with pytest.raises(RelayError, match="address already in use"):
            second.start()
        second.close()
        assert "\n" not in second.reason()


def test_config_has_limits_and_cluster() -> None:
    config = RelayConfig(port=4999, token="t0k", cluster=("127.0.0.1", 6999))
    config.routes = ["nats-route://127.0.0.1:7000"]
    text = config.text()
    for line in ('token: "t0k"', "jetstream {", "max_payload:", 'listen: "127.0.0.1:6999"'):
        assert line in text
    assert 'routes: ["nats-route://127.0.0.1:7000"]' in text


def test_host_port() -> None:
    assert host_port("0.0.0.0:5000") == ("0.0.0.0", 5000)
    assert host_port(":5000") == ("127.0.0.1", 5000)
    assert host_port("example.org") == ("example.org", 4222)
    with pytest.raises(ValueError, match="expected HOST:PORT, got 'a:b'"):
        host_port("a:b")


def _cli(*args: str) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "facewire.cli", *args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip


def test_cli_stops_cleanly_on_sigterm_and_says_why_it_cannot_start(tmp_path: Path) -> None:
    port = free_port()
    token = tmp_path / "relay.token"
    relay = _cli("relay", "--listen", f"127.0.0.1:{port}", "--token-file", str(token))
    try:
        assert relay.stdout is not None
        line = relay.stdout.readline()
        assert f"@127.0.0.1:{port}" in line and token.read_text().strip() in line
        assert oct(token.stat().st_mode & 0o777) == "0o600"
        taken = _cli("relay", "--listen", f"127.0.0.1:{port}")
        out, err = taken.communicate(timeout=30)
        assert taken.returncode == 1
        assert err.strip().count("\n") == 0 and "address already in use" in err
        relay.send_signal(signal.SIGTERM)
        out, err = relay.communicate(timeout=30)
        assert relay.returncode == 0, err
        assert "relay stopping (SIGTERM)" in out
    finally:
        relay.kill()
    # The nats-server it started went with it: the port is free again.
    with Relay(RelayConfig(port=port)):
        pass
