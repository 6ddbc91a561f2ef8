"""The paper's comparison methods (shared/planners/) against brute force and each other."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from shared.core.fhpe_sa import GAMMA, FhpeSAPlanner, walks
from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.evaluate import evaluate
from shared.planners.fhpe import Fhpe, FhpeSA
from shared.planners.milp import Milp
from shared.planners.oracle import OracleSearcher, oracle_expected_time
from shared.registry import make_searcher


def _team_value(planner, b, paths):
    """Discounted capture probability of fixed team paths, by explicit propagation (the definition)."""
    U = b @ planner.gamma_dense
    v = 0.0
    for k in range(len(paths[0])):
        if k:
            U = U @ planner.gamma_dense
        miss = np.ones(planner.n)
        for p in paths:
            miss *= 1.0 - planner.hit * planner.det[p[k]]
        v += GAMMA ** (k + 1) * (U * (1.0 - miss)).sum()
        U = U * miss
    return v


@pytest.fixture
def office():
    g = builtin_graph("office")
    rng = np.random.default_rng(3)
    b = rng.random(g.n)
    return g, uniform_walk(g), b / b.sum(), rng


def test_milp_finds_the_best_single_robot_path(office):
    g, model, b, rng = office
    sensor = Sensor(eta_fn=0.1)
    pl = Milp(g, model, sensor, time_limit=30)
    start = int(rng.integers(g.n))
    best = max(_team_value(pl, b, [p]) for p in walks(g, start, 5))
    got = pl._solve(b, [start], {})[0]
    assert _team_value(pl, b, [got]) == pytest.approx(best, rel=1e-6)


def test_milp_stopped_at_once_keeps_its_first_incumbent_the_best_uncovered_move(office):
    g, model, _, _ = office
    pl = Milp(g, model, Sensor(), time_limit=1e-9)  # HiGHS stops before improving on what it was given
    start = next(v for v in range(g.n) if len(g.closed(v)) >= 3)
    a, c = [int(v) for v in g.closed(start) if v != start][:2]
    b = np.zeros(g.n)
    b[a], b[c] = 0.7, 0.3  # a static-ish target: most of the predicted mass stays on a, then c
    pl.gamma_dense = np.eye(g.n)
    paths = pl._solve(b, [start, start], {})
    assert pl.timeouts == 1
    assert [p[0] for p in paths] == [a, c]  # robot 1 takes a, robot 2 the best node a does not cover
    assert all(p == [p[0]] * pl.h for p in paths)


def test_milp_continues_its_plan_and_a_d_milp_robot_respects_the_plans_before_it(office):
    """The next decision starts from the last plan shifted by the step taken (a feasible point the
    solver then improves, so the value never drops below it); in d-milp each robot's plan holds
    the earlier robots' plans fixed."""
    g, model, b, rng = office
    pl = Milp(g, model, Sensor(eta_fn=0.1), time_limit=30)
    start = int(rng.integers(g.n))
    first = pl._solve(b, [start], {})[0]
    b2 = b @ pl.gamma_dense
    shifted = first[1:] + first[-1:]
    second = pl._solve(b2, [first[0]], {})[0]
    assert _team_value(pl, b2, [second]) >= _team_value(pl, b2, [shifted]) - 1e-9
    d = Milp(g, model, Sensor(eta_fn=0.1), time_limit=30, distributed=True)
    s0, s1 = int(rng.integers(g.n)), int(rng.integers(g.n))
    fixed = d._solve(b, [s0], {})
    both = d._solve(b, [s0, s1], {0: fixed[0]})
    assert both[0] == fixed[0] and both[1][0] in g.closed(s1)


def test_fhpe_maximises_over_joint_two_step_paths(office):
    g, model, b, _ = office
    pl = Fhpe(g, model, Sensor(eta_fn=0.2))
    starts = np.array([g.index[x] for x in (23, 24)]) if 23 in g.index and 24 in g.index else np.array([5, 6])
    W = [walks(g, int(p), 2) for p in starts]
    vals = {tuple(p[0] for p in combo): _team_value(pl, b, list(combo)) for combo in itertools.product(*W)}
    best = max(vals.values())
    move = tuple(int(x) for x in pl.plan(b, starts, np.ones(2, bool)))
    assert vals[move] == pytest.approx(best, rel=1e-9)


def test_fhpe_sa_is_exact_for_one_robot(office):
    g, model, b, _ = office
    pl = FhpeSA(g, model, Sensor())
    start = g.start
    P = walks(g, start, 5)
    best = max(_team_value(pl, b, [p]) for p in P)
    first = pl.plan(b, np.array([start]), np.ones(1, bool))[0]
    assert max(_team_value(pl, b, [p]) for p in P if p[0] == first) == pytest.approx(best, rel=1e-9)


