import copy
import json
from pathlib import Path

import numpy as np
import pytest

from shared.core.graph import builtin_graph, grid_graph
from shared.core.models import Sensor, lazy_walk, uniform_walk
from shared.core.records import RecordError, canonical_record, parse_record, read_jsonl
from shared.engine.estimate import collect_missions, em, eq8, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.searchers import RandomSearcher


def simulated_records(graph, truth, sensor, N, missions, seed):
    res = evaluate(graph, truth, sensor, N, lambda s: RandomSearcher(graph, seed=s), missions, seed, record=True)
    return list(episode_records(graph, res, sensor))


@pytest.fixture(scope="module")
def grid_data():
    g = grid_graph(3, 3)
    truth = lazy_walk(g, 0.8)
    recs = simulated_records(g, truth, Sensor(eta_fn=0.1, eta_fp=0.02), N=3, missions=400, seed=11)
    return g, truth, recs


def test_em_recovers_a_lazy_target_from_robot_records_only(grid_data):
    g, truth, recs = grid_data
    data = collect_missions(enumerate(recs), g)
    assert data.used_records == len(recs) and not data.skipped
    est = em(g, data)
    assert est.converged
    ll = np.array(est.log_likelihood)
    assert np.all(np.diff(ll) >= -1e-6 * abs(ll[0]))  # EM (with SQUAREM safeguard) never goes down
    tv = mean_row_tv(est.model, truth)
    assert tv < 0.2, tv  # the estimator's acceptance bar (set for 1000 missions; 400 here)
    assert tv < mean_row_tv(uniform_walk(g), truth) / 3
    assert np.allclose(est.model.dense().sum(1), 1)
    assert np.all(est.model.dense()[~g.adjacency(closed=True)] == 0)  # support stays on N[u]
    plain = em(g, data, accelerate=False, max_iter=2000)
    assert mean_row_tv(plain.model, est.model) < 0.05  # same fixed point, reached faster with SQUAREM


def test_eq8_runs_and_is_row_stochastic(grid_data):
    g, truth, recs = grid_data
    est = eq8(g, collect_missions(enumerate(recs), g, capture_aware=False))
    G = est.model.dense()
    assert np.allclose(G.sum(1), 1) and np.all(G >= 0)
    assert mean_row_tv(est.model, truth) < mean_row_tv(uniform_walk(g), truth)


def _mutations(rec, graph):
    def m(f):
        r = copy.deepcopy(rec)
        f(r)
        return r

    far = int(graph.labels[-1])
    return {
        "schema": m(lambda r: r.update(schema="mures.episode/0")),
        "missing-field": m(lambda r: r.pop("robot_id")),
        "graph_id": m(lambda r: r.update(graph_id="sha256:00")),
        "sensor": m(lambda r: r["sensor"].update(eta_fn=0.7)),
        "t-sequence": m(lambda r: r["steps"][1].update(t=5)),
        "node": m(lambda r: r["steps"][1].update(node=999)),
        "move": m(lambda r: r["steps"][1].update(node=far)),
        "z": m(lambda r: r["steps"][0].update(z=2)),
        "outcome": m(lambda r: r["outcome"].update(capture_time=10**6)),
        "bad-id": m(lambda r: r.update(robot_id="r/1")),
        "not-object": [rec],
    }


def test_bad_records_are_rejected_with_a_reason_and_skipped(grid_data, tmp_path):
    g, _truth, recs = grid_data
    good = next(r for r in recs if len(r["steps"]) >= 3 and r["outcome"]["captured"])
    bad = _mutations(good, g)
    for reason, rec in bad.items():
        with pytest.raises(RecordError) as exc:
            parse_record(rec, g)
        assert exc.value.reason == reason, (reason, str(exc.value))
    path = tmp_path / "eps.jsonl"
    with open(path, "w") as fh:
        for r in recs[:30]:
            fh.write(json.dumps(r) + "\n")
        fh.write(json.dumps(recs[0]) + "\n")  # a duplicate
        fh.write("{not json\n")
        for r in bad.values():
            fh.write(json.dumps(r) + "\n")
    data = collect_missions(read_jsonl(path), g)
    assert data.used_records == 30
    assert data.skipped["duplicate"] == 1 and data.skipped["json"] == 1
    assert sum(data.skipped.values()) == 2 + len(bad)


