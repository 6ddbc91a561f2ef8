"""The robot agent's parts without a fleet: journal, outbox, policy install checks, backends."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import io
import json
import tarfile

import numpy as np
import pytest
import torch

from robot_agent.agent import Journal, Outbox, PolicyStore, team_clock_for
from robot_agent.backend import BackendError, load_backend
from robot_agent.examples.nav_goal import NavGoalBackend
from shared.core.graph import builtin_graph
from shared.core.models import Sensor, identity_model
from shared.core.snapshot_format import PolicyAgent, SnapshotError, read_snapshot
from shared.learning.policy import TeamPolicy
from shared.learning.team_snapshot import convert_snapshot, load_snapshot, save_snapshot
from shared.tools.cli import main as cli_main


def test_journal_recovers_the_steps_of_a_killed_mission(tmp_path):
    j = Journal(tmp_path / "journal.jsonl")
    j.begin({"mission_id": "m1", "policy_version": 3, "sensor": Sensor().to_json()})
    for t in range(4):
        j.step(t, 43, 0)
    j.fh.write('{"t": 4, "no')  # torn last line, as after a kill
    j.fh.flush()
    header, steps = Journal(tmp_path / "journal.jsonl").recover()
    assert header["mission_id"] == "m1" and [s["t"] for s in steps] == [0, 1, 2, 3]
    j.finish()
    assert Journal(tmp_path / "journal.jsonl").recover() is None


def test_outbox_is_durable_and_keeps_rejected_records(tmp_path):
    ob = Outbox(tmp_path / "outbox")
    p = ob.put({"mission_id": "m1", "robot_id": "r1"})
    assert ob.pending() == [p] and json.loads(p.read_text())["mission_id"] == "m1"
    ob.reject(p, "bad move")
    assert ob.pending() == []
    assert (tmp_path / "outbox" / "rejected" / "m1.json").exists()


def _artifact(tmp_path, graph, name="snap"):
    torch.manual_seed(0)
    pol = TeamPolicy(graph.n, 2, torch.as_tensor(graph.adjacency()))
    snap = save_snapshot(tmp_path / name, pol, graph, identity_model(graph), Sensor(), "cepg", [0.5, 0.5], {}, {})
    tar_path = tmp_path / f"{name}.tar"
    with tarfile.open(tar_path, "w") as tar:
        for f in snap.iterdir():
            tar.add(f, arcname=f.name)
    return tar_path, hashlib.sha256(tar_path.read_bytes()).hexdigest()


def test_policy_install_verifies_hash_map_and_contents(tmp_path):
    office, museum = builtin_graph("office"), builtin_graph("museum")
    store = PolicyStore(tmp_path / "policies", office)
    tar_path, sha = _artifact(tmp_path, office)
    with pytest.raises(ValueError, match="sha256"):
        store.install(2, tar_path, "0" * 64)
    assert store.version is None
    store.install(2, tar_path, sha)
    assert store.version == 2 and PolicyStore(tmp_path / "policies", office).load_current()
    other, other_sha = _artifact(tmp_path, museum, "m")
    with pytest.raises(ValueError, match=r"MUSEUM|map"):
        store.install(3, other, other_sha)
    evil = tmp_path / "evil.tar"
    with tarfile.open(evil, "w") as tar:
        info = tarfile.TarInfo("../../escape.txt")
        info.size = 3
        tar.addfile(info, io.BytesIO(b"bad"))
    import hashlib

    with pytest.raises((ValueError, tarfile.TarError)):
        store.install(4, evil, hashlib.sha256(evil.read_bytes()).hexdigest())
    assert not (tmp_path / "escape.txt").exists()
    assert store.version == 2  # the last good policy stays


class FakeNav:
    def __init__(self, node, fail_to=None):
        self.node, self.fail_to, self.goals = node, fail_to, []

    def current_node(self):
        return self.node

    def go_to(self, node, position, timeout_s):
        self.goals.append((node, position))
        if node == self.fail_to:
            return False
        self.node = node
        return True


class FakeDetector:
    def detect(self):
        return True


def test_nav_goal_backend_moves_and_reports_failures():
    g = builtin_graph("office")
    start = int(g.labels[g.start])
    nbr = int(g.labels[g.closed(g.start)[1]])
    nav = FakeNav(start, fail_to=nbr)
    b = NavGoalBackend(g, nav, FakeDetector())
    assert b.begin({}) == start and b.detect() == 1
    assert b.move(nbr) == start  # failed move: the robot stays, which is a legal step
    nav.fail_to = None
    assert b.move(nbr) == nbr and nav.goals[-1][0] == nbr
    with pytest.raises(BackendError):
        NavGoalBackend(g, FakeNav(99999), FakeDetector()).begin({})


def test_load_backend_errors_are_clear():
    with pytest.raises(ValueError, match="MODULE:CLASS"):
        load_backend("nonsense")
    with pytest.raises(ValueError, match="cannot load"):
        load_backend("no.such.module:Thing")
    with pytest.raises(ValueError, match="no begin"):
        load_backend("json:JSONDecoder")


def _legacy_snapshot(tmp_path, graph):
    """A snapshot as releases before safetensors wrote it: weights.pt (torch.save of the tensors)."""
    torch.manual_seed(1)
    pol = TeamPolicy(graph.n, 2, torch.as_tensor(graph.adjacency()))
    d = save_snapshot(tmp_path / "old", pol, graph, identity_model(graph), Sensor(), "cepg", [0.5, 0.5], {}, {})
    buf = io.BytesIO()
    torch.save({k: v.detach().clone() for k, v in pol.named_parameters()}, buf)
    (d / "weights.pt").write_bytes(buf.getvalue())
    (d / "weights.safetensors").unlink()
    meta = json.loads((d / "policy.json").read_text())
    meta["weights"] = {"file": "weights.pt", "sha256": hashlib.sha256(buf.getvalue()).hexdigest()}
    (d / "policy.json").write_text(json.dumps(meta))
    return d, pol


def test_older_torch_snapshots_are_read_and_converted_with_the_same_values(tmp_path):
    graph = builtin_graph("office")
    d, pol = _legacy_snapshot(tmp_path, graph)
    with pytest.raises(SnapshotError, match="mures snapshot convert"):  # the agent's reader names the fix
        read_snapshot(d, graph)
    team = load_snapshot(d, graph)  # the trainer's reader takes it as it is
    assert all(torch.equal(p, q) for p, q in zip(pol.parameters(), team.policy.parameters(), strict=True))
    assert convert_snapshot(d) is True and not (d / "weights.pt").exists()
    assert convert_snapshot(d) is False  # already converted
    data = read_snapshot(d, graph)
    for k, p in pol.named_parameters():
        assert np.array_equal(data.weights[k], p.detach().numpy()), k
    # the numpy decision step on the converted snapshot is the torch policy's, draw for draw
    agent = PolicyAgent(data, graph, robot=1, greedy_actions=True)
    agent.reset(graph.start, 0)
    logits = team.policy.logits_for(
        torch.tensor([1]), torch.tensor([[graph.start]]), torch.as_tensor(agent.belief, dtype=torch.float32)[None, None]
    )
    assert agent.act(graph.start) == int(logits.argmax())


def test_snapshot_convert_command(tmp_path):
    graph = builtin_graph("office")
    d, _pol = _legacy_snapshot(tmp_path, graph)
    assert cli_main(["snapshot", "convert", str(d)]) == 0 and (d / "weights.safetensors").exists()
    assert cli_main(["snapshot", "convert", str(d)]) == 0  # nothing to do, says so
    assert cli_main(["snapshot", "convert", str(tmp_path / "missing")]) == 2


def test_a_start_that_comes_during_a_mission_is_flown_after_it(tmp_path):
    """The server frees a robot once its mission is captured or stopped, before the agent has
    sent the record; an operator's next start can come in that gap and must not be lost."""
    from robot_agent.agent import Agent

    args = argparse.Namespace(
        robot_id="r1", fleet="f", token_file=None, server="http://127.0.0.1:9", ca_file=None, state_dir=str(tmp_path)
    )
    agent = Agent(args)
    for msg in (
        {"type": "start", "mission_id": "m2", "robots": ["r1", "r2"]},
        {"type": "start", "mission_id": "m3", "robots": ["r2"]},  # not this robot's
        {"type": "stop", "mission_id": "m1"},
    ):
        agent.control.put(msg)
    assert agent._control_for("m1") == {"type": "stop", "mission_id": "m1"}
    assert agent.next_control(timeout=0)["mission_id"] == "m2"
    assert agent.next_control(timeout=0) is None
    # a deferred start whose own stop arrives before the running mission ends is dropped
    agent.control.put({"type": "start", "mission_id": "m4", "robots": ["r1"]})
    agent.control.put({"type": "stop", "mission_id": "m4"})
    assert agent._control_for("m1") is None and agent.next_start is None


