"""Retraining a fleet with any of the project's methods over HTTP (training_server/methods.py):
each method's team published and flown by robot-agent processes, a version holding a team per
team size and the robots switching to the team for those left, `algorithm: "best"` with its
table of candidates, and a run that resumes from its checkpoint after a server restart."""

from __future__ import annotations

import json
import re
import signal
from pathlib import Path

import numpy as np
import pytest
import zenoh
from fleet_checks import long_mission, walk_record

from shared.core.files import read_token
from shared.core.graph import builtin_graph
from shared.core.http import ApiClient, ApiError
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import read_snapshot
from shared.core.wire import send_episode, zenoh_config
from shared.tools.fleetsim import launch, reap, start_server, wait_until
from training_server.jobs import TrainingParams

pytestmark = pytest.mark.slow  # a server, the world and three agent processes; training runs

ROBOTS = ["r1", "r2", "r3"]
TINY = {"episodes": 256, "gate": False, "gate_episodes": 20, "canary_pairs": 0, "team_searcher": "none"}


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    graph = builtin_graph("office")
    f = launch(
        graph, ["--env", "office"], uniform_walk(graph), Sensor(), 3, tmp_path_factory.mktemp("fleet"), step_timeout=3.0
    )
    for seed in range(20):
        f.fly(ROBOTS, seed=seed, max_steps=40)
    yield f
    f.close()


def _finished(api, run_id, timeout=600):
    return wait_until(
        lambda: (r := api.get(f"/api/v1/training-runs/{run_id}"))["status"] not in ("queued", "running") and r,
        timeout,
        f"training run {run_id}",
        every=0.2,
    )


def _snapshot(fleet, version):
    return read_snapshot(fleet.workdir / "server" / "policies" / f"v{version}" / "snapshot", fleet.graph)


@pytest.mark.parametrize("method", ["pg", "maddpg", "masac", "facmac", "mambpo", "mappo"])
def test_each_methods_team_is_published_and_flown_by_the_robots(fleet, method):
    run = fleet.api.post("/api/v1/training-runs", {"algorithm": method, "min_missions": 1, "seed": 3, **TINY})
    done = _finished(fleet.api, run["id"])
    assert done["status"] == "succeeded", done.get("error")
    assert done["metrics"]["chosen"] == method and done["metrics"]["train"]["episodes"] >= 256
    meta = _snapshot(fleet, done["version"]).meta
    assert meta["algorithm"] == ("cepg" if method == "pg" else method)
    assert meta["beta"] == ([1.0] * 3 if method == "pg" else [])
    m = fleet.fly(ROBOTS, seed=99, max_steps=40)
    assert m["outcome"]["policy_versions"] == [done["version"]]
    for robot in ROBOTS:
        rec = fleet.api.get(f"/api/v1/episodes/{robot}/{m['id']}")
        assert rec["policy_version"] == done["version"] and len(rec["steps"]) >= 2


def test_a_version_holds_a_team_per_team_size_and_robots_fly_the_one_for_their_number(fleet):
    run = fleet.api.post(
        "/api/v1/training-runs", {"algorithm": "cepg", "team_sizes": [1, 2], "min_missions": 1, **TINY}
    )
    done = _finished(fleet.api, run["id"])
    assert done["status"] == "succeeded", done
    assert done["metrics"]["team_sizes"] == [1, 2, 3]
    assert [(t["method"], t["robots"]) for t in done["metrics"]["teams"]] == [("cepg", 3), ("cepg", 1), ("cepg", 2)]
    snap = _snapshot(fleet, done["version"])
    assert snap.team_sizes == [1, 2, 3] and snap.team_for(2).robots == 2
    two = fleet.fly(["r1", "r3"], seed=5, max_steps=40)
    for robot in ("r1", "r3"):
        assert fleet.api.get(f"/api/v1/episodes/{robot}/{two['id']}")["coordination"]["flown_for"] == 2
    # a teammate killed mid-mission: its liveliness goes, and the others fly the team for two if
    # the run measured that switching to it captures sooner
    fleet.world.step_delay = 0.05
    try:
        mid = long_mission(fleet, ROBOTS, 21, steps=3, max_steps=80)
        fleet.stop_agent("r2", signal.SIGKILL)
        wait_until(
            lambda: set(fleet.api.get(f"/api/v1/missions/{mid}")["episodes_received"]) == {"r1", "r3"},
            60,
            "r1 and r3 to report",
        )
    finally:
        fleet.world.step_delay = 0.0
    switching = done["metrics"]["switching"]  # measured: whether robots left switch to the team for 2
    assert set(switching["by_size"]) == {"1", "2"} and set(switching["switch_to"]) <= {1, 2}
    assert snap.meta.get("switch_to") == switching["switch_to"]
    for robot in ("r1", "r3"):
        c = fleet.api.get(f"/api/v1/episodes/{robot}/{mid}")["coordination"]
        assert c["teammates_dropped"] == 1 and c["flown_for"] == (2 if 2 in switching["switch_to"] else 3), c
    fleet.start_agent("r2")
    wait_until(lambda: "r2" in fleet.online(), 60, "r2 back online")