def test_records_bound_integers_quote_little_and_store_only_the_contract(grid_data):
    g, _truth, recs = grid_data
    good = next(r for r in recs if r["outcome"]["captured"])
    with pytest.raises(RecordError) as exc:  # would overflow the database's 64-bit integers
        parse_record({**good, "policy_version": 2**64}, g)
    assert exc.value.reason == "bad-field"
    huge = "x" * 5_000_000
    for rec in ({**good, "schema": huge}, {**good, "fleet": huge}, {**good, "steps": [{"t": 0, "node": huge, "z": 0}]}):
        with pytest.raises(RecordError) as exc:
            parse_record(rec, g)
        assert len(str(exc.value)) < 300  # the value is quoted cut short, never echoed whole
    padded = {**good, "note": huge, "steps": [{**s, "extra": 1} for s in good["steps"]]}
    assert canonical_record(parse_record(padded, g), g) == good


def test_em_on_gamma_hats_support_alone_gives_the_dense_estimate(grid_data):
    """The sparse E-step (Gamma_hat on its n + 2m entries, one (n, k_t) block per step: what maps
    above 512 nodes use) against the dense one on the same missions, with and without a prior and
    with worker processes: the same passes, log-likelihoods and estimate up to rounding."""
    g, _truth, recs = grid_data
    data = collect_missions(enumerate(recs), g)
    for kw in ({}, {"pseudo_count": 1.0, "b0_pseudo_count": 1.0, "workers": 2}):
        dense, sparse = em(g, data, sparse=False, **kw), em(g, data, sparse=True, **kw)
        assert sparse.iterations == dense.iterations and sparse.converged
        assert np.allclose(sparse.log_likelihood, dense.log_likelihood, rtol=1e-10)
        assert np.abs(sparse.model.dense() - dense.model.dense()).max() < 1e-8
        assert np.abs(sparse.model.b0 - dense.model.b0).max() < 1e-8
        assert np.allclose(sparse.model.dense().sum(1), 1.0)
    subset = data.subset(np.array([3, 0, 7]))  # packed missions keep their own steps
    assert np.array_equal(subset.mission(1), data.mission(3)) and list(subset.length) == [
        data.length[0],
        data.length[3],
        data.length[7],
    ]


def test_packed_forward_backward_matches_a_plain_one_mission_at_a_time():
    """The EM's forward-backward (missions sorted by length, step t on the missions still
    running) against the textbook recursion run on each mission alone, lengths 1 to T."""
    import torch

    from shared.engine.estimate import MissionData, _ForwardBackward

    rng = np.random.default_rng(5)
    n, M, T = 6, 9, 7
    G = rng.random((n, n)) * (rng.random((n, n)) < 0.6) + np.eye(n)
    G /= G.sum(1, keepdims=True)
    b0 = rng.random(n)
    b0 /= b0.sum()
    length = np.array([1, 7, 3, 7, 2, 5, 4, 6, 3])
    lik = rng.random((M, T, n)) * (rng.random((M, T, n)) < 0.8)
    lik[np.arange(T)[None, :] >= length[:, None]] = 1.0
    packed = np.concatenate([lik[m, : length[m]] for m in range(M)])  # MissionData holds the steps taken
    fb = _ForwardBackward(MissionData(lik=packed, length=length, used_records=M))
    alpha, beta, c, xi = fb(torch.as_tensor(G), torch.as_tensor(b0))
    order = np.argsort(-length, kind="stable")
    ll, counts = 0.0, np.zeros((n, n))
    for slot, m in enumerate(order):
        Tm, Lm = length[m], lik[m]
        a, cs = np.zeros((Tm, n)), np.zeros(Tm)
        for t in range(Tm):
            a[t] = (b0 if t == 0 else a[t - 1] @ G) * Lm[t]
            cs[t] = a[t].sum()
            a[t] /= cs[t]
        bt = np.ones((Tm, n))
        for t in range(Tm - 2, -1, -1):
            bt[t] = G @ (Lm[t + 1] * bt[t + 1]) / cs[t + 1]
            counts += np.outer(a[t], Lm[t + 1] * bt[t + 1] / cs[t + 1])
        ll += np.log(cs).sum()
        assert np.allclose(alpha[:Tm, slot].numpy(), a) and np.allclose(beta[:Tm, slot].numpy(), bt)
        assert np.allclose(c[:Tm, slot].numpy(), cs) and np.all(c[Tm:, slot].numpy() == 1.0)
    assert np.isclose(float(c.log().sum()), ll)
    assert np.allclose(xi.numpy(), counts)
    again = fb(torch.as_tensor(G), torch.as_tensor(b0))  # buffers reused: the same answer
    assert np.allclose(again[3].numpy(), counts)


