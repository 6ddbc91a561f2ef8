"""Ingest fuzzing: thousands of Hypothesis-generated episode records, valid and broken one rule at
a time (tests/record_strategies.py), sent over Zenoh to a training-server process on each
database backend. Every invalid record is rejected with its reason, every valid one is stored
once (a resend is a duplicate), the server's counts add up to what was sent, the stored records
are the ones sent (reduced to the contract), and the server stays up."""

from __future__ import annotations

import json
import os
import random
import signal
from collections import Counter

import pytest
import zenoh
from hypothesis import HealthCheck, given, settings
from record_strategies import Sending, sendings

from shared.core.files import read_token
from shared.core.graph import builtin_graph
from shared.core.http import ApiClient
from shared.core.models import Sensor
from shared.core.records import canonical_record, parse_record, unexplained
from shared.core.wire import send_episode, zenoh_config
from shared.tools.fleetsim import start_server

pytestmark = pytest.mark.slow  # a server process

GRAPH = builtin_graph("office")
EXAMPLES = {"sqlite": 1500, "postgresql": 500}  # MURES_FUZZ_EXAMPLES overrides (benchmarks/reliability.py)


def test_generated_records_are_stored_once_or_rejected_with_their_reason(tmp_path, database_url, request):
    backend = "sqlite" if database_url is None else "postgresql"
    examples = int(os.environ.get("MURES_FUZZ_EXAMPLES", EXAMPLES[backend]))
    logs = tmp_path / "logs"
    logs.mkdir()
    data = tmp_path / "data"
    extra = ["--database-url", database_url] if database_url else []
    proc, base, endpoint = start_server(["--env", "office"], data, 2, Sensor(), logs, extra)
    stored: dict[tuple[str, str], bytes] = {}  # the first valid record sent for each key
    rejected: Counter[str] = Counter()
    sent = Counter[str]()
    try:
        with zenoh.open(zenoh_config("client", connect=[endpoint])) as session:

            @settings(
                max_examples=examples,
                deadline=None,
                database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
            )
            @given(s=sendings(GRAPH, "default"))
            def one(s: Sending) -> None:
                ok, body = send_episode(session, "default", s.robot, s.mission, s.payload)
                sent["valid" if s.valid else "invalid"] += 1
                if s.valid:
                    key = (s.robot, s.mission)
                    want = "duplicate" if key in stored else "stored"
                    # a valid record that no path of the target explains is stored, and set aside
                    aside = unexplained(parse_record(json.loads(s.payload), GRAPH), GRAPH)
                    assert ok is True and body == {"status": want, **({"set_aside": aside} if aside else {})}, (s, body)
                    stored.setdefault(key, s.payload)
                else:
                    assert ok is False and body["reason"] == s.reason and body["error"], (s, body)
                    rejected[s.reason] += 1

            one()
        api = ApiClient(base, read_token(data / "operator.token"))
        stats = api.get("/api/v1/episodes/stats")
        assert stats["stored"] == len(stored)
        assert stats["rejected"] == dict(rejected)
        assert sum(sent.values()) >= examples and sent["invalid"] > examples // 4 and len(stored) > examples // 20
        for (robot, mission), payload in random.Random(0).sample(sorted(stored.items()), min(100, len(stored))):
            want = canonical_record(parse_record(json.loads(payload), GRAPH, "default"), GRAPH)
            assert api.get(f"/api/v1/episodes/{robot}/{mission}") == want
        assert api.get("/api/v1/health")["status"] == "ok" and proc.poll() is None
        print(f"{backend}: {sum(sent.values())} records sent, {len(stored)} stored, rejected {dict(rejected)}")
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    assert "Traceback" not in (logs / "server.log").read_text()