def _travel_value(planner, b, start, path, steps):
    """One robot's discounted capture probability of ``path`` when each move lasts ``steps[u, v]``
    of the model's steps, the target propagated over each by dense matrix powers (the definition:
    c = ceil(s) passes of I + (s / c)(Gamma - I))."""
    eye = np.eye(planner.n)
    U, v, elapsed, here = b.copy(), 0.0, 0.0, start
    for p in path:
        s = steps[here, p]
        c = max(int(np.ceil(s - 1e-9)), 1)
        U = U @ np.linalg.matrix_power(eye + (s / c) * (planner.gamma_dense - eye), c)
        elapsed += s
        miss = 1.0 - planner.hit * planner.det[p]
        v += GAMMA**elapsed * (U * (1.0 - miss)).sum()
        U, here = U * miss, p
    return v


def test_fhpe_sa_with_travel_times_is_exact_for_one_robot(office):
    g, model, b, rng = office
    steps = np.zeros((g.n, g.n))
    u, v = g.edges[:, 0], g.edges[:, 1]
    steps[u, v] = steps[v, u] = rng.uniform(0.3, 3.0, len(u))  # each move's steps' worth of travel
    np.fill_diagonal(steps, 0.1)  # a stay: a tenth of a step
    pl = FhpeSAPlanner(g, model, Sensor(), horizon=3, move_steps=steps, travel=True)
    paper = FhpeSAPlanner(g, model, Sensor(), horizon=3)
    parted = 0
    for start in range(g.n):
        P = walks(g, start, 3)
        values = [_travel_value(pl, b, start, p, steps) for p in P]
        first = pl.plan(b, np.array([start]), np.ones(1, bool), np.random.default_rng(0))[0]
        assert max(x for x, p in zip(values, P, strict=True) if p[0] == first) == pytest.approx(max(values), rel=1e-9)
        parted += paper.plan(b, np.array([start]), np.ones(1, bool), np.random.default_rng(0))[0] != first
    assert parted  # travel times change the plan somewhere


def test_fhpe_sa_with_moves_of_one_step_each_plans_as_the_paper(office):
    g, model, _, rng = office
    ones = np.ones((g.n, g.n))
    paper = FhpeSAPlanner(g, model, Sensor())
    travel = FhpeSAPlanner(g, model, Sensor(), move_steps=ones, travel=True)
    for _ in range(5):
        b = rng.random(g.n)
        pos = rng.integers(0, g.n, 3)
        seed = int(rng.integers(1000))
        want = paper.plan(b / b.sum(), pos, np.ones(3, bool), np.random.default_rng(seed))
        got = travel.plan(b / b.sum(), pos, np.ones(3, bool), np.random.default_rng(seed))
        assert got.tolist() == want.tolist()
    with pytest.raises(ValueError, match="needs move_steps"):
        FhpeSAPlanner(g, model, Sensor(), travel=True)


def test_oracle_dp_matches_its_simulation_and_bounds_the_planners():
    g = builtin_graph("office")
    model, sensor = uniform_walk(g), Sensor()
    exact = oracle_expected_time(g, model, sensor, 1)
    sim = evaluate(g, model, sensor, 1, lambda s: OracleSearcher(g, model, sensor, 1, s), episodes=600, seed=2)
    r = sim.summary()
    assert abs(r["mean_capture_time"] - exact) <= 1.5 * r["ci95_halfwidth"] + 1e-9, (r, exact)
    sa = evaluate(g, model, sensor, 1, lambda s: make_searcher("fhpe-sa", g, model, sensor, s), episodes=60, seed=2)
    assert exact < sa.summary()["mean_capture_time"]
    assert oracle_expected_time(g, model, sensor, 2) < exact  # two all-seeing robots are faster


def test_planners_beat_random(office):
    g, model, _b, _ = office
    sensor = Sensor()
    res = {}
    for name in ("random", "fhpe-sa", "fhpe"):
        r = evaluate(
            g,
            model,
            sensor,
            2,
            lambda s, name=name: make_searcher(name, g, model, sensor, s, n_robots=2),
            episodes=80,
            seed=4,
        ).summary()
        res[name] = r["mean_capture_time"]
    assert res["fhpe-sa"] < res["random"] and res["fhpe"] < res["random"], res


def test_native_solver_output_stays_off_stdout():
    """What native code prints during a solve (HiGHS's printf diagnostics) goes to stderr, and
    output before and after keeps its order on stdout: `--json` stays pure JSON."""
    import subprocess
    import sys

    code = (
        "from shared.planners.milp import native_stdout_to_stderr, _LIBC\n"
        "print('before', flush=False)\n"
        "with native_stdout_to_stderr():\n"
        "    _LIBC.printf(b'HighsMipSolverData chatter\\n')\n"
        "print('after')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout == "before\nafter\n"
    assert "HighsMipSolverData chatter" in out.stderr
