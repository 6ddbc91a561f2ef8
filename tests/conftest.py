import numpy as np
import pytest

from shared.core.graph import Graph, graph_from_dict


@pytest.fixture
def small_graph() -> Graph:
    """5 nodes, a triangle with a tail and a pendant: irregular degrees, so Gamma != Gamma^T."""
    return graph_from_dict(
        {"name": "small", "nodes": [10, 11, 12, 13, 14], "edges": [[10, 11], [11, 12], [12, 10], [12, 13], [13, 14]]}
    )


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture
def certificates(tmp_path):
    """A test CA and a server certificate it signed for 127.0.0.1 and localhost, made by openssl:
    (ca.pem, server.pem, server-key.pem). Zenoh's TLS (rustls) refuses a self-signed certificate
    used as its own CA, so the server's is signed by a separate one."""
    import subprocess

    d = tmp_path / "certs"
    d.mkdir()
    run = lambda *a: subprocess.run(["openssl", *a], check=True, capture_output=True, cwd=d)  # noqa: E731
    run(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "2",
        "-subj",
        "/CN=mures-test-ca",
        "-addext",
        "basicConstraints=critical,CA:TRUE",
        "-addext",
        "keyUsage=critical,keyCertSign",
        "-keyout",
        "ca-key.pem",
        "-out",
        "ca.pem",
    )
    run("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost", "-keyout", "server-key.pem", "-out", "s.csr")
    (d / "ext.cnf").write_text(
        "subjectAltName=IP:127.0.0.1,DNS:localhost\nbasicConstraints=CA:FALSE\nextendedKeyUsage=serverAuth\n"
    )
    run(
        "x509",
        "-req",
        "-in",
        "s.csr",
        "-CA",
        "ca.pem",
        "-CAkey",
        "ca-key.pem",
        "-CAcreateserial",
        "-days",
        "2",
        "-extfile",
        "ext.cnf",
        "-out",
        "server.pem",
    )
    return d / "ca.pem", d / "server.pem", d / "server-key.pem"