def test_em_on_one_short_mission_gives_stochastic_rows():
    """Regression: the three records of one 45-step mission on OFFICE (from a console test's retrain)
    made EM divide a start node's expected transitions of about 1e-306 by the 1e-300 floor, so its
    row summed to 4e-6 and the training run failed with a ModelError. Such a row now keeps its value."""
    g = builtin_graph("office")
    records = json.loads((Path(__file__).parent / "data" / "em-one-mission.json").read_text())
    data = collect_missions(enumerate(records), g, fleet="default")
    assert len(data.length) == 1
    est = em(g, data, init=uniform_walk(g), max_iter=300, tol=1e-5)
    np.testing.assert_allclose(est.model.dense().sum(axis=1), 1.0, atol=1e-9)


def test_em_shared_by_worker_processes_gives_the_estimate_of_one(grid_data, monkeypatch):
    """`em(..., workers=K)`: K groups of missions, K - 1 of them in forked processes. The estimate
    is one process's up to the rounding of the counts' sums, and the same to the bit whether the
    groups run in the workers or here in turn (where processes cannot be forked)."""
    import shared.engine.estimate as estimate

    g, _truth, recs = grid_data
    data = collect_missions(enumerate(recs), g)
    import multiprocessing

    one = em(g, data)
    seen: set[int] = set()  # the worker processes alive while EM runs

    def progress(_it, _ll):
        seen.update(p.pid for p in multiprocessing.active_children() if p.name == "mures-em")

    forked = em(g, data, workers=3, progress=progress)
    assert len(seen) == 2  # two groups of three in processes of their own
    assert forked.iterations == one.iterations and forked.converged
    np.testing.assert_allclose(forked.model.dense(), one.model.dense(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(forked.model.b0, one.model.b0, rtol=0, atol=1e-6)
    np.testing.assert_allclose(forked.log_likelihood, one.log_likelihood, rtol=1e-12)
    monkeypatch.setattr(estimate.multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    here = em(g, data, workers=3)
    assert np.array_equal(here.model.dense(), forked.model.dense()) and np.array_equal(here.model.b0, forked.model.b0)
    assert here.log_likelihood == forked.log_likelihood


def _em_in_a_daemon(g, data, out):
    out.put(em(g, data, workers=3).model.dense())


def test_em_in_a_daemon_process_runs_its_groups_in_turn(grid_data):
    """A daemon (the training server's runs are) may not have children: EM there runs every group
    itself, with the numbers of the forked workers."""
    import multiprocessing

    g, _truth, recs = grid_data
    data = collect_missions(enumerate(recs), g)
    ctx = multiprocessing.get_context("fork")
    out = ctx.Queue()
    proc = ctx.Process(target=_em_in_a_daemon, args=(g, data, out), daemon=True)
    proc.start()
    got = out.get(timeout=60)
    proc.join(30)
    assert proc.exitcode == 0
    assert np.array_equal(got, em(g, data, workers=3).model.dense())


def test_em_says_which_worker_ended_and_leaves_none_behind(grid_data, monkeypatch):
    import multiprocessing
    import os

    import shared.engine.estimate as estimate

    g, _truth, recs = grid_data
    data = collect_missions(enumerate(recs), g)

    def dies(conn, data, missions, support, inherited):  # serves one pass, then its process ends
        conn.recv()
        os._exit(3)

    monkeypatch.setattr(estimate, "_serve", dies)
    with pytest.raises(estimate.EMWorkerError, match=r"worker process \d+ ended \(exit code 3\)"):
        em(g, data, workers=2)
    assert not [p for p in multiprocessing.active_children() if p.name == "mures-em"]
    with pytest.raises(ValueError, match="at least one worker"):
        em(g, data, workers=0)


def _em_for_long(g, data):
    em(g, data, workers=3, tol=-1.0, max_iter=10**7)  # never converges: runs until killed


def _alive(pid):
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return False
    return state != "Z"  # a zombie has ended


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads /proc (Linux)")
def test_em_workers_end_when_their_caller_is_killed(grid_data):
    """A kill -9 of the process running EM leaves no worker behind: each sees its pipe closed."""
    import multiprocessing
    import os
    import signal
    import time

    g, _truth, recs = grid_data
    data = collect_missions(enumerate(recs), g)
    proc = multiprocessing.get_context("fork").Process(target=_em_for_long, args=(g, data))
    proc.start()
    children: list[int] = []
    deadline = time.monotonic() + 60
    while len(children) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
        text = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text()
        children = [int(c) for c in text.split()]
    assert len(children) == 2, children
    time.sleep(0.5)  # in the middle of the passes
    os.kill(proc.pid, signal.SIGKILL)
    proc.join()
    deadline = time.monotonic() + 10
    while any(_alive(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = [c for c in children if _alive(c)]
    for c in left:
        os.kill(c, signal.SIGKILL)
    assert not left


def _impossible_record(g, mission_id="impossible"):
    """z = 1 at every step of a mission that was not captured, under a sensor with no false positives:
    no path of the target explains it (the record that broke every later retrain)."""
    from shared.core.records import make_record

    rows = [g.start, *g.closed(g.start)[1:3]]
    return make_record(
        g,
        fleet="default",
        mission_id=mission_id,
        robot_id="r1",
        nodes=rows,
        z=[1] * len(rows),
        sensor=Sensor(),
        captured=False,
        capture_time=None,
        captured_by=None,
    )


def test_a_record_no_target_path_explains_is_named_and_set_aside_and_em_stays_finite():
    from shared.core.records import unexplained

    g = builtin_graph("office")
    recs = simulated_records(g, uniform_walk(g), Sensor(), N=2, missions=60, seed=3)
    bad = _impossible_record(g)
    why = unexplained(parse_record(bad, g), g)
    assert why is not None and why.startswith("impossible: z = 1 at t=0") and "no false positives" in why
    assert all(unexplained(parse_record(r, g), g) is None for r in recs)  # simulated records are all possible
    data = collect_missions(enumerate([*recs, bad]), g, fleet="default")
    assert data.impossible == ["impossible"] and data.skipped["impossible"] == 1
    assert len(data.length) == 60 and data.used_records == len(recs)
    est = em(g, data, max_iter=200, tol=1e-5)
    assert np.isfinite(est.log_likelihood).all() and np.isfinite(est.model.b0).all()
    # records that are each possible but contradict each other (one robot sees the target where the
    # other, on the same node at the same step, does not, with a perfect sensor) are caught per mission
    twin = copy.deepcopy(recs[0])
    twin["robot_id"] = "r9"
    twin["steps"][0]["z"] = 1 - twin["steps"][0]["z"]
    assert collect_missions(enumerate([recs[0], twin]), g, fleet="default").impossible == [recs[0]["mission_id"]]


def test_the_prior_keeps_a_model_of_few_missions_cautious():
    """A Dirichlet prior (the training server's default, 1 and 1): from 3 missions, b0 rules no node
    out and Gamma_hat stays nearer the uniform walk than the maximum-likelihood estimate does."""
    g = builtin_graph("office")
    recs = simulated_records(g, lazy_walk(g, 0.5), Sensor(), N=2, missions=3, seed=4)
    data = collect_missions(enumerate(recs), g)
    ml = em(g, data, max_iter=300, tol=1e-6)
    cautious = em(g, data, max_iter=300, tol=1e-6, pseudo_count=1.0, b0_pseudo_count=1.0)
    assert (ml.model.b0 < 1e-9).sum() > 0 and (cautious.model.b0 > 1e-4).all()
    walk = uniform_walk(g)
    assert mean_row_tv(cautious.model, walk) < mean_row_tv(ml.model, walk)


def _timed_records(graph, truth, missions, seed, robots=2, ticks=80):
    """Records of robots on the mission clock: each reads when it arrives, a move taking 1-4 ticks,
    the target moving once a tick under ``truth``; eta = 0, so the first reading of the target (the
    lowest robot index within a tick) captures it and the other robots' records stop before."""
    from shared.core.records import make_record

    rng = np.random.default_rng(seed)
    gamma = truth.dense()
    out = []
    for m in range(missions):
        e = [int(rng.choice(graph.n, p=truth.b0))]
        for _ in range(ticks):
            e.append(int(rng.choice(graph.n, p=gamma[e[-1]])))
        paths = []
        for _r in range(robots):
            k, p, path = 0, graph.start, []
            while k < ticks:
                path.append((k, p))
                p, k = int(rng.choice(graph.closed(p))), k + int(rng.integers(1, 5))
            paths.append(path)
        hits = sorted((k, r) for r, path in enumerate(paths) for k, p in path if e[k] == p)
        cap = hits[0] if hits else None
        for r, path in enumerate(paths):
            keep = [(k, p) for k, p in path if cap is None or k < cap[0] or (k, r) == cap]
            if not keep:  # a teammate of a capture at t = 0 read nothing before it
                continue
            out.append(make_record(
                graph, fleet="f", mission_id=f"m{m}", robot_id=f"r{r}", nodes=[p for _k, p in keep],
                z=[int(cap is not None and (k, r) == cap) for k, _p in keep], sensor=Sensor(),
                captured=cap is not None, capture_time=len(keep) - 1 if cap else None,
                captured_by=f"r{cap[1]}" if cap else None, times=[float(k) for k, _p in keep],
            ))  # fmt: skip
    return out


def test_em_per_tick_fits_the_model_of_a_tick_from_timestamped_records():
    g = grid_graph(3, 3)
    truth = lazy_walk(g, 0.8)  # the target's move each tick (1 s)
    recs = _timed_records(g, truth, missions=1500, seed=5)
    per_tick = collect_missions(enumerate(recs), g, tick_s=1.0)
    assert per_tick.used_records == len(recs) and per_tick.length.max() > max(len(r["steps"]) for r in recs)
    tv_tick = mean_row_tv(em(g, per_tick).model, truth)
    # the same records read as steps: each reading one step after the last, however long the move took
    as_steps = collect_missions(enumerate(recs), g)
    assert as_steps.skipped["impossible"] > 0  # a target that moved several times between two readings
    tv_steps = mean_row_tv(em(g, as_steps).model, truth)
    # per tick the estimate converges to the truth (0.15 on 400 missions, 0.05 on 1500); read as steps it
    # stays biased (0.22, 0.19): a "step" lasted 1-4 ticks
    assert tv_tick < 0.1 and tv_tick < tv_steps / 2, (tv_tick, tv_steps)
    # records without times have no place on the clock
    untimed = [{**r, "steps": [{k: v for k, v in s.items() if k != "time_s"} for s in r["steps"]]} for r in recs[:4]]
    assert collect_missions(enumerate(untimed), g, tick_s=1.0).skipped == {"no-times": 4}


def test_mures_estimate_per_tick_writes_the_ticks_model(tmp_path):
    import subprocess
    import sys

    g = grid_graph(3, 3)
    (tmp_path / "g.json").write_text(json.dumps(g.to_json()))
    recs = _timed_records(g, lazy_walk(g, 0.8), missions=300, seed=2)
    (tmp_path / "e.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    cmd = [sys.executable, "-m", "shared.tools.cli", "estimate", "--graph", str(tmp_path / "g.json"),
           "--episodes", str(tmp_path / "e.jsonl"), "--out", str(tmp_path / "m.json")]  # fmt: skip
    r = subprocess.run([*cmd, "--tick", "1", "--truth", "lazy:0.8"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    model = json.loads((tmp_path / "m.json").read_text())
    assert model["tick_s"] == 1.0 and model["mean_row_tv_to_truth"] < 0.25
    r = subprocess.run([*cmd, "--tick", "1", "--method", "eq8"], capture_output=True, text=True)
    assert r.returncode == 2 and "--tick goes with --method em" in r.stderr
