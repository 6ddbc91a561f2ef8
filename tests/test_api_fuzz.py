"""API fuzzing with a peer's tool: Schemathesis, every check, from the OpenAPI document a
training-server process serves, with the operator token, the agent token and none on SQLite and
the operator token on PostgreSQL. Zero findings.

The server runs with a high --sign-in-limit: Schemathesis sends wrong tokens on purpose (its
ignored_auth check), and after ten of them the default limit answers 429 to everything from that
address, which is the point of the limit (tests/test_api.py tests it) but leaves nothing to fuzz.
benchmarks/reliability.py runs the same with more examples for docs/reliability.md.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from shared.core.models import Sensor
from shared.tools.fleetsim import start_server

pytestmark = pytest.mark.slow  # a server process

EXAMPLES = int(os.environ.get("MURES_API_FUZZ_EXAMPLES", "25"))
# the event stream runs until the client leaves (tests/test_console.py tests it)
EXCLUDE = ["--exclude-path", "/api/v1/events"]


def schemathesis(base: str, token: str | None, examples: int, out: Path) -> tuple[int, str]:
    """Run the Schemathesis CLI against ``base``; (exit status, its report)."""
    exe = Path(sys.executable).with_name("schemathesis")
    cmd = [str(exe), "run", f"{base}/openapi.json", "--checks", "all", "--max-examples", str(examples)]
    cmd += ["--workers", "1", "--no-color", *EXCLUDE]
    if token:
        cmd += ["-H", f"Authorization: Bearer {token}"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900, cwd=out)
    return r.returncode, r.stdout + r.stderr


def test_schemathesis_finds_nothing_with_any_token(tmp_path, database_url):
    logs = tmp_path / "logs"
    logs.mkdir()
    data = tmp_path / "data"
    extra = ["--sign-in-limit", "1000000"] + (["--database-url", database_url] if database_url else [])
    proc, base, _endpoint = start_server(["--env", "office"], data, 2, Sensor(), logs, extra)
    try:
        # every token on SQLite; on PostgreSQL the operator's, whose requests reach every handler
        # and the store: the agent's and no token differ from it in authentication and scopes,
        # above the store, and the agents' records on PostgreSQL are fuzzed by test_ingest_fuzz.py
        for who in ("operator", "agent", None) if database_url is None else ("operator",):
            token = (data / f"{who}.token").read_text().strip() if who else None
            code, report = schemathesis(base, token, EXAMPLES, tmp_path)
            cases = re.search(r"(\d+) generated", report)
            assert code == 0 and cases and int(cases.group(1)) > 100, f"token {who}:\n{report[-6000:]}"
            assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    assert "Traceback" not in (logs / "server.log").read_text()