def test_the_sim_backend_waits_its_whole_timeout_for_a_world_that_is_not_there():
    """With no simulated world on the bus a Zenoh query ends at once (nothing matches it): the sim
    backend asks again until its timeout, and then says how long it waited."""
    import time

    import zenoh

    from robot_agent.backend import SimBackend
    from shared.core.wire import zenoh_config
    from shared.tools.fleetsim import free_port

    port = free_port()
    with zenoh.open(zenoh_config("peer", listen=[f"tcp/127.0.0.1:{port}"])) as session:
        graph = builtin_graph("office")
        backend = SimBackend(graph, "r1", session, "default", timeout=1.5)
        backend.begin({"mission_id": "m-1"})
        t0 = time.monotonic()
        with pytest.raises(
            BackendError, match=r"no simulated world answers on mures/default/sim/m-1/r1 \(waited [12](\.\d)? s\)"
        ):
            backend.detect()
        assert time.monotonic() - t0 >= 1.4


def test_the_minimal_backend_of_the_docs_loads_and_flies(tmp_path):
    """docs/connecting-a-robot.md's minimal backend, as a user would save it: loaded by file path,
    constructed as the agent constructs it, and every value it returns passes the agent's checks."""
    import re
    from pathlib import Path

    from robot_agent.backend import load_backend

    doc = (Path(__file__).resolve().parents[1] / "docs" / "connecting-a-robot.md").read_text(encoding="utf-8")
    code = re.search(r"```python\n(.*?)```", doc, re.S)
    assert code is not None, "the page shows a backend"
    (tmp_path / "printbot.py").write_text(code.group(1))
    graph = builtin_graph("office")
    backend = load_backend(f"{tmp_path / 'printbot.py'}:PrintBot", graph=graph, robot_id="r1", session=None, fleet="f")
    node = backend.begin({"mission_id": "m-1", "start_node": int(graph.labels[graph.start])})
    assert node == int(graph.labels[graph.start]) and backend.detect() == 0
    assert backend.move(int(graph.labels[graph.closed(graph.start)[1]])) == node
    backend.end()


def test_the_team_clock_by_default_is_the_mission_clock_for_real_robots_on_a_map_with_edge_lengths():
    office = builtin_graph("office")  # the paper's map: no edge lengths
    timed = dataclasses.replace(office, edge_lengths=np.ones(len(office.edges)))
    assert team_clock_for("auto", "nav2", timed) == "seconds"
    assert team_clock_for("auto", "my_robot:Backend", timed) == "seconds"
    assert team_clock_for("auto", "sim", timed) == "steps"  # the simulator's worlds: fleet-sim says which
    assert team_clock_for("auto", "nav2", office) == "steps"  # no lengths, no clock
    assert team_clock_for("steps", "nav2", timed) == "steps" and team_clock_for("seconds", "sim", office) == "seconds"
