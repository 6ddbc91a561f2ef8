"""`mures map`: a map's size and graph_id, and `mures map import`: a ROS occupancy-grid map
(map_server's map.yaml and its image) turned into the fleet's graph of rooms (docs/your-building.md).

    mures map (--env NAME | --graph FILE)
    mures map import MAP.yaml --out GRAPH.json [--regions REGIONS.png] [--preview PREVIEW.png] [--nav2-route G.geojson]
        [--start X,Y] [--max-region-m M] [--min-door-m W] [--max-door-m D] [--largest-part] [--sensor-range M]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared.tools.cli_args import BUILTIN_MAPS, CliError, graph_of, number_where

LARGE_GRAPH_NODES = 200  # above this, training a graph's policy is slow and memory-hungry (warned)


def large_graph_warning(n: int) -> str | None:
    """What `mures map import` and `mures train` say of a graph of ``n`` nodes above LARGE_GRAPH_NODES."""
    if n <= LARGE_GRAPH_NODES:
        return None
    return (
        f"warning: {n} nodes. A per-map team's weights grow with the square of the nodes, and above about "
        f"{LARGE_GRAPH_NODES} training one (mures train from scratch) takes hours and tens of GB on a small machine "
        "(docs/your-building.md); the general policy flies the building untrained (--searcher general, a server's "
        "default first version; docs/general-policy.md), or a larger `mures map import --max-region-m` gives fewer, "
        "larger nodes"
    )


def cmd_map(args: argparse.Namespace) -> int:
    if args.map_command == "import":
        return cmd_map_import(args)
    if not (args.env or args.graph):
        raise CliError("map: give --env NAME or --graph FILE (or `mures map import MAP.yaml --out GRAPH.json`)")
    g = graph_of(args)
    deg = g.deg_closed - 1
    info = {
        "name": g.name,
        "nodes": g.n,
        "edges": g.m,
        "start_node": int(g.labels[g.start]),
        "max_degree": int(deg.max()),
        "mean_degree": float(np.mean(deg)),
        "graph_id": g.graph_id,
    }
    print(json.dumps(info, indent=2))
    return 0


def cmd_map_import(args: argparse.Namespace) -> int:
    from shared.core.graph import graph_from_dict
    from shared.floorplan.graph_file import graph_dict, route_geojson, write_preview, write_regions
    from shared.floorplan.occupancy import MapError, read_map
    from shared.floorplan.rooms import segment
    from shared.floorplan.travel import length_summary

    t0 = time.perf_counter()
    say = (lambda _t: None) if args.quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    parameters = {
        "max_region_m": args.max_region_m,
        "min_door_m": args.min_door_m,
        "max_door_m": args.max_door_m,
        "start": list(args.start) if args.start else None,
        "largest_part": args.largest_part,
    }
    try:
        grid = read_map(args.map)
        say(f"map import: {args.map}: {grid.shape[1]} x {grid.shape[0]} px at {grid.resolution:g} m, "
            f"{grid.free.sum() * grid.resolution**2:.1f} m2 free")  # fmt: skip
        regions = segment(
            grid,
            max_region_m=args.max_region_m,
            min_door_m=args.min_door_m,
            max_door_m=args.max_door_m,
            start_xy=args.start,
            largest_part=args.largest_part,
        )
    except MapError as exc:
        raise CliError(f"map import: {exc}") from None
    for note in regions.notes:
        say(f"map import: {note}")
    if args.sensor_range:
        parameters["sensor_range_m"] = args.sensor_range
    data = graph_dict(grid, regions, Path(args.map).stem.upper(), parameters)
    if args.sensor_range:  # D(p) for --detection custom: the nodes whose pose p's robot sees
        from shared.floorplan.sight import sensing_sets

        node_px = np.array([grid.to_pixel(*data["positions"][str(k)]) for k in data["nodes"]])
        sets = sensing_sets(grid.free, node_px, args.sensor_range, grid.resolution)
        data["sensing"] = {str(k): v for k, v in sets.items()}
        say(
            f"map import: sensing table: a robot sees {np.mean([len(v) for v in sets.values()]):.1f} nodes' poses "
            f"on average (itself included) within {args.sensor_range:g} m in line of sight (--detection custom)"
        )
    graph = graph_from_dict(data, str(args.out))  # the file loads with --graph everywhere
    if graph.n < 2:
        free_m2 = float((regions.labels > 0).sum()) * grid.resolution**2
        smaller = max(0.5, round(math.sqrt(free_m2) / 3, 1))
        raise CliError(
            f"map import: the building's {free_m2:.1f} m2 of free space is one region of at most "
            f"{args.max_region_m:g} m, so the graph has 1 node and nothing to search between: cut it into areas "
            f"with a smaller --max-region-m (e.g. {smaller:g})"
        )
    warning = large_graph_warning(graph.n)
    if warning:
        say(f"map import: {warning} (now {args.max_region_m:g} m)")
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=1) + "\n")
    written = [str(out)]
    if args.regions:
        write_regions(args.regions, regions.labels)
        written.append(str(args.regions))
    if args.preview:
        write_preview(args.preview, grid, regions)
        written.append(str(args.preview))
    if args.nav2_route:
        Path(args.nav2_route).write_text(json.dumps(route_geojson(data), indent=1) + "\n")
        written.append(str(args.nav2_route))
    say(f"map import: {length_summary(data['edge_lengths_m'])}")
    rooms = len(np.unique(regions.rooms)) - 1
    start = data["positions"][str(regions.start)]
    print(
        f"{graph.n} nodes ({rooms} room{'s' if rooms != 1 else ''} cut into areas of at most {args.max_region_m:g} m), "
        f"{graph.m} edges, "
        f"start node {regions.start} at ({start[0]:g}, {start[1]:g}); graph_id {graph.graph_id}; "
        f"wrote {', '.join(written)} in {time.perf_counter() - t0:.1f} s"
    )
    return 0


def point(text: str) -> tuple[float, float]:
    """``X,Y``: a map-frame point in metres (argparse type)."""
    parts = text.split(",")
    try:
        x, y = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in metres, got {text!r}") from None
    if not (math.isfinite(x) and math.isfinite(y)):
        raise argparse.ArgumentTypeError(f"expected finite X,Y in metres, got {text!r}")
    return x, y


def metres(text: str) -> float:
    return number_where(text, lambda v: 0.0 < v < 1e4, "a length in metres above 0")


def add_map_commands(sub: Any) -> None:
    """`mures map` and `mures map import` (``sub``: the subparsers of `mures`)."""
    from shared.floorplan import MAX_DOOR_M, MAX_REGION_M, MIN_DOOR_M

    p = sub.add_parser("map", help="print a map's size and graph_id; `map import`: a ROS map as the fleet's graph")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--env", choices=BUILTIN_MAPS, help="a built-in map")
    g.add_argument("--graph", metavar="FILE", help="a JSON graph file (docs/SPEC.md section 7)")
    p.set_defaults(func=cmd_map, map_command=None)
    actions = p.add_subparsers(dest="map_command", metavar="ACTION")
    imp = actions.add_parser(
        "import",
        help="turn a ROS occupancy-grid map (map_server's map.yaml and image) into a graph of rooms",
        description="Segment a ROS map's free space into rooms and areas (a node each) joined by passages "
        "(an edge each); write the graph file, and optionally the regions image and a preview.",
    )
    imp.add_argument("map", metavar="MAP.yaml", help="map_server's YAML (image, resolution, origin, thresholds, mode)")
    imp.add_argument("--out", required=True, metavar="GRAPH.json", help="the graph file to write")
    imp.add_argument(
        "--regions", metavar="REGIONS.png", help="a 16-bit PNG of the map's size: node index + 1 per free pixel"
    )
    imp.add_argument("--preview", metavar="PREVIEW.png", help="the regions, nodes and edges drawn over the map")
    imp.add_argument(
        "--nav2-route",
        metavar="GRAPH.geojson",
        help="also the graph as Nav2's route server reads one (nav2_route GeoJSON: nodes, both directions of each "
        "edge, its length along free space as its cost)",
    )
    imp.add_argument(
        "--start", type=point, metavar="X,Y", help="the start node's point in the map frame (default: the origin, "
        "where SLAM began, when it is free; else the point of largest clearance)"
    )  # fmt: skip
    imp.add_argument(
        "--max-region-m", type=metres, default=MAX_REGION_M, metavar="M",
        help=f"the widest region a node stands for: rooms wider are cut into areas (default {MAX_REGION_M:g})",
    )  # fmt: skip
    imp.add_argument(
        "--min-door-m", type=metres, default=MIN_DOOR_M, metavar="W",
        help=f"the narrowest passage that makes an edge (default {MIN_DOOR_M:g})",
    )  # fmt: skip
    imp.add_argument(
        "--max-door-m", type=metres, default=MAX_DOOR_M, metavar="D",
        help=f"openings narrower than this separate rooms (default {MAX_DOOR_M:g})",
    )  # fmt: skip
    imp.add_argument(
        "--largest-part", action="store_true", help="keep the largest part of a map whose free space is in pieces"
    )
    imp.add_argument(
        "--sensor-range", type=metres, default=None, metavar="M",
        help="also write the graph's sensing table: per node, the nodes whose pose its robot sees within M metres "
        "in line of sight (D(p) for --detection custom; docs/continuous-world.md)",
    )  # fmt: skip
    imp.add_argument("--quiet", action="store_true", help="print the summary line only")
    imp.set_defaults(func=cmd_map)
