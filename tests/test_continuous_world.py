"""The continuous world (shared/world/continuous.py): paths along free space, what a robot sees
through walls and doors, and missions whose capture times are in seconds, reproducible by seed."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from test_floorplan import two_rooms_floor

from shared.core.graph import graph_from_dict
from shared.core.models import Sensor
from shared.floorplan.graph_file import graph_dict
from shared.floorplan.occupancy import read_map
from shared.floorplan.rooms import segment
from shared.tools.fleetsim import fleet_mission_seed
from shared.world.continuous import building, fly


def _two_rooms(tmp_path):
    """Two 6 x 5.9 m rooms side by side, a 1.2 m door at the top of the wall between them; the
    graph a node a room, as `mures map import --max-region-m 10` makes it."""
    Image.fromarray(two_rooms_floor()).save(tmp_path / "m.pgm")
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\n")
    grid = read_map(tmp_path / "m.yaml")
    data = graph_dict(grid, segment(grid, max_region_m=10), "TWO", {})
    return grid, graph_from_dict(json.loads(json.dumps(data)))


def test_paths_follow_the_free_space_and_walls_block_the_view(tmp_path):
    grid, graph = _two_rooms(tmp_path)
    world = building(grid, graph, sensor_range_m=20.0)
    (u, v) = graph.edges[0].tolist()
    there, back = world.edge_of[u, v], world.edge_of[v, u]
    assert world.length_m[there] == pytest.approx(world.length_m[back])
    assert world.length_m[there] == pytest.approx(graph.edge_lengths[0], rel=0.05)  # the import's length
    assert world.edge_end[there] == v and world.edge_end[back] == u
    path = world.paths[there]
    assert grid.free[path[:, 0], path[:, 1]].all() and (path[-1] == world.node_px[v]).all()
    assert path[:, 0].min() <= 12  # through the door, at the top
    # a robot in one room sees its own room's far corner, and nothing of the other room behind the wall
    left = int(np.argmin(world.node_px[:, 1]))
    assert world.sees(np.array([left, left]), np.array([[55, 5], [55, 100]])).tolist() == [True, False]


def test_missions_capture_in_seconds_and_repeat_by_seed(tmp_path):
    grid, graph = _two_rooms(tmp_path)
    world = building(grid, graph, sensor_range_m=20.0)
    a = fly(world, "random", robots=2, missions=50, seed=3)
    b = fly(world, "random", robots=2, missions=50, seed=3)
    assert np.array_equal(a.capture_s, b.capture_s) and a.captured.all()
    # a robot that sees its whole room captures a target there at once (t = 0), and one in the
    # other room only once one of them or the target has gone through the door
    assert (a.capture_s == 0).any() and (a.capture_s > 0).any()
    start_room = world.sees(np.array([graph.start]), world.node_px[[1 - graph.start]])[0]
    assert not start_room  # the other room's pose is out of sight from the start
    team = fly(world, "fhpe-sa", robots=2, missions=20, seed=3)  # the plan on the clock, every observation at once
    assert team.captured.all() and np.array_equal(team.capture_s, fly(world, "fhpe-sa", 2, 20, seed=3).capture_s)
    blind = fly(world, "greedy", robots=2, missions=20, sensor=Sensor(eta_fn=0.5), seed=3)
    assert blind.decisions > 0 and (blind.capture_s >= 0).all()
    with pytest.raises(ValueError, match="random, greedy, sweep"):
        fly(world, "cepg", robots=2, missions=1)


def test_mures_evaluate_flies_a_searcher_in_the_continuous_world(tmp_path):
    """`mures evaluate --graph G.json --world MAP.yaml ... --json` prints the capture time in
    seconds with its CI; a map that is not the graph's, a searcher that cannot fly there yet and a
    graph given without its map are refused in one line."""
    import subprocess
    import sys

    def mures(*args):
        return subprocess.run(
            [sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True, timeout=300
        )

    _two_rooms(tmp_path)
    graph = tmp_path / "g.json"
    assert mures("map", "import", str(tmp_path / "m.yaml"), "--out", str(graph), "--max-region-m", "10").returncode == 0
    common = ["evaluate", "--graph", str(graph), "--world", str(tmp_path / "m.yaml"), "--robots", "2"]
    r = mures(*common, "--searcher", "greedy", "--episodes", "40", "--seed", "2", "--range", "20", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["episodes"] == 40 and out["captured_fraction"] == 1.0 and out["continuous"]["sensor_range_m"] == 20
    assert out["mean_capture_time_s"] >= 0 and out["ci95_halfwidth_s"] >= 0
    again = mures(*common, "--searcher", "greedy", "--episodes", "40", "--seed", "2", "--range", "20", "--json")
    assert json.loads(again.stdout)["mean_capture_time_s"] == out["mean_capture_time_s"]  # the same seed, the same
    other = tmp_path / "other"
    other.mkdir()
    floor = np.asarray(Image.open(tmp_path / "m.pgm")).copy()
    floor[30, 30] = 0
    Image.fromarray(floor).save(other / "m.pgm")
    (other / "m.yaml").write_text((tmp_path / "m.yaml").read_text())
    for args, words in (
        (["--world", str(other / "m.yaml"), "--searcher", "random"], "was not imported from"),
        (["--searcher", "fhpe"], "flies random, greedy, sweep, fhpe-sa (the trained policies fly in it as agents"),
        (["--searcher", "random", "--speed", "0"], "a number above 0"),
    ):
        r = mures(*common, *args, "--episodes", "5")
        assert r.returncode == 2 and words in r.stderr and "Traceback" not in r.stderr, r.stderr
    r = mures(
        "evaluate", "--env", "office", "--world", str(tmp_path / "m.yaml"), "--robots", "2", "--searcher", "random"
    )
    assert r.returncode == 2 and "--world goes with --graph" in r.stderr


def test_the_sweep_covers_every_node_with_one_arc_a_robot():
    """The sweep's tour visits every node once; its arcs, one a robot, cover the tour; each robot
    moves along shortest paths towards its arc's next node."""
    from shared.world.continuous import _arcs, _nearest_tour, _two_opt

    rng = np.random.default_rng(0)
    pts = rng.random((12, 2)) * 10
    dist = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    tour = _two_opt(_nearest_tour(dist, 0), dist)
    assert sorted(tour) == list(range(12)) and tour[0] == 0
    length = lambda t: sum(dist[t[k], t[(k + 1) % len(t)]] for k in range(len(t)))  # noqa: E731
    assert length(tour) <= length(_nearest_tour(dist, 0)) + 1e-9
    for robots in (1, 3, 5):
        arcs = _arcs(tour, dist, robots)
        assert len(arcs) == robots and set().union(*map(set, arcs)) == set(range(12))


