"""Each fault of benchmarks/reliability.py once, at a random moment (seeded), on real processes:
the benchmark repeats them (20 times each) for docs/reliability.md; here every CI run tries them
again. The kill -9 during ingest and of an agent mid-mission are tests/test_fleet.py's."""

from __future__ import annotations

import random
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import reliability

pytestmark = pytest.mark.slow  # server, agent and training processes


def test_kill_during_a_training_run(tmp_path, database_url):
    r = reliability.fault_training(tmp_path, database_url, 2, random.Random(1))
    assert r["training_process_outlived_server"] == 0 and r["versions_complete"] and r["answers"]
    # a cancelled run stays cancelled (or had finished); another is resumed by the restarted server
    assert set(r["run_status_after"]) <= {"cancelled", "succeeded", "resumed, then succeeded"}
    assert r["run_status_after"].get("resumed, then succeeded", 0) + r["run_status_after"].get("succeeded", 0) >= 1


def test_kill_during_publication_serves_no_partial_version(tmp_path):
    r = reliability.fault_publication(tmp_path, None, 3, random.Random(2))
    assert r["versions_complete"]


def test_a_full_disk_refuses_records_and_loses_none(tmp_path):
    r = reliability.fault_disk_full(tmp_path, None, 1, random.Random(3))
    assert r["lost"] == 0 and r["refused_while_full"] > 0 and r["acknowledged"] > 0


def test_the_router_restarted_mid_mission(tmp_path):
    r = reliability.fault_zenoh_link(tmp_path, None, 1, random.Random(4))
    assert r["records_stored"] == r["records_expected"] and r["outboxes_drained"]
