"""``mqtts://``: a real Mosquitto TLS listener on 127.0.0.1 with a certificate made by the test."""

from __future__ import annotations

import datetime
import ipaddress
import socket
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

from telerig.bus.base import Message
from telerig.bus.broker import MosquittoBroker
from telerig.bus.mqtt import MqttBus, MqttUrl, TlsOptions
from telerig.errors import BusError, ConfigError

pytestmark = pytest.mark.broker


def _write_ca_and_server_cert(folder: Path) -> tuple[Path, Path, Path]:
    """A CA, and a server certificate it signs for 127.0.0.1; returns (ca, cert, key) PEM paths."""
    now = datetime.datetime.now(datetime.UTC)
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "telerig test CA")])
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=True, path_length=None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=True,
                crl_sign=True,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "127.0.0.1")]))
        .issuer_name(ca_name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(minutes=5))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(
            x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), False
        )
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    ca_path, cert_path, key_path = folder / "ca.pem", folder / "server.pem", folder / "server.key"
    ca_path.write_bytes(ca.public_bytes(serialization.Encoding.PEM))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
        )
    )
    key_path.chmod(0o600)
    return ca_path, cert_path, key_path


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    return _write_ca_and_server_cert(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def tls_broker(pki: tuple[Path, Path, Path]) -> Iterator[MosquittoBroker]:
    _, cert, key = pki
    with MosquittoBroker(certfile=cert, keyfile=key) as broker:
        yield broker


def test_mqtts_url_parses_with_the_tls_port() -> None:
    url = MqttUrl.parse("mqtts://op:secret@broker.lab")
    assert (url.tls, url.port) == (True, 8883)
    assert str(url) == "mqtts://op:***@broker.lab:8883"


def test_mqtts_with_the_ca_connects_and_keeps_tcp_nodelay(
    tls_broker: MosquittoBroker, pki: tuple[Path, Path, Path]
) -> None:
    ca, _, _ = pki
    assert tls_broker.url.startswith("mqtts://")
    got: list[Message] = []
    arrived = threading.Event()

    def on_message(message: Message) -> None:
        got.append(message)
        arrived.set()

    with MqttBus(tls_broker.url, client_id="tls", tls=TlsOptions(ca_file=ca)) as bus:
        sock = bus._client.socket()
        assert sock is not None
        assert sock.version() is not None  # a TLS socket
        assert sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY) != 0
        bus.subscribe("t/x", on_message, qos=1)
        bus.publish("t/x", b"over tls", qos=1)
        assert arrived.wait(3.0)
    assert got[0].payload == b"over tls"


def test_mqtts_without_the_ca_fails_with_one_line_naming_the_fix(tls_broker: MosquittoBroker) -> None:
    bus = MqttBus(tls_broker.url, client_id="no-ca")
    with pytest.raises(BusError) as raised:
        bus.connect()
    bus.close()
    message = str(raised.value)
    assert "\n" not in message
    assert "TLS handshake" in message
    assert "certificate verify failed" in message
    assert "ca_file" in message
    assert "secret" not in message


def test_tls_options_with_a_plain_url_are_refused(pki: tuple[Path, Path, Path]) -> None:
    with pytest.raises(ConfigError, match="use an mqtts:// URL"):
        MqttBus("mqtt://127.0.0.1:1883", client_id="x", tls=TlsOptions(ca_file=pki[0]))


def test_a_missing_ca_file_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"TLS ca_file '.*nope.pem' does not exist"):
        TlsOptions(ca_file=tmp_path / "nope.pem")