def test_sweeping_robots_capture_in_the_two_rooms(tmp_path):
    grid, graph = _two_rooms(tmp_path)
    world = building(grid, graph, sensor_range_m=3.0)
    f = fly(world, "sweep", robots=1, missions=30, seed=4)
    assert f.captured.all() and f.decisions > 0


def test_missions_flown_by_their_own_seeds_meet_the_same_target_in_any_batch(tmp_path):
    """fly(mission_seeds=...): each mission's target walks by its seed's generator, as in the world
    served to robot agents, so a mission is the same whichever missions fly beside it, and a
    searcher's flight is paired with a fleet's on those seeds."""
    grid, graph = _two_rooms(tmp_path)
    world = building(grid, graph, sensor_range_m=3.0)
    seeds = [fleet_mission_seed(7, k) for k in range(12)]
    batch = fly(world, "sweep", robots=1, missions=12, seed=4, mission_seeds=seeds)
    alone = [fly(world, "sweep", robots=1, missions=1, seed=99, mission_seeds=[s]).capture_s[0] for s in seeds[-3:]]
    assert batch.captured.all() and batch.capture_s[-3:].tolist() == alone
    assert len(set(batch.capture_s.tolist())) > 3  # the seeds give different missions
    shared = fly(world, "sweep", robots=1, missions=12, seed=4)  # one generator for the batch: other missions
    assert shared.capture_s.tolist() != batch.capture_s.tolist()
    with pytest.raises(ValueError, match="one mission seed a mission"):
        fly(world, "sweep", robots=1, missions=2, mission_seeds=[1])


def test_map_import_writes_what_each_nodes_robot_sees_as_the_graphs_sensing_table(tmp_path):
    from test_floorplan import NAV2, mures

    from shared.core.graph import load_graph_file

    Image.fromarray(two_rooms_floor()).save(tmp_path / "m.pgm")
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\n")
    r = mures("map", "import", str(tmp_path / "m.yaml"), "--out", str(tmp_path / "g.json"), "--max-region-m", "10",
              "--sensor-range", "20")  # fmt: skip
    assert r.returncode == 0, r.stderr
    two = load_graph_file(tmp_path / "g.json")
    assert two.n == 2 and two.detection_sets("custom")[1].tolist() == [0, 1]  # each sees itself, not through the wall
    assert "sees 1.0 nodes' poses on average" in r.stderr
    r = mures("map", "import", str(NAV2 / "depot.yaml"), "--out", str(tmp_path / "d.json"), "--sensor-range", "4")
    depot = load_graph_file(tmp_path / "d.json")
    world = building(read_map(NAV2 / "depot.yaml"), depot, 4.0)
    ptr, idx = depot.detection_sets("custom")
    for p in range(depot.n):  # D(p): the nodes whose pose the continuous world's robot on p sees
        seen = idx[ptr[p] : ptr[p + 1]]
        assert p in seen
        assert world.sees(np.full(depot.n, p), world.node_px).nonzero()[0].tolist() == sorted(seen.tolist())
    assert max(ptr[1:] - ptr[:-1]) > 1  # some robot sees a neighbouring area