def test_best_trains_the_candidates_and_publishes_the_one_that_captures_soonest(fleet):
    params = {"algorithm": "best", "candidates": ["cepg", "masac", "mappo"], "min_missions": 1, "seed": 4, **TINY}
    done = _finished(fleet.api, fleet.api.post("/api/v1/training-runs", {**params, "gate_episodes": 60})["id"])
    assert done["status"] == "succeeded", done
    table = {row["method"]: row for row in done["metrics"]["candidates"]}
    assert list(table) == ["current", "cepg", "masac", "mappo"]
    means = {m: table[m]["mean_capture_time"] for m in ("cepg", "masac", "mappo")}
    assert done["metrics"]["chosen"] == min(means, key=means.__getitem__)
    for m in means:  # on the same episodes as the current version: a paired difference
        assert table[m]["episodes"] == table["current"]["episodes"] == 60
        assert table[m]["paired_ci95"] >= 0 and len(table[m]["ci95"]) == 2
    assert done["metrics"]["gate"]["new"] == {
        k: table[done["metrics"]["chosen"]][k] for k in done["metrics"]["gate"]["new"]
    }


@pytest.mark.parametrize(
    ("body", "names"),
    [
        ({"algorithm": "sac"}, "algorithm"),
        ({"algorithm": "best", "candidates": ["pg", "pg"]}, "must not repeat"),
        ({"algorithm": "best", "candidates": []}, "candidates"),
        ({"hyperparameters": {"sac": {"lr": 0.1}}}, "hyperparameters"),
        ({"team_sizes": [0]}, "team_sizes"),
        ({"budget_fraction": 0}, "budget_fraction"),
        ({"speed": 0}, "speed"),
    ],
)
def test_bad_training_parameters_are_refused_naming_the_problem(body, names):
    with pytest.raises(ValueError, match=names):
        TrainingParams.model_validate(body)


def test_a_run_on_travel_times_takes_its_speed_or_the_current_versions_and_names_a_foreign_tick():
    from training_server.jobs import run_speed

    assert run_speed(TrainingParams.model_validate({}), None) is None
    assert run_speed(TrainingParams.model_validate({}), (0.4, 1.0)) == 0.4  # the current version's speed
    assert run_speed(TrainingParams.model_validate({"speed": 0.7}), (0.4, 1.0)) == 0.7
    for method in ("mappo", "mambpo"):  # every method trains on travel times
        assert run_speed(TrainingParams.model_validate({"speed": 0.5, "algorithm": method}), None) == 0.5
    best = TrainingParams.model_validate({"algorithm": "best", "candidates": ["pg", "mambpo"]})
    assert run_speed(best, (0.5, 1.0)) == 0.5
    with pytest.raises(ValueError, match=re.escape("ticks of 2 s")):
        run_speed(TrainingParams.model_validate({}), (0.5, 2.0))


