"""Key files: ``facewire keys`` writes them, protocol.keys reads them or says what is wrong."""

from __future__ import annotations

import stat
from pathlib import Path

import pytest
import zmq.auth

from facewire.cli import main
from facewire.protocol.keys import load_keypair, load_public_key, load_public_keys, write_keypair


def test_keys_command_writes_a_zmq_certificate_pair(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["keys", "--out", str(tmp_path), "--name", "alice"]) == 0
    public, secret = tmp_path / "alice.key", tmp_path / "alice.key_secret"
    assert (
        capsys.readouterr().out
        == f"wrote {public} (public) and {secret} (secret, keep it private)\n"
    )
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert "secret-key" not in public.read_text()
    # pyzmq reads what we wrote, and we read what pyzmq writes.
    z_public, z_secret = zmq.auth.load_certificate(secret)
    pair = load_keypair(secret)
    assert (pair.public, pair.secret) == (z_public, z_secret)
    assert load_public_key(public) == z_public
    assert zmq.curve_public(pair.secret) == pair.public
    zmq.auth.create_certificates(tmp_path, "bob")
    assert load_keypair(tmp_path / "bob.key_secret").public == load_public_key(tmp_path / "bob.key")
    assert load_public_keys(tmp_path) == {pair.public, load_public_key(tmp_path / "bob.key")}
    assert "secret" not in repr(pair)


def test_keys_command_refuses_to_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["keys", "--out", str(tmp_path)]) == 0
    before = (tmp_path / "facewire.key_secret").read_text()
    capsys.readouterr()
    assert main(["keys", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert err == (
        f"facewire: error: {tmp_path / 'facewire.key'} already exists "
        "(pass --force to replace it)\n"
    )
    assert (tmp_path / "facewire.key_secret").read_text() == before
    assert main(["keys", "--out", str(tmp_path), "--force"]) == 0
    assert (tmp_path / "facewire.key_secret").read_text() != before


def test_keys_command_makes_its_folder_private(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # The README's first command on a fresh checkout, where keys/ does not exist yet.
    folder = tmp_path / "keys"
    assert main(["keys", "--out", str(folder), "--name", "sender"]) == 0
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert stat.S_IMODE((folder / "sender.key_secret").stat().st_mode) == 0o600
    load_keypair(folder / "sender.key_secret")
    assert capsys.readouterr().out.startswith(f"wrote {folder / 'sender.key'} (public)")
    # A file where the folder should be is one line.
    assert main(["keys", "--out", str(folder / "sender.key")]) == 1
    assert capsys.readouterr().err == (
        f"facewire: error: cannot write keys to {folder / 'sender.key'}: "
        "it is a file, not a folder\n"
    )


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("", "has no secret-key line"),
        ('curve\n    public-key = "short"\n', "public-key is not a 40-character Z85 key"),
        ('    secret-key = "' + "~" * 40 + '"\n', "secret-key is not a 40-character Z85 key"),
        ("\xff\xfe", "not a key file (not UTF-8 text)"),
    ],
)
def test_garbled_key_files_give_one_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.key_secret"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(ValueError) as info:
        load_keypair(path)
    assert message in str(info.value) and str(path) in str(info.value)
    assert "\n" not in str(info.value)


def test_missing_keys_give_one_line(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"key file .*none.key does not exist"):
        load_public_key(tmp_path / "none.key")
    with pytest.raises(ValueError, match=r"no public key files \(\*.key\) in"):
        load_public_keys(tmp_path)
    with pytest.raises(ValueError, match="key directory .* does not exist"):
        load_public_keys(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="list of allowed public key files is empty"):
        load_public_keys([])
    public, _ = write_keypair(tmp_path, "a")
    with pytest.raises(ValueError, match=r"has no secret-key line \(that is a public key file\)"):
        load_keypair(public)
    with pytest.raises(ValueError, match="key name '../x' may only use"):
        write_keypair(tmp_path, "../x")
