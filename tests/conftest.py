import os
import shutil
import socket
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import pytest

from shared.core.graph import Graph, graph_from_dict


def pytest_configure(config: pytest.Config) -> None:
    """One torch thread in every test process, as `mures train` and the server's training runs
    default to: `make test` runs one process per core (pytest-xdist), and a second thread in each
    would wait at the end of every small operation for the core the other process holds."""
    import torch

    torch.set_num_threads(1)


@pytest.fixture(autouse=True, scope="session")
def _checkpoints_in_a_temporary_folder(tmp_path_factory: pytest.TempPathFactory):
    """MARL teams that tests train through `mures experiment` keep their checkpoints under the
    session's temporary folder (subprocesses included), not in the user's ~/.cache."""
    from shared.tools.experiments import CHECKPOINTS_ENV

    before = os.environ.get(CHECKPOINTS_ENV)
    os.environ[CHECKPOINTS_ENV] = str(tmp_path_factory.mktemp("checkpoints"))
    yield
    if before is None:
        del os.environ[CHECKPOINTS_ENV]
    else:
        os.environ[CHECKPOINTS_ENV] = before


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


# ---------------------------------------------------------------------- PostgreSQL
def _postgres_bin() -> Path | None:
    """The directory of the machine's PostgreSQL server programs (initdb, pg_ctl), if installed."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"))
    if found:
        return found[-1].parent
    pg_ctl = shutil.which("pg_ctl")
    return Path(pg_ctl).parent if pg_ctl else None


class PostgresCluster:
    """A throwaway PostgreSQL cluster of the machine's own PostgreSQL on a free loopback port: initdb
    and pg_ctl run as the postgres user when we are root (initdb refuses root), trust auth on
    loopback only. ``database()`` gives a fresh, empty database's SQLAlchemy URL."""

    def __init__(self, bindir: Path) -> None:
        self.bindir = bindir
        self.root = Path(tempfile.mkdtemp(prefix="mures-pg-"))
        self.port = free_port()
        self.count = 0
        self.as_postgres = os.geteuid() == 0
        if self.as_postgres:
            shutil.chown(self.root, "postgres", "postgres")
        self._run("initdb", "-D", str(self.root / "data"), "-U", "postgres", "--auth=trust", "-E", "UTF8")
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1"
        self._run("pg_ctl", "-D", str(self.root / "data"), "-o", opts, "-l", str(self.root / "log"), "-w", "start")
        self.url = f"postgresql+psycopg://postgres@127.0.0.1:{self.port}"

    def _run(self, prog: str, *args: str) -> None:
        cmd = [str(self.bindir / prog), *args]
        if self.as_postgres:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)

    def database(self) -> str:
        import psycopg

        self.count += 1
        name = f"mures_test_{self.count}"
        with psycopg.connect(f"host=127.0.0.1 port={self.port} user=postgres dbname=postgres", autocommit=True) as c:
            c.execute(f"CREATE DATABASE {name}")
        return f"{self.url}/{name}"

    def stop(self) -> None:
        try:
            self._run("pg_ctl", "-D", str(self.root / "data"), "-m", "immediate", "stop")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="session")
def postgres():
    """The session's PostgreSQL cluster. Skipped where PostgreSQL is not installed, unless
    MURES_REQUIRE_POSTGRES=1 (CI), where its absence fails the tests."""
    bindir = _postgres_bin()
    if bindir is None:
        if os.environ.get("MURES_REQUIRE_POSTGRES") == "1":
            pytest.fail("PostgreSQL is not installed (apt-get install postgresql), and MURES_REQUIRE_POSTGRES=1")
        pytest.skip("PostgreSQL is not installed (apt-get install postgresql)")
    cluster = PostgresCluster(bindir)
    yield cluster
    cluster.stop()


@pytest.fixture(params=["sqlite", "postgresql"])
def database_url(request, tmp_path):
    """Each backend in turn: None (the server's embedded SQLite) or a fresh PostgreSQL database."""
    if request.param == "sqlite":
        return None
    return request.getfixturevalue("postgres").database()