def test_a_retraining_of_a_marl_baseline_on_travel_times_trains_it_on_the_runs_model_per_tick(tmp_path):
    """What the server's run does for ``{"algorithm": "mappo", "speed": ...}``: the team trains on
    the map's travel times under the run's EM model as fitted (per tick, not made a tick's worth
    again), and its snapshot says it was trained on the clock."""
    import dataclasses

    from shared.core.clock import TravelTimes
    from shared.learning.team_snapshot import load_snapshot
    from training_server.methods import RunFolder, train_team

    g = builtin_graph("office")
    g = dataclasses.replace(g, edge_lengths=np.linspace(1.0, 3.0, g.m))
    per_tick = TravelTimes.of(g, 0.5).model(uniform_walk(g))  # what the run's EM fits from timed records
    params = TrainingParams.model_validate(
        {"algorithm": "mappo", "hyperparameters": {"mappo": {"envs": 16, "steps": 8}}}
    )
    team = train_team("mappo", 2, 64, (g, per_tick, Sensor()), params, None, RunFolder(tmp_path), lambda _: None,
                      lambda: False, speed=0.5)  # fmt: skip
    assert team is not None
    snap = load_snapshot(tmp_path / "teams" / "mappo-2", g)
    assert snap.clock == (0.5, 1.0) and snap.model.kind == per_tick.kind  # not made a tick's worth twice
    assert np.allclose(snap.model.prob, per_tick.prob, atol=1e-6)  # as stored
    assert snap.meta["summary"]["clock"]["unit"] == "ticks"


def test_an_unknown_hyperparameter_fails_the_run_at_once_naming_it(fleet):
    body = {"algorithm": "masac", "hyperparameters": {"masac": {"learning_speed": 2}}, "min_missions": 1, **TINY}
    done = _finished(fleet.api, fleet.api.post("/api/v1/training-runs", body)["id"], timeout=60)
    assert done["status"] == "failed" and "hyperparameters.masac: 'learning_speed=2'" in done["error"], done


def _records(endpoint: str, graph, missions: int) -> None:
    rng = np.random.default_rng(0)
    with zenoh.open(zenoh_config("client", connect=[endpoint])) as s:
        for k in range(missions):
            rec = walk_record(graph, f"m{k}", 20, rng)
            assert send_episode(s, "default", "r1", f"m{k}", json.dumps(rec).encode())[0]


def test_a_run_goes_on_from_its_checkpoint_after_a_server_restart_and_a_cancelled_one_stays_cancelled(tmp_path):
    graph = builtin_graph("office")
    data, logs = tmp_path / "data", tmp_path / "logs"
    logs.mkdir()
    proc, base, endpoint = start_server(["--env", "office"], data, 2, Sensor(), logs)
    try:
        _records(endpoint, graph, 60)
        api = ApiClient(base, read_token(data / "operator.token"))
        body = {"algorithm": "mappo", "episodes": 6000, "seed": 2, **{k: v for k, v in TINY.items() if k != "episodes"}}
        run = api.post("/api/v1/training-runs", body)
        progress = wait_until(
            lambda: (
                (p := api.get(f"/api/v1/training-runs/{run['id']}")["progress"] or {}).get("episodes", 0) >= 1000 and p
            ),
            300,
            "the run to train 1000 episodes",
            every=0.2,
        )
        assert progress["method"] == "mappo" and progress["robots"] == 2 and progress["total"] == 6000
        assert progress["eta_s"] >= 0 and len(progress["curve"]) >= 1  # the team's time left, its learning curve
        proc.send_signal(signal.SIGTERM)  # the server stops: the run pauses, its checkpoint saved
        assert reap(proc, 90) == 0
        checkpoint = data / "runs" / run["id"] / "checkpoints" / "mappo-2" / "state.pt"
        assert checkpoint.is_file()
        proc, base, endpoint = start_server(["--env", "office"], data, 2, Sensor(), logs)
        api = ApiClient(base, read_token(data / "operator.token"))
        done = _finished(api, run["id"])
        assert done["status"] == "succeeded", done
        team = done["metrics"]["teams"][0]
        assert team["episodes"] >= 6000 and team["resumed"][0]["episodes"] >= 1000, team
        # the run's folder goes with its end (removed just after the run is marked succeeded)
        wait_until(lambda: not (data / "runs" / run["id"]).exists(), 30, "the run's folder to go")
        # cancelled: it stops, and a restart keeps it cancelled
        run = api.post("/api/v1/training-runs", {**body, "episodes": 1_000_000})
        wait_until(lambda: api.get(f"/api/v1/training-runs/{run['id']}")["status"] == "running", 60, "running")
        api.post(f"/api/v1/training-runs/{run['id']}/cancel")
        assert _finished(api, run["id"], 120)["status"] == "cancelled"
        with pytest.raises(ApiError):
            api.post(f"/api/v1/training-runs/{run['id']}/cancel")
        assert not (data / "runs" / run["id"]).exists()
    finally:
        proc.send_signal(signal.SIGTERM)
        reap(proc, 90)
    assert Path(logs / "server.log").read_text().count("resumed from version") == 1
