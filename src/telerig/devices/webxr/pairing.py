"""Reaching the control center from a headset on a LAN: a self-signed certificate, the address to
dial and a QR code of the WebXR page's URL.

Headset browsers expose WebXR to secure contexts only, so ``telerig serve`` serves TLS; without a
certificate of its own it generates one per TLS directory (``<data root>/.tls-server``), reused
while it is valid and names the address; its key is written 0600. (The page used to be served by
the device itself with a per-run pairing token; it is the control center's now, behind its login.)
"""

from __future__ import annotations

import datetime
import io
import ipaddress
import os
import socket
from pathlib import Path

from telerig.errors import DependencyError, DeviceError

__all__ = [
    "CERT_FILE",
    "KEY_FILE",
    "is_loopback",
    "lan_url_host",
    "self_signed_pair",
    "terminal_qr",
]

#: File names of the generated pair in the TLS directory.
CERT_FILE = "webxr-cert.pem"
KEY_FILE = "webxr-key.pem"
#: Validity of a generated certificate [days]; it is renewed this long before it expires.
_VALID_DAYS = 365
_RENEW_DAYS = 7


def is_loopback(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is reachable from this machine only.

    ``0.0.0.0`` / ``::`` / ``""`` (every interface) and names other than ``localhost`` are not.
    """
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def terminal_qr(text: str) -> str:
    """``text`` as a QR code drawn with Unicode half blocks, for a terminal (scan it with the headset)."""
    try:
        import segno
    except ImportError:
        raise DependencyError(
            "the webxr pairing QR code needs 'segno'; install it with: pip install 'telerig[devices]'"
        ) from None
    out = io.StringIO()
    segno.make(text, error="l").terminal(out=out, compact=True, border=2)
    return out.getvalue()


def _names(host: str) -> tuple[list[str], list[str]]:
    """(IP addresses, DNS names) the certificate must carry for a server bound to ``host``."""
    ips, dns = ["127.0.0.1"], ["localhost"]
    candidates = [_lan_address()] if host in ("0.0.0.0", "::", "") else [host]
    for name in candidates:
        if name is None:
            continue
        try:
            ipaddress.ip_address(name)
        except ValueError:
            dns.append(name)
        else:
            ips.append(name)
    return sorted(set(ips)), sorted(set(dns))


def _lan_address() -> str | None:
    """This host's address on the default route (no packet is sent), or None offline."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect(("192.0.2.1", 9))  # TEST-NET-1: routing only, nothing is sent
            return str(probe.getsockname()[0])
        except OSError:
            return None


def lan_url_host(host: str) -> str:
    """The address a headset should dial for a server bound to ``host``."""
    if host in ("0.0.0.0", "::", ""):
        return _lan_address() or "127.0.0.1"
    return host


def self_signed_pair(tls_dir: Path, host: str) -> tuple[Path, Path]:
    """Certificate and key (PEM) for a server bound to ``host``, made once and reused from ``tls_dir``.

    A cached pair is reused while it has more than a week left and names every address the server
    is reached by; otherwise a new ECDSA P-256 pair, valid a year, replaces it. The key file is 0600.

    Raises:
        DeviceError: ``tls_dir`` cannot be created or written (the message names it).
        DependencyError: ``cryptography`` is not installed.
    """
    try:
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes, serialization
        from cryptography.hazmat.primitives.asymmetric import ec
        from cryptography.x509.oid import NameOID
    except ImportError:
        raise DependencyError(
            "the webxr device's generated certificate needs 'cryptography'; "
            "install it with: pip install 'telerig[devices]'"
        ) from None
    cert_path, key_path = tls_dir / CERT_FILE, tls_dir / KEY_FILE
    ips, dns = _names(host)
    now = datetime.datetime.now(datetime.UTC)
    if cert_path.is_file() and key_path.is_file():
        try:
            cached = x509.load_pem_x509_certificate(cert_path.read_bytes())
            san = cached.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
            have_ips = {str(a) for a in san.get_values_for_type(x509.IPAddress)}
            have_dns = set(san.get_values_for_type(x509.DNSName))
            fresh = cached.not_valid_after_utc - now > datetime.timedelta(days=_RENEW_DAYS)
            if fresh and set(ips) <= have_ips and set(dns) <= have_dns:
                return cert_path, key_path
        except (ValueError, x509.ExtensionNotFound):
            pass  # unreadable or foreign: replaced below
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "telerig webxr")])
    alt = [x509.IPAddress(ipaddress.ip_address(a)) for a in ips] + [x509.DNSName(d) for d in dns]
    cert = (
        x509.CertificateBuilder()
        .subject_name(name)
        .issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=_VALID_DAYS))
        .add_extension(x509.SubjectAlternativeName(alt), critical=False)
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .sign(key, hashes.SHA256())
    )
    key_pem = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )
    try:
        tls_dir.mkdir(parents=True, exist_ok=True)
        key_path.unlink(missing_ok=True)
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(key_pem)
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    except OSError as exc:
        raise DeviceError(
            f"cannot write the webxr TLS certificate to {tls_dir}: {exc}; set tls_dir to a writable directory"
        ) from exc
    return cert_path, key_path
