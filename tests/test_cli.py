import json
import subprocess
import sys

import pytest

from shared.core.files import read_token
from shared.core.http import ApiClient
from shared.tools.fleetsim import wait_until


def mures(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_evaluate_json_fields():
    r = mures("evaluate", "--env", "office", "--robots", "2", "--searcher", "greedy", "--episodes", "200", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    for key in ("mean_capture_time", "ci95", "median", "censored_fraction", "false_alarms_per_episode", "episodes"):
        assert key in out
    assert out["episodes"] == 200 and out["ci95"][0] < out["mean_capture_time"] < out["ci95"][1]
    again = json.loads(mures(*r.args[3:]).stdout)
    assert again["mean_capture_time"] == out["mean_capture_time"]  # deterministic for a seed


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--robots", "0", "--searcher", "random"], "positive integer"),
        (["--robots", "2", "--searcher", "random", "--eta-fn", "0.7"], "[0, 0.5]"),
        (["--robots", "2", "--searcher", "random", "--eta-fn", "0.5", "--eta-fp", "0.5"], "uninformative"),
        (["--robots", "2", "--searcher", "astar"], "unknown searcher 'astar'"),
        (["--robots", "2", "--searcher", "random", "--target", "lazy:x"], "lazy:STAY"),
        (["--robots", "2", "--searcher", "random", "--detection", "custom"], "no 'sensing' table"),
        (["--robots", "2", "--searcher", "random", "--device", "cuda:7"], "cuda"),
    ],
)
def test_bad_arguments_exit_2_with_a_clear_error(args, fragment):
    r = mures("evaluate", "--env", "museum", *args)
    assert r.returncode == 2
    assert fragment in r.stderr and "Traceback" not in r.stderr


def test_simulate_then_estimate(tmp_path):
    eps, model = tmp_path / "eps.jsonl", tmp_path / "model.json"
    r = mures(
        "simulate",
        "--env",
        "office",
        "--robots",
        "3",
        "--missions",
        "60",
        "--target",
        "lazy:0.8",
        "--eta-fn",
        "0.1",
        "--out",
        str(eps),
    )
    assert r.returncode == 0, r.stderr
    assert len(eps.read_text().splitlines()) == 180
    r = mures("estimate", "--env", "office", "--episodes", str(eps), "--out", str(model), "--truth", "lazy:0.8")
    assert r.returncode == 0, r.stderr
    out = json.loads(model.read_text())
    assert len(out["nodes"]) == 60 and len(out["gamma"]) == 60 and len(out["b0"]) == 60
    assert out["records_used"] == 180 and out["log_likelihood"]
    # the estimate is itself a valid target model for the simulator
    r = mures(
        "evaluate",
        "--env",
        "office",
        "--robots",
        "1",
        "--searcher",
        "random",
        "--episodes",
        "50",
        "--target",
        str(model),
    )
    assert r.returncode == 0, r.stderr
    # records for another map are all skipped: nothing written, exit 2
    r = mures("estimate", "--env", "museum", "--episodes", str(eps), "--out", str(tmp_path / "m2.json"))
    assert r.returncode == 2 and "graph_id: 180" in r.stderr and not (tmp_path / "m2.json").exists()


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--zenoh-connect", "nonsense"], "not a Zenoh endpoint such as tcp/127.0.0.1:7447"),
        (["--fleet", "bad fleet!"], "fleet 'bad fleet!' must be"),
        (["--eta-fn", "0.9"], "[0, 0.5]"),
    ],
)
def test_world_refuses_bad_arguments_clearly(args, fragment):
    r = mures("world", "--env", "office", *args)
    assert r.returncode == 2 and fragment in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize(
    "args, fragment",
    [
        ([], "give --missions N, or --serve"),
        (["--missions", "0"], "0 only with --serve"),
        (["--missions", "-1"], ">= 0"),
    ],
)
def test_fleet_sim_needs_missions_or_serve(args, fragment):
    r = mures("fleet-sim", "--env", "office", "--robots", "2", *args)
    assert r.returncode == 2 and fragment in r.stderr and "Traceback" not in r.stderr


