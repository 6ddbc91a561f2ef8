"""Searching as a team (shared/core/team.py): the collective belief from observations that come
late, twice or never, the team's plan that robots with the same information agree on, the
fallback to a robot's own policy, and the team flown in the simulator over lossy links."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, lazy_walk, uniform_walk
from shared.core.records import RecordError, make_record, parse_record
from shared.core.snapshot_format import (
    PolicyAgent,
    SnapshotData,
    SnapshotError,
    param_shapes,
    read_snapshot,
    write_snapshot,
)
from shared.core.team import CollectiveBelief, LinkHistory, TeamAgent, mission_seed, team_searcher_of
from shared.engine.batched_belief import BatchedBelief, BeliefTracker
from shared.engine.evaluate import evaluate
from shared.engine.linked_team import LinkedTeamSearcher
from training_server.jobs import measured_links


def _observations(graph, robots: int, steps: int, seed: int) -> list[list[tuple[int, int]]]:
    """steps x robots (node row, z): random walks with random readings."""
    rng = np.random.default_rng(seed)
    pos = rng.integers(graph.n, size=robots)
    out = []
    for _ in range(steps):
        out.append([(int(p), int(rng.random() < 0.2)) for p in pos])
        pos = np.array([rng.choice(graph.closed(int(p))) for p in pos])
    return out


@pytest.mark.parametrize("sensor", [Sensor(), Sensor(eta_fn=0.2, eta_fp=0.1, detection="neighbourhood")])
def test_the_collective_belief_is_eq6_as_the_batched_engine_computes_it(sensor):
    graph = builtin_graph("office")
    model = lazy_walk(graph, 0.3)
    obs = _observations(graph, 3, 12, seed=1)
    mine = CollectiveBelief(graph, model, sensor, ["a", "b", "c"])
    for t, step in enumerate(obs):
        for r, (p, z) in zip("abc", step, strict=True):
            mine.add(t, r, p, z)
    engine = BatchedBelief(graph, model, sensor, "cpu", dtype=torch.float64)
    tracker = BeliefTracker(engine)
    for t, step in enumerate(obs):
        pos = torch.tensor([[p for p, _z in step]])
        z = torch.tensor([[bool(z) for _p, z in step]])
        lik = engine.collective_likelihood(pos, z).unsqueeze(1)  # (1, 1, n)
        b, _pred = tracker.update(lik, torch.tensor([t == 0]))
        np.testing.assert_allclose(mine.belief(t), b[0, 0].numpy(), rtol=1e-9, atol=1e-14)


def test_a_late_observation_changes_the_belief_exactly_as_if_it_had_come_on_time():
    """Observations added in a shuffled order, some twice, give the very same beliefs (bit for
    bit) as in order; a step never reported is no observation from that robot."""
    graph = builtin_graph("museum")
    model, sensor = uniform_walk(graph), Sensor(eta_fn=0.1)
    obs = _observations(graph, 4, 15, seed=2)
    robots = ["r1", "r2", "r3", "r4"]
    in_order = CollectiveBelief(graph, model, sensor, robots)
    for t, step in enumerate(obs):
        for r, (p, z) in zip(robots, step, strict=True):
            assert in_order.add(t, r, p, z)
    expected = [in_order.belief(t).copy() for t in range(len(obs))]

    late = CollectiveBelief(graph, model, sensor, robots)
    items = [(t, r, p, z) for t, step in enumerate(obs) for r, (p, z) in zip(robots, step, strict=True)]
    order = np.random.default_rng(0).permutation(len(items))
    for k, i in enumerate(order):
        late.add(*items[i])
        if k % 7 == 0:  # beliefs asked for along the way, before the late ones come
            late.belief(len(obs) - 1)
    assert not late.add(*items[0])  # a second copy is ignored
    assert not late.add(0, "r9", 0, 1)  # and a robot outside the team
    for t in range(len(obs)):
        assert np.array_equal(late.belief(t), expected[t])

    missing = CollectiveBelief(graph, model, sensor, robots)
    for t, r, p, z in items:
        if not (t == 5 and r == "r3"):
            missing.add(t, r, p, z)
    without = CollectiveBelief(graph, model, sensor, ["r1", "r2", "r4"])
    for t, r, p, z in items:
        if not (t == 5 and r == "r3"):
            without.add(t, r, p, z) if r != "r3" else None
    assert missing.reported(5) == {"r1", "r2", "r4"}
    np.testing.assert_allclose(missing.likelihood(5), without.likelihood(5))


def _snapshot(graph, robots: int, variant: str = "cepg", seed: int = 0) -> SnapshotData:
    """A snapshot of random weights (H = 8) with the uniform walk as its model."""
    rng = np.random.default_rng(seed)
    n, H = graph.n, 8
    weights = {
        "w_pos": rng.normal(size=(robots, n, H)),
        "w_bel": rng.normal(size=(robots, n, H)),
        "b1": rng.normal(size=(robots, H)),
        "w2": rng.normal(size=(robots, H, n)),
        "b2": rng.normal(size=(robots, n)),
    }
    meta = {"variant": variant, "robots": robots}
    return SnapshotData(meta=meta, weights=weights, model=uniform_walk(graph), sensor=Sensor())


def test_robots_with_the_same_information_choose_the_same_team_plan():
    graph = builtin_graph("office")
    snap = _snapshot(graph, 3)
    robots = ["r1", "r2", "r3"]
    agents = [TeamAgent(snap, graph, robots, r, seed=42, searcher="fhpe-sa") for r in robots]
    obs = _observations(graph, 3, 6, seed=3)
    for t, step in enumerate(obs):
        for agent in agents:
            for r, (p, z) in zip(robots, step, strict=True):
                agent.observe(r, t, p, 0 if t < 5 else z)
        plans = []
        for agent in agents:
            b = agent.collective.belief(t)
            pos = np.array([p for p, _z in step])
            plans.append(agent._team_plan(t, b, pos, np.ones(3, dtype=bool)))
            move, mode = agent.act(t, step[agent.index][0])
            assert mode == "team" and move == plans[-1][agent.index]
        assert all(np.array_equal(plans[0], q) for q in plans[1:])
        for i, (p, _z) in enumerate(step):
            assert plans[0][i] in graph.closed(p)


def test_a_robot_falls_back_to_its_own_policy_while_its_teammates_are_missing():
    """With fallback_after 1, incomplete steps fly the robot's own policy (a lone PolicyAgent's draws); a
    teammate silent past the timeout is dropped and the plan goes on without it; one that
    reports again is taken back; a robot that hears from nobody flies alone."""
    graph = builtin_graph("office")
    snap = _snapshot(graph, 3)
    robots = ["r1", "r2", "r3"]
    steps_only = {"link_quality_min": 0.0}  # the step rule alone (the link's quality: the next test)
    me = TeamAgent(
        snap,
        graph,
        robots,
        "r1",
        seed=7,
        searcher="fhpe-sa",
        own_seed=11,
        timeout_steps=2,
        fallback_after=1,
        **steps_only,
    )
    partial = TeamAgent(
        snap, graph, robots, "r1", seed=7, searcher="fhpe-sa", own_seed=11, timeout_steps=2, **steps_only
    )
    lone = PolicyAgent(snap, graph, 0, seed=11)
    p = 0
    modes = []
    for t in range(8):
        me.observe("r1", t, p, 0)
        partial.observe("r1", t, p, 0)
        lone.reset(p, 0) if t == 0 else lone.observe(p, 0)
        if t not in (1, 2, 3, 6):
            me.observe("r2", t, 5, 0)
            partial.observe("r2", t, 5, 0)
        if t < 1 or t >= 5:
            me.observe("r3", t, 9, 0)
            partial.observe("r3", t, 9, 0)
        modes.append(partial.act(t, p)[1])
        move, mode = me.act(t, p)
        expected = {0: "team", 1: "own", 2: "own", 3: "own", 4: "team", 5: "team", 6: "own", 7: "team"}[t]
        assert mode == expected, (t, mode)
        if mode == "own":  # the own policy draws only when it flies: as a lone agent drawing then
            assert move == lone.act(p)
        assert move in graph.closed(p)
        p = move
    # steps 1-3: r2 silent (below the timeout at 1, dropped from 3: yet r3 also silent until 5);
    # step 4: r3 dropped (silent 1-4), r2 back: complete without r3
    assert me.live(4) == ["r1", "r2"] and me.live(5) == ["r1", "r2", "r3"]
    # by default (no fallback_after) an incomplete step while a teammate is heard plans on what came
    assert modes == ["team", "partial", "own", "own", "team", "team", "partial", "team"]
    # r2 heard at 0, 4, 5, 7 (sent 0-7), r3 at 0, 5, 6, 7 (sent 0-7)
    assert partial.summary() == {
        "team_steps": 4,
        "partial_steps": 2,
        "own_steps": 2,
        "observations_heard": 8,
        "observations_sent": 16,
        "teammates_dropped": 0,  # silent, not gone: their liveliness stayed
        "flown_for": 3,
    }
    alone = TeamAgent(snap, graph, robots, "r1", seed=7, searcher="fhpe-sa", timeout_steps=1)
    alone.observe("r1", 0, 0, 0)
    alone.observe("r1", 1, 0, 0)
    assert alone.act(1, 0)[1] == "own"  # nobody heard at all: not a team of one


def test_a_robot_whose_links_deliver_too_little_flies_its_own_policy_throughout():
    """The link's quality counts this mission's messages and the earlier missions' (LinkHistory):
    a robot whose earlier missions heard half of what was sent flies its own policy even on a
    complete step, one with a good history plans with its team, and a robot alone always does (its
    belief is the team's); a teammate's silence after its last step heard (a withdrawn robot) is
    not counted as loss."""
    graph = builtin_graph("office")
    snap = _snapshot(graph, 2)
    robots = ["r1", "r2"]
    poor, good = LinkHistory(), LinkHistory()
    poor.fold(heard=30, sent=60)
    good.fold(heard=58, sent=60)
    good.fold(heard=60, sent=60)
    assert good.sent == pytest.approx(0.9 * 60 + 60) and good.heard == pytest.approx(0.9 * 58 + 60)
    for history, expected in ((poor, "own"), (good, "team")):
        agent = TeamAgent(snap, graph, robots, "r1", seed=3, searcher="fhpe-sa", link_history=history)
        for t in range(3):
            agent.observe("r1", t, 0, 0)
            agent.observe("r2", t, 4, 0)
            assert agent.act(t, 0)[1] == expected
    # a robot alone plans on its own belief (the team's): no link to judge
    lone = TeamAgent(snap, graph, ["r1"], "r1", seed=3, searcher="fhpe-sa", link_history=poor)
    lone.observe("r1", 0, 0, 0)
    assert lone.act(0, 0)[1] == "team"
    # r2 reports steps 0-2 and falls silent: its steps 3-9 are not counted as sent
    agent = TeamAgent(snap, graph, robots, "r1", seed=3, searcher="fhpe-sa")
    for t in range(10):
        agent.observe("r1", t, 0, 0)
        if t < 3:
            agent.observe("r2", t, 4, 0)
    assert agent.link_counts() == (3, 3) and agent.link_quality() == 1.0


def test_a_c_cepg_snapshot_flies_in_a_team_and_nowhere_else():
    graph = builtin_graph("office")
    snap = _snapshot(graph, 2, variant="c-cepg")
    with pytest.raises(SnapshotError, match="fly it in a team"):
        PolicyAgent(snap, graph, 0)
    assert team_searcher_of(snap) == "c-cepg" and team_searcher_of(_snapshot(graph, 2)) is None
    agent = TeamAgent(snap, graph, ["a", "b"], "a", seed=1, searcher=team_searcher_of(snap))
    agent.observe("a", 0, 0, 0)
    agent.observe("b", 0, 3, 0)
    move, mode = agent.act(0, 0)
    assert mode == "team" and move in graph.closed(0)


def _capture_times(snap, graph, searcher, loss, episodes=40, delay=0):
    counter = {"team": 0, "partial": 0, "own": 0}
    res = evaluate(
        graph,
        uniform_walk(graph),
        Sensor(),
        3,
        lambda s: LinkedTeamSearcher(snap, graph, 3, s, searcher, loss, delay, counter=counter),
        episodes=episodes,
        seed=4,
    )
    return np.asarray(res.capture_time), counter


def test_the_team_in_the_simulator_with_links_up_down_and_lossy():
    """All links down: exactly the robots' own policies (every robot-step falls back); links up:
    every robot-step on the team's plan, and sooner than on its own on these episodes; a lossy
    link plans on what has come at some steps; a link whose messages all come a step late
    delivers nothing in time: the own policies again, as with one late by the timeout's length."""
    graph = builtin_graph("office")
    snap = _snapshot(graph, 3)
    own, _ = _capture_times(snap, graph, None, 0.0)
    down, c_down = _capture_times(snap, graph, "fhpe-sa", 1.0)
    up, c_up = _capture_times(snap, graph, "fhpe-sa", 0.0)
    lossy, c_lossy = _capture_times(snap, graph, "fhpe-sa", 0.3)
    assert np.array_equal(down, own) and c_down["team"] == 0
    assert c_up["own"] == c_up["partial"] == 0 and c_up["team"] > 0
    assert c_lossy["team"] > 0 and c_lossy["partial"] > 0
    assert up.mean() < own.mean()  # random networks against FHPE-SA on the true model
    delayed, c_delayed = _capture_times(snap, graph, "fhpe-sa", 0.0, delay=1)
    assert c_delayed["team"] == c_delayed["partial"] == 0 and np.array_equal(delayed, own)
    stale, c_stale = _capture_times(snap, graph, "fhpe-sa", 0.0, delay=3)
    assert c_stale["team"] == c_stale["partial"] == 0 and np.array_equal(stale, own)
    assert mission_seed(5, 0) != mission_seed(5, 1)
    assert len(lossy) == 40


def test_the_servers_link_loss_counts_the_records_of_robots_that_flew_with_a_team():
    def rec(searcher, heard, sent, team=3, own=1):
        c = {"team_searcher": searcher, "team_steps": team, "partial_steps": 0, "own_steps": own}
        return {"coordination": {**c, "observations_heard": heard, "observations_sent": sent}}

    links = measured_links([rec("fhpe-sa", 30, 40), rec("fhpe-sa", 10, 40, team=0, own=4), rec(None, 0, 0), {}, "x"])
    assert links == {"records": 2, "link_loss": 0.5, "coordinated_share": 0.375}
    assert measured_links([rec(None, 0, 0), {}]) == {"records": 0, "link_loss": None, "coordinated_share": None}


def test_a_records_coordination_is_checked_and_kept():
    graph = builtin_graph("office")
    base = {"team_searcher": "fhpe-sa", "team_steps": 1, "partial_steps": 0, "own_steps": 1}

    def record(coordination):
        return make_record(
            graph, fleet="f", mission_id="m", robot_id="r1", nodes=[0, 0, 0], z=[0, 0, 0], sensor=Sensor(),
            captured=False, capture_time=None, captured_by=None, policy_version=1, coordination=coordination,
        )  # fmt: skip

    full = {**base, "observations_heard": 3, "observations_sent": 4}
    assert parse_record(record(full), graph).coordination == full
    assert parse_record(record(base), graph).coordination == base  # records of agents before links were counted
    for bad in (
        {"observations_heard": 5, "observations_sent": 4},
        {"observations_heard": 3},
        {"observations_sent": -1},
    ):
        with pytest.raises(RecordError, match="observations_heard and observations_sent") as err:
            parse_record(record({**base, **bad}), graph)
        assert err.value.reason == "coordination"


def _weights(graph, robots: int, hidden: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {k: rng.normal(size=s).astype(np.float32) for k, s in param_shapes(graph.n, robots, hidden).items()}


def test_a_snapshot_holds_a_team_per_team_size_each_file_checked(tmp_path):
    graph = builtin_graph("office")
    path = tmp_path / "s"
    teams = {1: _weights(graph, 1, 4, 1), 2: _weights(graph, 2, 8, 2)}
    write_snapshot(
        path, graph, _weights(graph, 3, 8, 0), uniform_walk(graph), Sensor(), "cepg", [0.5], {}, {}, teams=teams
    )
    snap = read_snapshot(path, graph)
    assert snap.team_sizes == [1, 2, 3]
    one = snap.team_for(1)
    assert one.robots == 1 and one.meta["hidden"] == 4 and np.array_equal(one.weights["w2"], teams[1]["w2"])
    assert snap.team_for(3) is snap and snap.team_for(5) is snap  # its own N, and a size it holds no team for
    with pytest.raises(ValueError, match="other than the main team's 3"):
        write_snapshot(path, graph, snap.weights, snap.model, Sensor(), "cepg", [0.5], {}, {}, teams={3: snap.weights})
    (path / "team-2.safetensors").write_bytes(b"x" + (path / "team-2.safetensors").read_bytes()[1:])
    with pytest.raises(SnapshotError, match=r"team-2\.safetensors: sha256 does not match"):
        read_snapshot(path, graph)
    meta = json.loads((path / "policy.json").read_text())
    meta["teams"]["7"] = meta["teams"].pop("2")
    (path / "policy.json").write_text(json.dumps(meta))
    with pytest.raises(SnapshotError, match="teams entry '7'"):
        read_snapshot(path, graph)


def test_a_robot_flies_the_team_for_its_missions_robots_and_switches_when_a_teammate_drops_out():
    graph = builtin_graph("office")
    snap = _snapshot(graph, 3)
    snap.teams = {1: _weights(graph, 1, 8, 1), 2: _weights(graph, 2, 8, 2)}
    pair = TeamAgent(snap, graph, ["a", "b"], "b", seed=1, searcher=None)
    assert pair.flown_for == 2 and np.array_equal(pair.own.w2, snap.teams[2]["w2"][1])
    trio = TeamAgent(snap, graph, ["a", "b", "c"], "c", seed=1, searcher=None)
    trio.observe("c", 0, 5, 0)
    trio.act(0, 5)
    belief = trio.own.belief.copy()
    assert trio.withdraw("a") and not trio.withdraw("a") and not trio.withdraw("c") and not trio.withdraw("x")
    # c is the second of the robots left: network 1 of the team for 2, its belief kept
    assert trio.flown_for == 2 and np.array_equal(trio.own.w2, snap.teams[2]["w2"][1])
    assert np.array_equal(trio.own.belief, belief) and trio.live(1) == ["b", "c"]
    trio.withdraw("b")
    assert trio.flown_for == 1 and np.array_equal(trio.own.w2, snap.teams[1]["w2"][0])
    assert trio.summary()["teammates_dropped"] == 2 and trio.summary()["flown_for"] == 1
    # a version that switches to the team for 1 only (its training measured the switch to 2 a loss)
    snap.meta["switch_to"] = [1]
    picky = TeamAgent(snap, graph, ["a", "b", "c"], "c", seed=1, searcher=None)
    picky.withdraw("a")
    assert picky.flown_for == 3 and np.array_equal(picky.own.w2, snap.weights["w2"][2])
    picky.withdraw("b")
    assert picky.flown_for == 1 and np.array_equal(picky.own.w2, snap.teams[1]["w2"][0])
    # a version without teams: the N-robot team's network i, whoever drops out
    plain = TeamAgent(_snapshot(graph, 3), graph, ["a", "b", "c"], "c", seed=1, searcher=None)
    plain.withdraw("a")
    assert plain.flown_for == 3 and np.array_equal(plain.own.w2, _snapshot(graph, 3).weights["w2"][2])


def test_with_known_withdrawals_the_robots_left_fly_the_team_built_for_them_in_the_simulator():
    """The simulator's withdrawn robot (Fig. 12, 13): robots that learn of it fly the team for the
    robots left; robots that do not, and a version without teams, fly the N-robot team throughout."""
    graph = builtin_graph("office")
    snap = _snapshot(graph, 3)
    snap.teams = {2: _weights(graph, 2, 8, 2)}
    counts = {}
    for known in (False, True):
        counter = {"team": 0, "partial": 0, "own": 0}
        searcher = LinkedTeamSearcher(snap, graph, 3, 0, None, counter=counter, known_withdrawals=known)
        evaluate(
            graph,
            uniform_walk(graph),
            Sensor(),
            3,
            lambda s, x=searcher: x,
            episodes=8,
            seed=2,
            withdraw_at=[None, 2, None],
        )
        counts[known] = {tuple(a.flown_for for a in team) for team in searcher.teams.values()}
    assert counts[False] == {(3, 3, 3)} and (2, 3, 2) in counts[True]  # r2 withdrawn at t = 2


def test_snapshot_combine_writes_one_version_with_a_team_per_size(tmp_path, capsys):
    from shared.tools.cli import main

    graph = builtin_graph("office")
    for k in (1, 3):
        write_snapshot(
            tmp_path / f"N{k}",
            graph,
            _weights(graph, k, 8, k),
            uniform_walk(graph),
            Sensor(),
            "cepg",
            [0.5] * k,
            {"seed": k},
            {},
        )

    def combine(main_team: str, other: str, out: str) -> int:
        return main(
            [
                "snapshot",
                "combine",
                "--env",
                "office",
                str(tmp_path / main_team),
                str(tmp_path / other),
                "--out",
                str(tmp_path / out),
            ]
        )

    assert combine("N3", "N1", "c") == 0
    snap = read_snapshot(tmp_path / "c", graph)
    assert snap.team_sizes == [1, 3] and snap.meta["training"]["teams_from"] == [str(tmp_path / "N1")]
    assert combine("N3", "N3", "d") == 2
    assert "a team for 3 robots is there already" in capsys.readouterr().err and not (tmp_path / "d").exists()


def test_a_general_policy_flown_as_a_robots_own_reads_where_its_teammates_were_heard(monkeypatch):
    """The general policy's teammates' features (docs/general-policy.md) come from the observations
    a robot hears: by step, each teammate's latest node (none for one not heard or withdrawn); on
    the mission clock, where each is headed."""
    from shared.core.graph_policy import GeneralAgent
    from shared.core.graph_policy import param_shapes as general_shapes
    from shared.core.timed_team import TimedTeamAgent

    graph = builtin_graph("office")
    rng = np.random.default_rng(0)
    weights = {k: rng.normal(size=s).astype(np.float32) for k, s in general_shapes(8).items()}
    meta = {"architecture": "general", "variant": "cepg", "robots": 3, "hidden": 8}
    snap = SnapshotData(meta=meta, weights=weights, model=uniform_walk(graph), sensor=Sensor())
    heard: list[list[int]] = []

    def act(self, p, belief, mates=None):
        heard.append(sorted(np.asarray(mates).tolist()))
        return p

    monkeypatch.setattr(GeneralAgent, "act", act)
    robots = ["a", "b", "c"]
    agent = TeamAgent(snap, graph, robots, "a", seed=1, searcher=None)
    agent.observe("a", 0, 5, 0)
    agent.observe("b", 0, 7, 0)
    agent.act(0, 5)
    agent.observe("b", 1, 8, 0)
    agent.observe("c", 1, 9, 0)
    agent.act(1, 5)
    agent.withdraw("b")
    agent.act(2, 5)
    assert heard == [[7], [8, 9], [9]]
    timed = TimedTeamAgent(snap, graph, robots, "a", seed=1, searcher=None, step_s=8.0)
    timed.observe_at("a", 0, 5, 0, 0.0)
    timed.observe_at("b", 0, 7, 0, 0.0, goal=11)
    timed.act_at(0.0, 5)
    assert heard[-1] == [11]
