"""The engine on the mission clock: moves that take their edge's travel time in ticks, robots that
decide on arrival, training and evaluation with travel times (`mures train --speed`, `mures evaluate
--clock`), and the paper's model as the special case of one tick a move."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from shared.core.clock import TravelTimes, move_ticks, step_model, tick_model
from shared.core.graph import builtin_graph, graph_from_dict
from shared.core.models import Sensor, lazy_walk, uniform_walk
from shared.core.records import parse_record
from shared.engine.estimate import collect_missions
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.searchers import RandomSearcher
from shared.engine.sim import SearchSim
from shared.learning.config import TrainConfig
from shared.learning.train import train


def mures(*args):
    return subprocess.run([sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True)


def _office(lengths: np.ndarray | float):
    g = builtin_graph("office")
    return dataclasses.replace(g, edge_lengths=np.broadcast_to(np.asarray(lengths, dtype=float), (g.m,)).copy())


def _office_file(tmp_path):
    """OFFICE with doors 1-3 m apart (at 0.5 m/s moves of 2-6 ticks, a step 4) as a graph file."""
    graph_file = tmp_path / "office.json"
    graph_file.write_text(json.dumps(_office(np.linspace(1.0, 3.0, builtin_graph("office").m)).to_json()))
    return graph_file


def _line(ticks: int):
    """Three rooms in a row, each door ``ticks`` m apart (1 m/s, 1 s ticks: ``ticks`` ticks a move)."""
    g = graph_from_dict({"name": "LINE", "nodes": [0, 1, 2], "edges": [[0, 1], [1, 2]], "start_node": 0})
    return dataclasses.replace(g, edge_lengths=np.full(g.m, float(ticks)))


def test_move_ticks_round_each_edge_to_whole_ticks_and_refuse_a_graph_without_lengths():
    g = _line(1)
    g = dataclasses.replace(g, edge_lengths=np.array([2.6, 0.2]))
    ticks = move_ticks(g, speed=0.5, tick_s=1.0)  # 5.2 s and 0.4 s
    assert ticks[0, 1] == ticks[1, 0] == 5 and ticks[1, 2] == 1  # at least one tick
    assert ticks[0, 0] == ticks[2, 2] == 1 and ticks[0, 2] == 0  # a stay one tick, no edge none
    with pytest.raises(ValueError, match="no edge lengths"):
        move_ticks(builtin_graph("office"), 0.5)
    with pytest.raises(ValueError, match="give a robot's real speed"):  # a speed in the wrong unit
        move_ticks(g, 1e-9)
    fast = lazy_walk(g, 0.5)  # per tick, faster than any step of 8 ticks made a tick's worth
    made = step_model(fast, step_s=8.0)
    assert (made.prob >= 0).all() and np.allclose(np.bincount(made.src, weights=made.prob), 1.0)
    assert made.prob[made.src == made.dst].max() == 0.0  # the stay clipped: it always moves
    np.testing.assert_allclose(step_model(tick_model(fast, 8.0), 8.0).prob, fast.prob)  # the inverse
    clock = TravelTimes.of(g, 0.5, 1.0)
    assert clock.step_s == pytest.approx(np.median([2.6, 0.2]) / 0.5) and clock.t_max(g.n) == 3 * 3 * 3


def test_a_robot_in_transit_reads_nothing_decides_nothing_and_arrives_after_its_ticks():
    g = _line(3)
    target = uniform_walk(g)
    target = dataclasses.replace(target, b0=np.array([0.0, 0.0, 1.0]))  # the target starts at the far end
    stay = dataclasses.replace(target, prob=np.where(target.src == target.dst, 1.0, 0.0))  # and stays there
    sim = SearchSim(g, stay, Sensor(), 1, 1, seed=0, auto_reset=False, move_ticks=move_ticks(g, 1.0))
    obs = sim.reset()
    assert obs.ready.tolist() == [[True]] and obs.pos.tolist() == [[0]]
    seen = []
    for action in (1, 0, 0, 2, 2, 2):  # only the first and the fourth count: the others come in transit
        obs, res = sim.step(torch.tensor([[action]]))
        seen.append((int(obs.t[0]), int(obs.pos[0, 0]), bool(obs.ready[0, 0]), bool(res.done[0])))
    assert seen == [
        (1, 0, False, False),
        (2, 0, False, False),
        (3, 1, True, False),  # arrived at 1 after 3 ticks
        (4, 1, False, False),
        (5, 1, False, False),
        (6, 2, True, True),  # arrived at 2 and caught the target there at tick 6
    ]
    assert int(res.capture_time[0]) == 6


def test_one_tick_a_move_is_the_paper_model_the_same_seeds_give_the_same_episodes_and_training():
    g, g1 = builtin_graph("office"), _office(0.8)
    target, sensor = uniform_walk(g), Sensor()
    clock = TravelTimes.of(g1, speed=0.8)
    assert (clock.ticks[g1.closed_adjacency] == 1).all() and clock.ticks_per_step == 1.0

    def rand(seed):
        return RandomSearcher(g, seed=seed)

    steps = evaluate(g, target, sensor, 3, rand, episodes=300, seed=4)
    ticks = evaluate(g1, clock.model(target), sensor, 3, rand, episodes=300, seed=4, clock=clock)
    np.testing.assert_array_equal(steps.capture_time, ticks.capture_time)
    curves = []
    for graph, speed in ((g, None), (g1, 0.8)):
        cfg = TrainConfig(robots=2, episodes=768, em_first=512, em_missions=32, seed=2, speed=speed)
        res = train(graph, target, sensor, cfg)
        curves.append([p["mean_capture_time"] for p in res.summary["learning_curve"]])
        assert res.summary["em_updates"][0]["missions"] == 32
    assert curves[0] == curves[1]


def test_records_on_the_clock_hold_each_robots_readings_at_their_ticks_and_em_fits_per_tick():
    g = _office(np.linspace(1.0, 4.0, builtin_graph("office").m))  # moves of 1-4 ticks at 1 m/s
    clock = TravelTimes.of(g, speed=1.0)
    target = clock.model(uniform_walk(g))
    res = evaluate(g, target, Sensor(), 2, lambda s: RandomSearcher(g, seed=s), episodes=40, seed=1, record=True,
                   clock=clock)  # fmt: skip
    recs = list(episode_records(g, res, Sensor(), tick_s=clock.tick_s))
    assert len(recs) == 80
    for rec in recs:
        ep = parse_record(rec, g)
        assert ep.times is not None and ep.times[0] == 0.0 and (np.diff(ep.times) >= 1.0).all()
    # some robot spent more than one tick on a move somewhere: readings are not every tick
    assert any((np.diff(parse_record(r, g).times) > 1.0).any() for r in recs)
    mission0 = [parse_record(r, g) for r in recs[:2]]
    assert max(float(ep.times[-1]) for ep in mission0) == pytest.approx(float(res.capture_time[0]) * clock.tick_s)
    data = collect_missions(((0, r) for r in recs), g, tick_s=clock.tick_s)
    assert len(data.length) == 40 and int(data.length[0]) == int(res.capture_time[0]) + 1
    with pytest.raises(ValueError, match="tick_s"):
        next(episode_records(g, res, Sensor()))


def test_mures_train_speed_and_evaluate_clock_from_the_command_line(tmp_path):
    graph_file = _office_file(tmp_path)
    team = tmp_path / "team"
    r = mures("train", "--graph", str(graph_file), "--robots", "2", "--episodes", "512", "--em-first", "256",
              "--em-missions", "16", "--speed", "0.5", "--seed", "1", "--out", str(team), "--quiet")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "on the clock at 0.5 m/s: moves of 2-6 ticks of 1 s" in r.stderr
    assert "ticks when some robot decided" in r.stdout and " s); wrote" in r.stdout
    meta = json.loads((team / "policy.json").read_text())
    assert meta["training"]["speed"] == 0.5 and meta["training"]["tick"] == 1.0
    r = mures("evaluate", "--graph", str(graph_file), "--robots", "2", "--searcher", f"policy:{team}",
              "--episodes", "64", "--seed", "1", "--clock", "--speed", "0.5", "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["clock"] == {"speed_m_s": 0.5, "tick_s": 1.0, "step_s": pytest.approx(4.0, abs=0.01)}
    assert out["mean_capture_time_s"] == pytest.approx(out["mean_capture_time"]) and out["ci95_halfwidth_s"] > 0
    # the robots' own team code on the clock (TimedTeamAgent) in the engine: with links up every
    # decision is on the team's plan
    r = mures("evaluate", "--graph", str(graph_file), "--robots", "2", "--searcher", f"policy:{team}",
              "--team-searcher", "fhpe-sa", "--episodes", "16", "--seed", "1", "--clock", "--speed", "0.5",
              "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    flight = json.loads(r.stdout)["team"]
    assert flight["coordinated_share"] == 1.0 and flight["own_steps"] == 0 and flight["team_steps"] > 0
    # a team trained on the clock has a model per tick: refused in steps, in one line
    r = mures("evaluate", "--graph", str(graph_file), "--robots", "2", "--searcher", f"policy:{team}",
              "--episodes", "8")  # fmt: skip
    assert r.returncode == 2 and "trained on the clock" in r.stderr and "Traceback" not in r.stderr
    r = mures("evaluate", "--graph", str(graph_file), "--robots", "2", "--searcher", f"policy:{team}",
              "--team-searcher", "fhpe-sa", "--episodes", "8")  # fmt: skip
    assert r.returncode == 2 and "fly its team on travel times (--clock)" in r.stderr, r.stderr
    for args, says in (
        (("train", "--env", "office", "--speed", "0.5"), "no edge lengths"),
        (("train", "--graph", str(graph_file), "--tick", "2"), "give --speed too"),
        (("evaluate", "--graph", str(graph_file), "--searcher", "fhpe-sa", "--clock"), "not 'fhpe-sa'"),
        (("evaluate", "--env", "office", "--searcher", "greedy", "--clock"), "no edge lengths"),
    ):
        r = mures(*args, "--robots", "2", "--episodes", "8", "--out", str(tmp_path / "x"))
        if args[0] == "evaluate":
            r = mures(*args, "--robots", "2", "--episodes", "8")
        assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, (args, r.stderr)


def test_mures_train_speed_trains_a_marl_baseline_on_the_clock_with_em_per_tick(tmp_path):
    graph_file = _office_file(tmp_path)
    team = tmp_path / "mappo"
    r = mures("train", "--graph", str(graph_file), "--robots", "2", "--algorithm", "mappo", "--episodes", "200",
              "--batch", "32", "--hp", "steps=16", "--em-first", "100", "--em-missions", "16", "--speed", "0.5",
              "--out", str(team), "--quiet")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "mappo on OFFICE" in r.stderr and "on the clock at 0.5 m/s: moves of 2-6 ticks" in r.stderr
    assert " team ticks) in " in r.stdout and " s); wrote" in r.stdout
    meta = json.loads((team / "policy.json").read_text())
    assert meta["algorithm"] == "mappo" and meta["training"]["speed"] == 0.5
    em = meta["summary"]["em_updates"][0]
    assert em["missions"] == 16 and em["kind"] == "em"  # fitted from the team's own timestamped missions
    assert meta["summary"]["clock"]["unit"] == "ticks" and meta["summary"]["clock"]["step_s"] == pytest.approx(4.0)
    r = mures("evaluate", "--graph", str(graph_file), "--robots", "2", "--searcher", f"policy:{team}",
              "--episodes", "32", "--seed", "1", "--clock", "--speed", "0.5", "--json")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["mean_capture_time_s"] > 0


def test_the_team_on_the_clock_drops_a_withdrawn_teammate_when_told_and_not_otherwise():
    from test_team import _snapshot

    from shared.engine.linked_team import TimedLinkedTeamSearcher

    graph = _office(np.linspace(1.0, 3.0, builtin_graph("office").m))
    clock = TravelTimes.of(graph, speed=0.5)
    snap = _snapshot(graph, 3)
    target = clock.model(uniform_walk(graph))
    seen = {}
    for known in (True, False):
        made = []

        def make(seed, known=known, made=made):
            made.append(TimedLinkedTeamSearcher(snap, graph, 3, clock, seed, "fhpe-sa", known_withdrawals=known))
            return made[-1]

        evaluate(graph, target, Sensor(), 3, make, episodes=4, seed=2, withdraw_at=[None, None, 6], clock=clock)
        agents = [a for team in made[0].timed.values() for a in team if a.me != "r3"]
        seen[known] = {frozenset(a.withdrawn) for a in agents}
        assert made[0].steps["team"] + made[0].steps["partial"] > 0
    assert seen[True] == {frozenset({"r3"})} and seen[False] == {frozenset()}
