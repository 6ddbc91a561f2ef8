"""Searching as a team on the mission clock (shared/core/timed_team.py): the model a tick's worth,
observations folded in at the tick they were made whatever order they come in, teammates counted
where they are headed, no wait for a teammate that is travelling, and links judged by delay."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from test_team import _snapshot

from shared.core.clock import move_seconds, tick_model
from shared.core.graph import builtin_graph
from shared.core.models import uniform_walk
from shared.core.timed_team import LATE_S, TimedTeamAgent
from shared.core.wire import observation_message, parse_observation

ROBOTS = ["r1", "r2", "r3"]


def test_the_step_model_made_a_ticks_worth_stays_a_model_and_is_the_step_model_at_one_step():
    graph = builtin_graph("office")
    step = uniform_walk(graph)
    tick = tick_model(step, step_s=10.0, tick_s=1.0)
    gamma, per_step = tick.dense(), step.dense()
    np.testing.assert_allclose(gamma.sum(axis=1), 1.0)
    np.testing.assert_allclose(gamma - np.eye(graph.n), 0.1 * (per_step - np.eye(graph.n)))
    np.testing.assert_allclose(tick_model(step, step_s=2.0, tick_s=2.0).dense(), per_step)
    # ten ticks move about as far as one step: the mass that left the start node is close
    start = np.eye(graph.n)[graph.start]
    left_ticks = 1 - (start @ np.linalg.matrix_power(gamma, 10))[graph.start]
    left_step = 1 - (start @ per_step)[graph.start]
    assert left_ticks == pytest.approx(left_step, rel=0.4) and left_ticks < left_step


def test_a_graph_without_edge_lengths_has_no_mission_clock():
    graph = builtin_graph("office")
    with pytest.raises(ValueError, match="no edge lengths"):
        move_seconds(graph, 0.5)
    lengths = np.linspace(2.0, 10.0, len(graph.edges))
    assert move_seconds(dataclasses.replace(graph, edge_lengths=lengths), 0.5) == pytest.approx(12.0)


def _agents(graph, step_s: float = 8.0):
    snap = _snapshot(graph, 3)
    return [TimedTeamAgent(snap, graph, ROBOTS, r, seed=7, searcher="fhpe-sa", step_s=step_s) for r in ROBOTS]


def test_observations_are_folded_in_at_the_tick_they_were_made_whatever_order_they_come_in():
    graph = builtin_graph("office")
    rng = np.random.default_rng(2)
    readings = []  # (robot, t, p, z, time_s): each robot on its own clock
    for r in ROBOTS:
        clock, p = 0.0, graph.start
        for t in range(8):
            readings.append((r, t, p, int(rng.random() < 0.2), clock))
            p = int(rng.choice(graph.closed(p)))
            clock += float(rng.uniform(4.0, 25.0))
    on_time, shuffled = _agents(graph)[0], _agents(graph)[0]
    for obs in sorted(readings, key=lambda o: o[4]):
        on_time.observe_at(*obs)
    for i in rng.permutation(len(readings)):
        shuffled.observe_at(*readings[i])
    k = on_time.tick(max(o[4] for o in readings)) + 3
    np.testing.assert_allclose(on_time.collective.belief(k), shuffled.collective.belief(k))
    assert on_time.collective.reported(on_time.tick(readings[9][4])) >= {readings[9][0]}


def test_a_teammate_in_transit_counts_where_it_is_headed_and_nobody_waits_for_it():
    graph = builtin_graph("office")
    me, other, third = _agents(graph)
    start = graph.start
    far = int(graph.nbr[start, 1])
    for agent in (me, other, third):
        for r in ROBOTS:
            agent.observe_at(r, 0, start, 0, 0.0)
    # r2 left for `far` at t = 0; its next reading comes 20 s later. r1 decides at 6 s meanwhile.
    me.observe_at("r2", 0, start, 0, 0.0, goal=far)
    seen = {}
    me._team_plan = lambda k, b, pos, active: seen.update(k=k, pos=pos.copy(), active=active.copy()) or pos
    _row, mode = me.act_at(6.0, start)
    assert mode == "team" and seen["k"] == 6
    assert seen["pos"].tolist() == [start, far, start] and seen["active"].all()
    # a teammate not heard for the timeout leaves the plan; one never heard at all sends the robot to its own policy
    me.observe_at("r1", 1, start, 0, 200.0)
    me._team_plan = lambda k, b, pos, active: seen.update(k=k, pos=pos.copy(), active=active.copy()) or pos
    assert me.act_at(200.0, start)[1] == "own"  # r2 and r3 last heard at 0 s, 200 s ago: no teammate in reach


def test_at_the_start_a_robot_plans_with_its_teammates_on_the_start_node_before_hearing_them():
    graph = builtin_graph("office")
    me = _agents(graph)[0]
    me.observe_at("r1", 0, graph.start, 0, 0.0)
    seen = {}
    me._team_plan = lambda k, b, pos, active: seen.update(pos=pos.copy()) or pos
    assert me.act_at(0.0, graph.start)[1] == "partial" and seen["pos"].tolist() == [graph.start] * 3
    me.observe_at("r1", 1, graph.start, 0, 1.0)
    assert me.act_at(1.0, graph.start)[1] == "own"  # later, none heard: its link may be down


def test_links_are_judged_by_the_networks_delay_not_by_the_teammates_travel_times():
    graph = builtin_graph("office")
    me = _agents(graph)[0]
    me.observe_at("r1", 0, graph.start, 0, 0.0)
    me.act_at(0.0, graph.start)
    # a teammate's reading made 30 s after this robot's last decision (it travelled long) is in time
    me.observe_at("r2", 0, graph.start, 0, 0.0)
    me.observe_at("r2", 1, graph.start, 0, 30.0)
    assert me.link_counts() == (2, 2)
    me.act_at(60.0, graph.start)
    # one made at 40 s that comes only after this robot decided at 60 s is late
    me.observe_at("r2", 2, graph.start, 0, 60.0 - LATE_S - 18.0)
    assert me.link_counts() == (2, 3)


def test_an_observation_on_the_clock_carries_its_time_and_goal_and_bad_ones_are_refused():
    key = "mures/default/observations/r1/m1"
    msg = observation_message("m1", "r1", 3, 12, 0, time_s=41.25, goal=14)
    assert parse_observation(key, json.dumps(msg).encode()) == (msg, "")
    assert "time_s" not in observation_message("m1", "r1", 3, 12, 0)
    for bad, says in ((-1, "time_s"), ("5", "time_s"), (True, "time_s"), (float("inf"), "time_s")):
        assert says in parse_observation(key, json.dumps({**msg, "time_s": bad}).encode())[1]
    assert "goal" in parse_observation(key, json.dumps({**msg, "goal": -2}).encode())[1]


def test_a_record_carries_the_clock_of_every_reading_or_of_none():
    from shared.core.models import Sensor
    from shared.core.records import RecordError, make_record, parse_record

    graph = builtin_graph("office")

    def record(times):
        return make_record(graph, fleet="f", mission_id="m", robot_id="r1", nodes=[0, 0, 0], z=[0, 0, 0],
                           sensor=Sensor(), captured=False, capture_time=None, captured_by=None,
                           times=times)  # fmt: skip

    assert parse_record(record([0.0, 4.5, 19.25]), graph).times.tolist() == [0.0, 4.5, 19.25]
    assert parse_record(record(None), graph).times is None  # the step clock's records, as before
    for steps, says in (
        ([0.0, 5.0, 3.0], "before the step before it"),
        ([0.0, -1.0, 3.0], "finite number of seconds"),
    ):
        with pytest.raises(RecordError, match=says) as err:
            parse_record(record(steps), graph)
        assert err.value.reason == "time"
    partial = record([0.0, 1.0, 2.0])
    del partial["steps"][1]["time_s"]
    with pytest.raises(RecordError, match="on some steps only"):
        parse_record(partial, graph)
    first_missing = record([0.0, 1.0, 2.0])
    del first_missing["steps"][0]["time_s"]
    with pytest.raises(RecordError, match="on some steps only"):
        parse_record(first_missing, graph)
    bad = record([0.0, 1.0, 2.0])
    bad["steps"][2]["time_s"] = "2"
    with pytest.raises(RecordError, match="finite number"):
        parse_record(bad, graph)


def test_a_version_trained_on_the_clock_keeps_its_model_per_tick_and_its_own_belief_predicts_each_tick():
    graph = builtin_graph("office")
    graph = dataclasses.replace(graph, edge_lengths=np.full(graph.m, 4.0))  # a step of 8 s at 0.5 m/s
    step_snap = _snapshot(graph, 3)
    per_tick = tick_model(step_snap.model, step_s=8.0)
    clock_snap = dataclasses.replace(step_snap, model=per_tick, meta={**step_snap.meta, "training": {"speed": 0.5}})
    assert clock_snap.clock == (0.5, 1.0) and step_snap.clock is None
    on_clock = TimedTeamAgent(clock_snap, graph, ROBOTS, "r1", seed=7, searcher="fhpe-sa", step_s=8.0)
    of_steps = TimedTeamAgent(step_snap, graph, ROBOTS, "r1", seed=7, searcher="fhpe-sa", step_s=8.0)
    # the same team plan's model either way: converted once, never twice; FHPE-SA, which moves once
    # a step, plans on the model made a step's worth again
    np.testing.assert_allclose(on_clock.collective._filter._prob, of_steps.collective._filter._prob)
    np.testing.assert_allclose(on_clock.planner.gamma_dense, step_snap.model.dense(), atol=1e-12)
    np.testing.assert_allclose(of_steps.planner.gamma_dense, step_snap.model.dense())
    nxt = int(graph.nbr[graph.start, 1])
    for agent in (on_clock, of_steps):
        agent.observe_at("r1", 0, graph.start, 0, 0.0)
        agent.observe_at("r1", 1, nxt, 0, 9.0)  # its next reading 9 ticks later
    b0 = on_clock.own.filter._observe(on_clock.own.filter._b0.copy(), graph.start, 0)
    prior = b0
    for _ in range(9):
        prior = on_clock.own.filter.predict_of(prior)
    np.testing.assert_allclose(on_clock.own.belief, on_clock.own.filter._observe(prior, nxt, 0))
    # a team of steps: its own policy's belief moves one step between its readings, as trained
    np.testing.assert_allclose(
        of_steps.own.belief, of_steps.own.filter._observe(of_steps.own.filter.predict_of(b0), nxt, 0)
    )
    with pytest.raises(ValueError, match="ticks of 1 s, the agent's are 2 s"):
        TimedTeamAgent(clock_snap, graph, ROBOTS, "r1", seed=7, searcher="fhpe-sa", step_s=8.0, tick_s=2.0)
