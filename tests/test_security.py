"""The fleet's protections with real processes: HTTPS with a self-signed certificate."""

from __future__ import annotations

import signal
import ssl
import subprocess
import urllib.error

import pytest

from shared.core.files import read_token
from shared.core.http import ApiClient
from shared.core.models import Sensor
from shared.tools.fleetsim import start_server

pytestmark = pytest.mark.slow  # starts a training-server process


def self_signed(tmp_path, name="server"):
    """A self-signed certificate for 127.0.0.1 and localhost, made by openssl: (cert, key)."""
    cert, key = tmp_path / f"{name}.pem", tmp_path / f"{name}-key.pem"
    cmd = ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=127.0.0.1"]
    cmd += ["-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost", "-keyout", str(key), "-out", str(cert)]
    subprocess.run(cmd, check=True, capture_output=True)
    return cert, key


def test_rest_api_over_https_with_a_self_signed_certificate(tmp_path):
    cert, key = self_signed(tmp_path)
    logs = tmp_path / "logs"
    logs.mkdir()
    tls = ["--tls-cert", str(cert), "--tls-key", str(key)]
    proc, base, _endpoint = start_server(["--env", "office"], tmp_path / "data", 2, Sensor(), logs, tls, str(cert))
    try:
        assert base.startswith("https://")
        token = read_token(tmp_path / "data" / "agent.token")
        api = ApiClient(base, token, ca_file=str(cert))  # the agent's --ca-file
        assert api.get("/api/v1/policies/current")["version"] == 1
        with pytest.raises(urllib.error.URLError) as exc:  # an unverified certificate is refused
            ApiClient(base, token).get("/api/v1/health")
        assert isinstance(exc.value.reason, ssl.SSLCertVerificationError)
        with pytest.raises(OSError):  # and plaintext gets no answer
            ApiClient(base.replace("https://", "http://"), token, timeout=5).get("/api/v1/health")
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
