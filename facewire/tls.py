"""TLS on the NATS hop: a relay's self-signed certificate, and a participant's trust in it.

``facewire keys --tls-for HOST`` makes ``HOST.crt`` and ``HOST.key`` (mode 0600): an ECDSA
P-256 key and a certificate for HOST (a DNS name or an IP address) that signs itself, so it
is its own CA: ``facewire relay --tls-cert HOST.crt --tls-key HOST.key`` serves it, and each
participant trusts it with ``facewire room --tls-ca HOST.crt``. A certificate from a real CA
works the same way. This guards the hop to the relay (the token, who talks to whom); the faces
are sealed end to end whatever the hop (protocol/sframe.py).
"""

from __future__ import annotations

import datetime
import ipaddress
import os
import ssl
from pathlib import Path

#: How long a certificate made here is valid.
VALID_DAYS = 365


def write_self_signed(host: str, out: str | Path, force: bool = False) -> tuple[Path, Path]:
    """Write ``out/HOST.crt`` and ``out/HOST.key`` (mode 0600); FileExistsError unless
    ``force``."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not host or any(c in host for c in "/\\ \t\n"):
        raise ValueError(f"expected a host name or an IP address, got {host!r}")
    try:
        name: x509.GeneralName = x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        name = x509.DNSName(host)
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    cert_path, key_path = folder / f"{host}.crt", folder / f"{host}.key"
    for path in (cert_path, key_path):
        if path.exists() and not force:
            raise FileExistsError(f"{path} exists (--force replaces it)")
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"facewire relay {host}")])
    now = datetime.datetime.now(datetime.UTC)
    public = key.public_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(public)
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))  # clocks a little apart
        .not_valid_after(now + datetime.timedelta(days=VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName([name]), critical=False)
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                key_cert_sign=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                crl_sign=False,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )  # fmt: skip
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(public), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(public), critical=False)
        .sign(key, hashes.SHA256())
    )
    key_bytes = key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    key_path.unlink(missing_ok=True)
    fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(key_bytes)
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert_path, key_path


def readable(path: str, option: str) -> str:
    """``path`` when it is a file that can be read; else ValueError naming ``option``."""
    try:
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise ValueError(f"{option} {path}: {exc.strerror or exc}") from None
    return path


def client_context(ca_file: str) -> ssl.SSLContext:
    """A TLS context that trusts the relay certificates ``ca_file`` signed (and checks the
    relay's host name against them)."""
    readable(ca_file, "--tls-ca")
    try:
        return ssl.create_default_context(cafile=ca_file)
    except ssl.SSLError as exc:
        raise ValueError(f"--tls-ca {ca_file}: not a PEM certificate ({exc.reason})") from None
