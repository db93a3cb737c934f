"""CURVE key files: ZeroMQ's certificate format, read and written without a socket.

A keypair is two text files, as ``zmq.auth.create_certificates`` writes them:
``NAME.key`` holds the public key and may be handed to the other end of a call;
``NAME.key_secret`` holds both keys and stays with its owner (mode 0600). Keys are Z85 text,
40 characters for 32 bytes::

    metadata
    curve
        public-key = "rq:rM>}U?@Lns47E1%kR.o@n%FcmmsL/@{H8]yf7"
        secret-key = "JTKVSB%%)wK0E.X)V>+}o?pNmC{O&4W4b!Ni{Lh6"

Every function raises ValueError with a one-line message naming the file when a key file is
missing, unreadable or garbled. Only :func:`write_keypair` needs zmq (imported there).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

logger = logging.getLogger(__name__)

PUBLIC_SUFFIX = ".key"
SECRET_SUFFIX = ".key_secret"
#: Z85 text of a 32-byte CURVE key.
KEY_CHARS = 40
_Z85 = frozenset(
    "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ.-:+=^!/*?&<>()[]{}@%$#"
)
_LINE = re.compile(r'^\s*(public-key|secret-key)\s*=\s*"([^"]*)"\s*$')
_NAME = re.compile(r"^[A-Za-z0-9_.-]+$")
_MAX_FILE_BYTES = 64 * 1024

_PUBLIC_BANNER = """#   ****  Generated on {now} by facewire  ****
#   ZeroMQ CURVE Public Certificate
#   Give this file to the other end of the call.

"""
_SECRET_BANNER = """#   ****  Generated on {now} by facewire  ****
#   ZeroMQ CURVE **Secret** Certificate
#   DO NOT PROVIDE THIS FILE TO OTHER USERS nor change its permissions.

"""


@dataclass(frozen=True)
class KeyPair:
    """One end's CURVE keys, Z85 text as bytes (what the zmq CURVE socket options take)."""

    public: bytes
    secret: bytes

    def __repr__(self) -> str:  # never print the secret key
        return f"KeyPair(public={self.public!r})"


def _read_keys(path: str | os.PathLike[str]) -> dict[str, bytes]:
    path = Path(path)
    try:
        if path.is_dir():
            raise ValueError(f"key file {path} is a directory")
        with path.open("rb") as f:
            raw = f.read(_MAX_FILE_BYTES + 1)
    except FileNotFoundError:
        raise ValueError(f"key file {path} does not exist") from None
    except OSError as exc:
        raise ValueError(f"cannot read key file {path}: {exc.strerror or exc}") from None
    if len(raw) > _MAX_FILE_BYTES:
        raise ValueError(f"key file {path} is not a key file (over {_MAX_FILE_BYTES} bytes)")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError(f"key file {path} is not a key file (not UTF-8 text)") from None
    keys: dict[str, bytes] = {}
    for line in text.splitlines():
        match = _LINE.match(line)
        if match is None:
            continue
        name, value = match.groups()
        if len(value) != KEY_CHARS or not set(value) <= _Z85:
            raise ValueError(f"key file {path}: {name} is not a {KEY_CHARS}-character Z85 key")
        keys[name] = value.encode("ascii")
    return keys


def load_public_key(path: str | os.PathLike[str]) -> bytes:
    """The public key in ``path`` (a ``.key`` file, or a ``.key_secret`` file, which has it too)."""
    keys = _read_keys(path)
    if "public-key" not in keys:
        raise ValueError(f"key file {path} has no public-key line")
    return keys["public-key"]


def public_key_files(sources: Iterable[str | os.PathLike[str]]) -> list[Path]:
    """The ``*.key`` files named by ``sources``: files as given, folders by what they hold
    (ValueError for a folder with none)."""
    files: list[Path] = []
    for source in sources:
        path = Path(source)
        if path.is_dir():
            found = sorted(path.glob(f"*{PUBLIC_SUFFIX}"))
            if not found:
                raise ValueError(f"no public key files (*{PUBLIC_SUFFIX}) in {path}")
            files += found
        else:
            files.append(path)
    return files


def load_keypair(path: str | os.PathLike[str]) -> KeyPair:
    """Both keys from a ``.key_secret`` file."""
    keys = _read_keys(path)
    if "secret-key" not in keys:
        hint = " (that is a public key file)" if "public-key" in keys else ""
        raise ValueError(f"key file {path} has no secret-key line{hint}")
    if "public-key" not in keys:
        raise ValueError(f"key file {path} has no public-key line")
    return KeyPair(keys["public-key"], keys["secret-key"])


def load_public_keys(
    source: str | os.PathLike[str] | Iterable[str | os.PathLike[str]],
) -> frozenset[bytes]:
    """Allowed peers' public keys: every ``*.key`` file of a directory, or a list of files."""
    if isinstance(source, str | os.PathLike):
        folder = Path(source)
        if not folder.is_dir():
            if not folder.exists():
                raise ValueError(f"key directory {folder} does not exist")
            raise ValueError(f"{folder} is not a directory (pass a list for single key files)")
        files = sorted(folder.glob(f"*{PUBLIC_SUFFIX}"))
        if not files:
            raise ValueError(f"no public key files (*{PUBLIC_SUFFIX}) in {folder}")
    else:
        files = [Path(p) for p in source]
        if not files:
            raise ValueError("the list of allowed public key files is empty")
    return frozenset(load_public_key(f) for f in files)


def write_keypair(
    out_dir: str | os.PathLike[str], name: str, force: bool = False
) -> tuple[Path, Path]:
    """Make a new keypair: ``out_dir/NAME.key`` and ``out_dir/NAME.key_secret`` (mode 0600).

    A missing ``out_dir`` is made, mode 0700. Existing files are kept (ValueError) unless
    ``force``. Returns (public file, secret file).
    """
    import zmq

    if not _NAME.match(name):
        raise ValueError(f"key name {name!r} may only use letters, digits, '_', '-' and '.'")
    folder = Path(out_dir)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"cannot write keys to {folder}: it is a file, not a folder")
    try:
        # A folder made for keys holds secret ones: only its owner may look inside.
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot make the folder {folder}: {exc.strerror or exc}") from None
    public_file = folder / f"{name}{PUBLIC_SUFFIX}"
    secret_file = folder / f"{name}{SECRET_SUFFIX}"
    if not force:
        for path in (public_file, secret_file):
            if path.exists():
                raise ValueError(f"{path} already exists (pass --force to replace it)")
    public, secret = zmq.curve_keypair()
    now = datetime.now().isoformat(timespec="seconds")
    body = f'metadata\ncurve\n    public-key = "{public.decode()}"\n'
    secret_text = _SECRET_BANNER.format(now=now) + body + f'    secret-key = "{secret.decode()}"\n'
    _write_new(secret_file, secret_text, 0o600, force)
    _write_new(public_file, _PUBLIC_BANNER.format(now=now) + body, 0o644, force)
    logger.info("wrote %s and %s", public_file, secret_file)
    return public_file, secret_file


def _write_new(path: Path, text: str, mode: int, replace: bool) -> None:
    """Write ``text`` to a new file created with ``mode`` (never briefly readable by others)."""
    if replace:
        path.unlink(missing_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    except FileExistsError:
        raise ValueError(f"{path} already exists (pass --force to replace it)") from None
    except OSError as exc:
        raise ValueError(f"cannot write {path}: {exc.strerror or exc}") from None
    with os.fdopen(fd, "w", encoding="ascii") as f:
        f.write(text)