def test_a_lazy_target_or_a_model_files_target_walks_its_model_in_continuous_time(tmp_path):
    """After each dwell the target draws its next node from the model's row: a lazy walk that
    always stays never leaves, a model file's b0 says where it starts; the uniform walk keeps its
    rule (a neighbour after each dwell). `mures evaluate --world --target lazy:STAY` flies it."""
    import dataclasses
    import subprocess
    import sys

    from shared.core.models import lazy_walk
    from shared.world.continuous import Targets

    grid, graph = _two_rooms(tmp_path)
    world = building(grid, graph, sensor_range_m=4.0)
    rng = np.random.default_rng(0)
    still = dataclasses.replace(lazy_walk(graph, 1.0), b0=np.eye(graph.n)[1])
    targets = Targets.start(world, 5, rng, 2.0, still)
    assert targets.at.tolist() == [1] * 5
    for _ in range(600):  # a minute of dwells, each drawing its own node again
        targets.advance(world, 0.1, np.ones(5, dtype=bool), rng, 0.5, 2.0, still)
    assert targets.at.tolist() == [1] * 5 and (targets.edge == -1).all()
    walking, set_off = Targets.start(world, 5, rng, 2.0), np.zeros(5, dtype=bool)
    for _ in range(600):
        walking.advance(world, 0.1, np.ones(5, dtype=bool), rng, 0.5, 2.0)
        set_off |= walking.edge >= 0
    assert set_off.all()  # the uniform walk sets off after every dwell
    graph_file = tmp_path / "g.json"
    mures = [sys.executable, "-m", "shared.tools.cli"]
    made = subprocess.run([*mures, "map", "import", str(tmp_path / "m.yaml"), "--out", str(graph_file),
                           "--max-region-m", "10"], capture_output=True, text=True)  # fmt: skip
    assert made.returncode == 0, made.stderr
    r = subprocess.run([*mures, "evaluate", "--graph", str(graph_file), "--world", str(tmp_path / "m.yaml"),
                        "--robots", "2", "--searcher", "fhpe-sa", "--episodes", "20", "--target", "lazy:0.5",
                        "--json"], capture_output=True, text=True)  # fmt: skip
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["continuous"]["target"] == "lazy-walk:0.5" and out["captured_fraction"] == 1.0


def test_hold_ups_make_the_batched_missions_later(tmp_path):
    grid, graph = _two_rooms(tmp_path)
    world = building(grid, graph, sensor_range_m=4.0)
    free = fly(world, "sweep", 1, 200, seed=3)
    held = fly(world, "sweep", 1, 200, seed=3, stop_prob=1.0, stop_s=60.0)  # every move held up a minute
    assert free.captured.all() and held.captured.all()
    assert held.capture_s.mean() > free.capture_s.mean() + 20.0, (held.capture_s.mean(), free.capture_s.mean())


def test_a_graph_with_a_sensing_table_makes_it_the_default_d_of_p(tmp_path):
    """A graph imported with --sensor-range: evaluation, training and the server's first version
    take its sensing table as D(p) unless --detection says otherwise; a graph without one keeps {p}."""
    from fleet_checks import stop_processes
    from test_floorplan import mures

    from shared.core.files import read_token
    from shared.core.http import ApiClient
    from shared.tools.fleetsim import start_server

    Image.fromarray(two_rooms_floor()).save(tmp_path / "m.pgm")
    (tmp_path / "m.yaml").write_text("image: m.pgm\nresolution: 0.1\norigin: [0.0, 0.0, 0.0]\n")
    for name, extra in (("seen.json", ["--sensor-range", "20"]), ("plain.json", [])):
        r = mures("map", "import", str(tmp_path / "m.yaml"), "--out", str(tmp_path / name), "--max-region-m", "10",
                  *extra)  # fmt: skip
        assert r.returncode == 0, r.stderr
    ev = ["evaluate", "--robots", "2", "--searcher", "greedy", "--episodes", "5", "--json"]
    for name, flags, detection in (("seen.json", [], "custom"), ("seen.json", ["--detection", "node"], "node"),
                                   ("plain.json", [], "node")):  # fmt: skip
        r = mures(*ev, "--graph", str(tmp_path / name), *flags)
        assert r.returncode == 0 and json.loads(r.stdout)["sensor"]["detection"] == detection, r.stderr
    r = mures("train", "--graph", str(tmp_path / "seen.json"), "--robots", "2", "--episodes", "256", "--out",
              str(tmp_path / "team"), "--quiet")  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "team" / "policy.json").read_text())["sensor"]["detection"] == "custom"
    logs = tmp_path / "logs"
    logs.mkdir()
    proc, base, _ = start_server(["--graph", str(tmp_path / "seen.json")], tmp_path / "data", 2, None, logs)
    try:
        api = ApiClient(base, read_token(tmp_path / "data" / "operator.token"))
        assert api.get("/api/v1/policies/current")["meta"]["sensor"]["detection"] == "custom"
    finally:
        stop_processes(proc)
