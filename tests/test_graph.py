import hashlib
import json
import subprocess
import sys
from pathlib import Path

import pytest

from shared.core.graph import GraphError, builtin_graph, graph_from_dict, grid_graph, load_graph_file


def test_builtin_maps_match_the_reference_data():
    """The built-in maps against the published node and edge lists, kept apart in tests/data."""
    ref = json.loads((Path(__file__).parent / "data" / "reference_graphs.json").read_text())
    for key, n, m, start in (("office", 60, 65, 43), ("museum", 70, 93, 1)):
        g = builtin_graph(key)
        assert (g.n, g.m) == (n, m)
        assert int(g.labels[g.start]) == start
        assert sorted(int(x) for x in g.labels) == sorted(ref[key]["nodes"])
        got = sorted(sorted((int(g.labels[u]), int(g.labels[v]))) for u, v in g.edges)
        assert got == sorted(sorted(e) for e in ref[key]["edges"])


def test_graph_id_is_the_spec_formula():
    g = builtin_graph("office")
    canon = {
        "nodes": sorted(int(x) for x in g.labels),
        "edges": sorted(
            [min(int(g.labels[u]), int(g.labels[v])), max(int(g.labels[u]), int(g.labels[v]))] for u, v in g.edges
        ),
    }
    want = "sha256:" + hashlib.sha256(json.dumps(canon, separators=(",", ":")).encode()).hexdigest()
    assert g.graph_id == want
    # independent of edge orientation and listing order
    d = g.to_json()
    d["edges"] = [[v, u] for u, v in reversed(d["edges"])]
    assert graph_from_dict(d).graph_id == want


def test_closed_neighbourhoods(small_graph):
    g = small_graph
    assert [int(g.labels[j]) for j in g.closed(g.row(12))] == [12, 10, 11, 13]
    assert list(g.deg_closed) == [3, 3, 4, 3, 2]
    for p in range(g.n):  # padded table holds N[p] then repeats of p
        assert set(g.nbr[p]) == set(g.closed(p))


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"nodes": [1, 2], "edges": [[1, 1]]}, "edge #0 [1, 1] is a self-loop"),
        ({"nodes": [1, 2], "edges": [[1, 2], [2, 1]]}, "edge #1 [2, 1] duplicates"),
        ({"nodes": [1, 2], "edges": [[1, 3]]}, "names node 3"),
        ({"nodes": [1, 2, 3], "edges": [[1, 2]]}, "not connected: node(s) [3]"),
        ({"nodes": [1, -2], "edges": [[1, -2]]}, "node #1 (-2)"),
        ({"nodes": [1, 1], "edges": []}, "node 1 is listed twice"),
        ({"nodes": [1, 2], "edges": [[1, 2]], "start_node": 9}, "start_node 9"),
        ({"nodes": [1, 2.5], "edges": []}, "node #1 (2.5)"),
        ({"nodes": [], "edges": []}, "non-empty list"),
        ({"nodes": [1, 2], "edges": [[1, 2, 3]]}, "edge #0"),
        ({"nodes": [1, 2], "edges": [[1, 2]], "sensing": {"1": [7]}}, "sensing[1] names node 7"),
        ([1, 2], "expected a JSON object"),
        ({"nodes": [1, 2**64], "edges": [[1, 2**64]]}, "not an integer label in [0, 9223372036854775807]"),
    ],
)
def test_bad_graphs_name_the_problem(data, fragment):
    with pytest.raises(GraphError, match=None) as exc:
        graph_from_dict(data)
    assert fragment in str(exc.value)


def test_bad_graph_file_gives_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"nodes": [1, 2, 3], "edges": [[1, 2], [2, 2]]}))
    r = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "map", "--graph", str(bad)], capture_output=True, text=True
    )
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "Traceback" not in r.stderr
    assert "edge #1 [2, 2] is a self-loop" in r.stderr
    notjson = tmp_path / "x.json"
    notjson.write_text("{nope")
    with pytest.raises(GraphError, match="not valid JSON"):
        load_graph_file(notjson)
    with pytest.raises(GraphError, match="cannot read"):
        load_graph_file(tmp_path / "missing.json")


def test_grid_and_custom_sensing():
    g = grid_graph(3, 2)
    assert (g.n, g.m) == (6, 7)
    h = graph_from_dict({"nodes": [0, 1, 2], "edges": [[0, 1], [1, 2]], "sensing": {"0": [0, 1, 2]}})
    ptr, idx = h.detection_sets("custom")
    assert list(idx[ptr[0] : ptr[1]]) == [0, 1, 2]
    assert sorted(idx[ptr[2] : ptr[3]]) == [1, 2]  # unlisted nodes default to N[p]


def test_a_map_too_large_for_dense_arrays_is_simulated_sparse_and_refused_where_arrays_are_dense(tmp_path):
    big = {"name": "corridor", "nodes": list(range(6000)), "edges": [[i, i + 1] for i in range(5999)]}
    g = graph_from_dict(big)  # the agent's sparse filter takes it
    with pytest.raises(GraphError, match=r"6000 nodes: training, EM and the planners hold dense n x n arrays .* 5000"):
        g.closed_adjacency  # noqa: B018
    path = tmp_path / "corridor.json"
    path.write_text(json.dumps(big))

    def mures(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True)

    # the simulator and the reference searchers are sparse: they take it
    r = mures("evaluate", "--graph", str(path), "--robots", "1", "--searcher", "random", "--episodes", "2")
    assert r.returncode == 0 and "T_max = 18000" in r.stdout, r.stderr
    # training holds (n, n) arrays: refused in one line, naming the limit, before anything is written
    r = mures("train", "--graph", str(path), "--robots", "1", "--episodes", "256", "--out", str(tmp_path / "team"))
    assert r.returncode == 2 and "at most 5000" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "team").exists()
