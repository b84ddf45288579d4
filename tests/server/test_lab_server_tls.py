"""The lab server's transport: HTTPS of its own (`--certfile`/`--keyfile`, a self-signed certificate
made here with `cryptography`), or behind a TLS proxy (`--forwarded-allow-ips`): the session cookie
is `Secure` and every answer carries HSTS; a proxy's headers are believed only from the addresses
given; bound beyond this machine without either, one line of warning."""

from __future__ import annotations

import ipaddress
import re
import ssl
from datetime import UTC, datetime, timedelta

import httpx
import pytest
from cli import labcal
from lab_server import add_user, served

from labcal.server.serving import Transport, exposure_warning

PASSWORD = "vic's passphrase"


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> dict:
    base = tmp_path_factory.mktemp("tls")
    db = str(base / "lab.sqlite")
    add_user(db, "vic", "viewer", PASSWORD)
    return {"db": db, "base": base}


@pytest.fixture(scope="module")
def certificate(lab) -> tuple[str, str]:
    """A self-signed certificate for 127.0.0.1 and its key, as PEM files."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "labcal test")])
    now = datetime.now(UTC)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(x509.random_serial_number()).not_valid_before(now - timedelta(minutes=5))
            .not_valid_after(now + timedelta(days=1))
            .add_extension(x509.SubjectAlternativeName([x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]),
                           critical=False)
            .sign(key, hashes.SHA256()))
    certfile, keyfile = lab["base"] / "cert.pem", lab["base"] / "key.pem"
    certfile.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    keyfile.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                          serialization.NoEncryption()))
    keyfile.chmod(0o600)
    return str(certfile), str(keyfile)


def _sign_in(client: httpx.Client, headers: dict | None = None) -> httpx.Response:
    """Sign in; with ``headers`` (a proxy's), the form's cookie is sent back by hand, as the browser
    on the proxy's HTTPS side would (httpx keeps a Secure cookie from a plain-HTTP URL)."""
    form = client.get("/login", headers=headers)
    csrf = re.search(r'name="csrf" value="([^"]+)"', form.text)[1]
    cookie = {"Cookie": f"labcal_login={csrf}"} if headers else {}  # the double-submit token is the cookie
    return client.post("/login", data={"name": "vic", "password": PASSWORD, "csrf": csrf},
                       headers={**(headers or {}), **cookie})


def test_over_https_the_cookie_is_secure_and_every_answer_carries_hsts(lab, certificate):
    certfile, keyfile = certificate
    with served(lab["db"], "--certfile", certfile, "--keyfile", keyfile) as url:
        assert url.startswith("https://")
        trusted = ssl.create_default_context(cafile=certfile)
        with httpx.Client(base_url=url, timeout=15, verify=trusted) as client:
            signed = _sign_in(client)
            assert signed.status_code == 303
            assert "secure" in signed.headers["set-cookie"].lower()
            assert "max-age=" in signed.headers["strict-transport-security"]
            assert "max-age=" in client.get("/").headers["strict-transport-security"]
        with pytest.raises(httpx.TransportError):  # plain HTTP on the TLS port: no answer in clear
            httpx.get(url.replace("https://", "http://") + "/login", timeout=5).raise_for_status()


def test_behind_a_trusted_proxy_the_forwarded_scheme_makes_the_cookie_secure(lab):
    forwarded = {"X-Forwarded-Proto": "https", "X-Forwarded-For": "192.0.2.7"}
    with served(lab["db"], "--forwarded-allow-ips", "127.0.0.1") as url:
        with httpx.Client(base_url=url, timeout=15) as client:
            signed = _sign_in(client, forwarded)
            assert signed.status_code == 303 and "secure" in signed.headers["set-cookie"].lower()
            assert "strict-transport-security" in signed.headers
    with served(lab["db"]) as url:  # no proxy named: its headers are anybody's, and ignored
        with httpx.Client(base_url=url, timeout=15) as client:
            signed = _sign_in(client, forwarded)
            assert signed.status_code == 303 and "secure" not in signed.headers["set-cookie"].lower()
            assert "strict-transport-security" not in signed.headers


def test_listening_beyond_this_machine_without_tls_is_warned_about_in_one_line():
    """The warning itself (binding 0.0.0.0 in a test would open the test's server to the network)."""
    assert exposure_warning("127.0.0.1", Transport()) is None
    assert exposure_warning("::1", Transport()) is None
    warned = exposure_warning("0.0.0.0", Transport())
    assert warned is not None and "without TLS" in warned and "\n" not in warned
    assert exposure_warning("0.0.0.0", Transport(forwarded_allow_ips="10.0.0.2")) is None


def test_a_certificate_without_its_key_is_refused_in_one_line(lab, certificate):
    certfile, _ = certificate
    for args, why in ((["--certfile", certfile], "together"),
                      (["--certfile", certfile, "--keyfile", certfile], "not a certificate and its")):
        done = labcal("serve", "--port", "0", "--db", lab["db"], *args)
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1 and why in done.stderr