@pytest.mark.slow
def test_fleet_sim_serve_keeps_the_console_up_until_sigterm(tmp_path):
    """`mures fleet-sim --serve`: the fleet stays up and says where the console is; SIGTERM ends it
    cleanly with the usual summary, which counts the missions an operator flew meanwhile."""
    import signal
    import time
    import urllib.request

    cmd = ["fleet-sim", "--env", "office", "--robots", "2", "--missions", "1", "--serve", "--workdir", str(tmp_path)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "shared.tools.cli", *cmd, "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = ""
        deadline = time.monotonic() + 120
        while "Console:" not in line and time.monotonic() < deadline:
            line = proc.stderr.readline()
        assert "Console:" in line, line
        url = line.split("Console: ")[1].split(" ;")[0]
        assert str(tmp_path / "server" / "operator.token") in line
        with urllib.request.urlopen(url) as r:
            assert r.status == 200 and "MuRES fleet" in r.read().decode()
        api = ApiClient(url.rstrip("/"), read_token(tmp_path / "server" / "operator.token"))
        m = api.post("/api/v1/missions", {"seed": 7, "max_steps": 30})  # as the console's Missions page does
        wait_until(lambda: api.get(f"/api/v1/missions/{m['id']}")["status"] == "completed", 60, "the mission")
        proc.send_signal(signal.SIGTERM)
        out, _err = proc.communicate(timeout=60)
        summary = json.loads(out)
        assert proc.returncode == 0 and summary["missions"] == 2, summary
        assert m["id"] in [r["mission_id"] for r in summary["results"]] and summary["mean_capture_time"] > 0
    finally:
        if proc.poll() is None:
            proc.kill()


def test_a_graph_of_one_node_is_refused_in_one_line_by_every_command_that_searches(tmp_path):
    """A building imported as a single region gives a graph of one node: valid as a file, but there
    is nothing to search between, so train, evaluate and the server say so instead of failing deep
    inside (train used to end in torch.cat() on an empty list)."""
    one = tmp_path / "one.json"
    one.write_text(json.dumps({"name": "ONE", "nodes": [0], "edges": [], "start_node": 0}))
    for args in (
        ["train", "--graph", str(one), "--robots", "2", "--episodes", "10", "--out", str(tmp_path / "t")],
        ["evaluate", "--graph", str(one), "--robots", "2", "--searcher", "random", "--episodes", "10"],
    ):
        r = mures(*args)
        assert r.returncode == 2 and r.stderr.strip().endswith("cuts a building into more)"), r.stderr
        assert "nothing to search between" in r.stderr and "Traceback" not in r.stderr
    r = subprocess.run(
        [sys.executable, "-m", "training_server", "--graph", str(one), "--data-dir", str(tmp_path / "data")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode == 2 and "nothing to search between" in r.stderr and not (tmp_path / "data").exists()


def test_fleet_sim_passes_the_map_image_to_its_server_which_checks_it(tmp_path):
    """fleet-sim --graph G --map-image MAP.yaml: the server draws that map under the graph, and
    refuses, in one line, a map the graph was not imported from (before any agent starts)."""
    from pathlib import Path

    nav2 = Path(__file__).resolve().parents[1] / "examples" / "maps" / "nav2"
    graph = tmp_path / "depot.json"
    assert mures("map", "import", str(nav2 / "depot.yaml"), "--out", str(graph), "--quiet").returncode == 0
    r = mures("fleet-sim", "--graph", str(graph), "--map-image", str(nav2 / "warehouse.yaml"), "--robots", "2",
              "--missions", "1", "--workdir", str(tmp_path / "w"))  # fmt: skip
    assert r.returncode == 2 and "not the one this graph was imported from" in r.stderr, r.stderr
    r = mures(
        "fleet-sim", "--env", "office", "--map-image", str(nav2 / "depot.yaml"), "--robots", "2", "--missions", "1"
    )
    assert r.returncode == 2 and "--map-image goes with --graph" in r.stderr
