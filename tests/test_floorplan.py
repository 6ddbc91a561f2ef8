"""`mures map import`: a ROS occupancy-grid map turned into the fleet's graph of rooms. Nav2's maps
and generated office floors segment into a connected graph whose every node stands on its own
region's free space; the reader follows map_server's modes; every bad input ends with one line
and exit status 2, writing nothing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from shared.core.graph import load_graph_file
from shared.floorplan.floors import office_floor, segmentation_scores
from shared.floorplan.occupancy import MapError, read_map
from shared.floorplan.rooms import segment

NAV2 = Path(__file__).resolve().parents[1] / "examples" / "maps" / "nav2"


def mures(*args):
    return subprocess.run([sys.executable, "-m", "shared.tools.cli", *args], capture_output=True, text=True)


def test_nav2_depot_imports_as_a_connected_graph_with_its_regions_and_preview(tmp_path):
    out, regions, preview = tmp_path / "depot.json", tmp_path / "regions.png", tmp_path / "preview.png"
    r = mures("map", "import", str(NAV2 / "depot.yaml"), "--out", str(out), "--regions", str(regions),
              "--preview", str(preview))  # fmt: skip
    assert r.returncode == 0, r.stderr
    graph = load_graph_file(out)  # validated: connected, edges between its nodes
    data = json.loads(out.read_text())
    assert data["source"]["map"] == "depot.yaml" and data["source"]["parameters"]["max_region_m"] == 8.0
    assert f"{graph.n} nodes" in r.stdout and graph.graph_id in r.stdout
    labels = np.asarray(Image.open(regions))
    grid = read_map(NAV2 / "depot.yaml")
    assert labels.dtype == np.uint16 and labels.shape == grid.shape and labels.max() == graph.n
    assert not (labels[~grid.free] > 0).any()  # regions on free pixels only
    for k in range(graph.n):  # every node's position is a free pixel of its own region
        x, y = data["positions"][str(k)]
        row, col = grid.to_pixel(x, y)
        assert labels[row, col] == k + 1
    assert Image.open(preview).size[0] >= grid.shape[1]
    # the graph flies: a search on it, with the imported file as --graph
    r = mures("evaluate", "--graph", str(out), "--robots", "2", "--searcher", "greedy", "--episodes", "20", "--json")
    assert r.returncode == 0, r.stderr and json.loads(r.stdout)["episodes"] == 20


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_generated_office_floors_segment_into_their_rooms(tmp_path, seed):
    floor = office_floor(seed)
    grid = read_map(floor.write(tmp_path, f"floor-{seed}"))
    regions = segment(grid)
    recall, precision = segmentation_scores(floor.rooms, regions.rooms)
    assert recall >= 0.85 and precision >= 0.92, (recall, precision)
    assert regions.labels.max() >= floor.rooms.max()  # areas: at least a node per room
    # every node reachable: the edges join all the regions kept
    seen, todo = {regions.start}, [regions.start]
    adjacency = {k: set() for k in range(int(regions.labels.max()))}
    for i, j, width in regions.edges:
        assert width >= 0.6
        adjacency[i].add(j)
        adjacency[j].add(i)
    while todo:
        for j in adjacency[todo.pop()] - seen:
            seen.add(j)
            todo.append(j)
    assert len(seen) == regions.labels.max()


def two_rooms_floor() -> np.ndarray:
    """(62, 122) map_saver grey at 0.1 m a pixel: two 6 x 5.9 m rooms side by side, walled, joined
    by a 1.2 m door at the top of the wall between them."""
    floor = np.full((62, 122), 0, dtype=np.uint8)
    floor[1:61, 1:60] = 254
    floor[1:61, 62:121] = 254
    floor[1:13, 60:62] = 254  # the door
    return floor


def _write(tmp_path, pixels, **yaml_extra):
    Image.fromarray(np.asarray(pixels, dtype=np.uint8)).save(tmp_path / "m.pgm")
    settings = {"image": "m.pgm", "resolution": 0.1, "origin": [-1.0, -2.0, 0.0], "negate": 0,
                "occupied_thresh": 0.65, "free_thresh": 0.196, **yaml_extra}  # fmt: skip
    (tmp_path / "m.yaml").write_text("\n".join(f"{k}: {json.dumps(v)}" for k, v in settings.items()) + "\n")
    return tmp_path / "m.yaml"


def test_the_reader_follows_map_servers_modes_and_frame(tmp_path):
    row = [[0, 50, 205, 254, 255]]
    grid = read_map(_write(tmp_path, row))
    assert grid.free.tolist() == [[False, False, False, True, True]]
    assert grid.occupied.tolist() == [[True, True, False, False, False]]
    neg = read_map(_write(tmp_path, row, negate=1))  # p = v / 255
    assert neg.free.tolist() == [[True, False, False, False, False]] and neg.occupied[0, 3:].all()
    raw = read_map(_write(tmp_path, [[0, 10, 50, 100, 101]], mode="raw"))  # occupancy in percent
    assert raw.free.tolist() == [[True, True, False, False, False]]
    assert raw.occupied.tolist() == [[False, False, False, True, False]]
    # trinary: map_saver's unknown grey stays unknown even under a free_thresh of 0.25
    assert not read_map(_write(tmp_path, row, free_thresh=0.25)).free[0, 2]
    assert read_map(_write(tmp_path, row, free_thresh=0.25, mode="scale")).free[0, 2]
    # the map frame: the origin is the lower-left pixel's corner; row 0 is the top row
    grid = read_map(_write(tmp_path, [[254] * 5] * 3))
    assert grid.to_map_frame(2, 0) == pytest.approx((-0.95, -1.95))
    assert grid.to_pixel(-0.95, -1.95) == (2, 0) and grid.to_pixel(-0.55, -1.85) == (1, 4)


def test_bad_maps_end_with_one_line_and_exit_2_writing_nothing(tmp_path):
    cases = {}
    cases["no such map file"] = tmp_path / "absent.yaml"
    (tmp_path / "bad.yaml").write_text("image: [unclosed\n")
    cases["not valid YAML"] = tmp_path / "bad.yaml"
    (tmp_path / "noimage.yaml").write_text("image: gone.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    cases["is missing"] = tmp_path / "noimage.yaml"
    (tmp_path / "list.yaml").write_text("- 1\n- 2\n")
    cases["expected a YAML mapping"] = tmp_path / "list.yaml"
    d = tmp_path / "unknown"
    d.mkdir()
    cases["no free pixel"] = _write(d, [[205] * 20] * 20)
    d = tmp_path / "mode"
    d.mkdir()
    cases["'mode' must be one of"] = _write(d, [[254] * 4] * 4, mode="fancy")
    d = tmp_path / "resolution"
    d.mkdir()
    cases["'resolution' is 0 metres a pixel"] = _write(d, [[254] * 4] * 4, resolution=0)
    for name, value, words in (("coarse", 1000, "is 1000 metres a pixel"), ("fine", "1e-9", "is 1e-09 metres")):
        d = tmp_path / name
        d.mkdir()
        cases[words] = _write(d, [[254] * 40] * 40)
        (d / "m.yaml").write_text((d / "m.yaml").read_text().replace("resolution: 0.1", f"resolution: {value}"))
    for name, side, words in (("bomb", 100_000, "too large to read"), ("huge", 8000, "8000 x 8000 px")):
        d = tmp_path / name  # a PGM whose header claims more pixels than it holds: refused before reading them
        d.mkdir()
        _write(d, [[254] * 4] * 4)
        (d / "m.pgm").write_bytes(f"P5\n{side} {side}\n255\n".encode() + bytes(16))
        cases[words] = d / "m.yaml"
    d = tmp_path / "one-room"
    d.mkdir()
    cases["1 node and nothing to search between"] = _write(d, [[254] * 30] * 30)  # 3 x 3 m: one region
    d = tmp_path / "pieces"
    d.mkdir()
    two_rooms = np.full((60, 130), 254)
    two_rooms[:, 60:70] = 0  # a wall with no door: two halls of 3 x 6 m
    pieces = _write(d, two_rooms)
    cases["in 2 pieces"] = pieces
    out = tmp_path / "out.json"
    for fragment, path in cases.items():
        r = mures("map", "import", str(path), "--out", str(out))
        assert r.returncode == 2, (fragment, r.stdout, r.stderr)
        last = r.stderr.strip().splitlines()[-1]
        assert last.startswith("mures: error: map import:") and fragment in last, (fragment, r.stderr)
        assert "Traceback" not in r.stderr and not out.exists()
    r = mures("map", "import", str(pieces), "--out", str(out), "--largest-part", "--max-region-m", "3")
    assert r.returncode == 0 and "nodes" in r.stdout, r.stderr
    r = mures("map", "import", str(pieces), "--out", str(tmp_path / "o2.json"), "--largest-part", "--start", "50,50")
    assert r.returncode == 2 and "not on the building's free space" in r.stderr
    r = mures("map", "import", str(pieces), "--out", str(out), "--max-region-m", "-1")
    assert r.returncode == 2 and "a length in metres above 0" in r.stderr
    with pytest.raises(MapError, match="pieces"):
        segment(read_map(pieces))


def test_small_pockets_apart_from_the_building_are_dropped_and_named(tmp_path):
    """A closed closet of 1.2 m2 against the outer wall of a 12 x 6 m floor (under 5 % of it) is
    dropped by default, its area in the note; a room of 7.2 m2 walled off is a piece (an error)."""
    floor = np.full((62, 140), 0)
    floor[1:61, 1:121] = 254  # 12 x 6 m of free space
    floor[1:13, 126:136] = 254  # a closet of 1.0 x 1.2 m behind a wall, touching the outer wall
    grid = read_map(_write(tmp_path, floor))
    regions = segment(grid)
    assert regions.labels[5, 130] == 0 and regions.labels[30, 60] > 0
    assert any("1 pocket apart from it (1.2 m2; under 3.6 m2, 5% of the building)" in n for n in regions.notes), (
        regions.notes
    )
    r = mures("map", "import", str(tmp_path / "m.yaml"), "--out", str(tmp_path / "g.json"))
    assert r.returncode == 0 and "1.2 m2" in r.stderr, r.stderr
    floor[1:61, 121:127] = 0
    floor[1:61, 127:139] = 254  # 7.2 m2 behind a wall: not a pocket
    with pytest.raises(MapError, match="2 pieces"):
        segment(read_map(_write(tmp_path, floor)))


def test_every_example_map_imports_with_default_flags_or_says_in_one_line_why_not(tmp_path):
    """The Nav2 maps shipped in examples/maps: warehouse (and depot, above) import with default
    flags; tb3_sandbox, 20 m2 of free space, is one region at the default --max-region-m, so the
    import refuses it in one line that names the flag, and with that flag it imports."""
    r = mures("map", "import", str(NAV2 / "warehouse.yaml"), "--out", str(tmp_path / "w.json"))
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert json.loads((tmp_path / "w.json").read_text())["source"]["map"] == "warehouse.yaml"
    r = mures("map", "import", str(NAV2 / "tb3_sandbox.yaml"), "--out", str(tmp_path / "t.json"))
    last = r.stderr.strip().splitlines()[-1]
    assert r.returncode == 2 and "1 node and nothing to search between" in last and "--max-region-m" in last
    assert not (tmp_path / "t.json").exists()
    r = mures(
        "map", "import", str(NAV2 / "tb3_sandbox.yaml"), "--out", str(tmp_path / "t.json"), "--max-region-m", "1.5"
    )
    assert r.returncode == 0 and json.loads((tmp_path / "t.json").read_text())["edges"], r.stderr


def test_edge_lengths_follow_the_free_space_and_the_nav2_route_graph_has_them(tmp_path):
    """Two rooms joined by a door at the far end of their shared wall: the edge between their nodes
    is as long as the path through the door, not the straight line through the wall; the graph file
    carries the lengths, and --nav2-route writes the graph as Nav2's route server reads it."""
    from shared.core.graph import GraphError, graph_from_dict, load_graph_file

    grid = read_map(_write(tmp_path, two_rooms_floor(), resolution=0.1))
    regions = segment(grid, max_region_m=10)  # a node a room
    assert len(regions.centers) == 2 and len(regions.edges) == 1
    out = tmp_path / "g.json"
    r = mures(
        "map", "import", str(tmp_path / "m.yaml"), "--out", str(out), "--max-region-m", "10",
        "--nav2-route", str(tmp_path / "g.geojson"),
    )  # fmt: skip
    assert r.returncode == 0 and "along free space" in r.stderr, r.stderr
    data = json.loads(out.read_text())
    (a, b), (length,) = data["edges"][0], data["edge_lengths_m"]
    straight = float(np.hypot(*np.subtract(data["positions"][str(a)], data["positions"][str(b)])))
    (ra, ca), (rb, cb) = regions.centers
    via_door = 0.1 * (np.hypot(ra - 6, ca - 61) + np.hypot(rb - 6, cb - 61))  # centre, door, centre
    assert length > 1.2 * straight and length == pytest.approx(via_door, rel=0.08)
    assert load_graph_file(out).edge_lengths.tolist() == [length]
    route = json.loads((tmp_path / "g.geojson").read_text())
    points = [f for f in route["features"] if f["geometry"]["type"] == "Point"]
    lines = [f["properties"] for f in route["features"] if f["geometry"]["type"] == "MultiLineString"]
    assert [p["properties"]["id"] for p in points] == data["nodes"]
    assert sorted((e["startid"], e["endid"]) for e in lines) == sorted([(a, b), (b, a)])
    assert all(e["cost"] == length for e in lines) and len({e["id"] for e in lines} | {a, b}) == 4
    for bad, words in ((["x"], "edge_lengths_m\\[0\\]"), ([1.0, 2.0], "one length per edge"), ([-1], "above 0")):
        with pytest.raises(GraphError, match=words):
            graph_from_dict({**data, "edge_lengths_m": bad})


def test_a_graph_too_large_to_train_easily_is_warned_of_by_import_and_train(tmp_path):
    """A 60 x 60 m open hall imports as over 200 nodes: the import says so, with the figure and the
    flag that coarsens it, and `mures train` on the graph says so before it starts."""
    hall = np.zeros((302, 302), dtype=np.uint8)
    hall[1:301, 1:301] = 254
    graph = tmp_path / "hall.json"
    r = mures("map", "import", str(_write(tmp_path, hall, resolution=0.2)), "--out", str(graph))
    nodes = len(json.loads(graph.read_text())["nodes"])
    assert r.returncode == 0 and nodes > 200, r.stderr
    assert f"map import: warning: {nodes} nodes." in r.stderr and "--max-region-m` gives fewer" in r.stderr
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "notes.txt").write_text("not a policy snapshot\n")  # train stops there, after its warning
    r = mures("train", "--graph", str(graph), "--robots", "2", "--out", str(taken))
    assert r.returncode == 2 and f"warning: {nodes} nodes." in r.stderr and "refusing to replace it" in r.stderr
