"""What the `mures` commands share: their error, argument types, and the map and world arguments."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import Any

from shared.core.choices import BUILTIN_MAPS, DETECTIONS
from shared.core.graph import Graph, builtin_graph, check_searchable, default_detection, load_graph_file
from shared.core.models import Sensor, TargetModel, parse_target
from shared.learning.config import positive_int


class CliError(Exception):
    pass


def number_where(text: str, ok: Callable[[float], bool], what: str) -> float:
    """A float that ``ok`` accepts, else an argparse error saying ``what`` was expected."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not ok(v):
        raise argparse.ArgumentTypeError(f"expected {what}, got {v}")
    return v


def eta_arg(text: str) -> float:
    return number_where(text, lambda v: 0.0 <= v <= 0.5, "a number in [0, 0.5]")


def probability(text: str) -> float:
    return number_where(text, lambda v: 0.0 <= v <= 1.0, "a probability in [0, 1]")


def positive_hours(text: str) -> float:
    """``--hours``: a finite number of hours above 0 (argparse type)."""
    return number_where(text, lambda v: 0.0 < v < float("inf"), "a number of hours above 0")


def positive_number(text: str) -> float:
    """A finite number above 0 (argparse type): a speed, a range, a time."""
    return number_where(text, lambda v: 0.0 < v < float("inf"), "a number above 0")


def map_names(text: str) -> tuple[str, ...]:
    """``office,museum``: comma-separated names (argparse type; `mures experiment` checks them)."""
    names = tuple(t.strip().lower() for t in text.split(",") if t.strip())
    if not names:
        raise argparse.ArgumentTypeError(f"expected map names separated by commas, got {text!r}")
    return names


def team_sizes(text: str) -> tuple[int, ...]:
    """``4`` or ``1,2,3``: comma-separated positive integers (argparse type)."""
    sizes = tuple(positive_int(t.strip()) for t in text.split(",") if t.strip())
    if not sizes:
        raise argparse.ArgumentTypeError(f"expected team sizes separated by commas, got {text!r}")
    return sizes


def add_map_args(p: argparse.ArgumentParser) -> None:
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--env", choices=BUILTIN_MAPS, help="a built-in map")
    g.add_argument("--graph", metavar="FILE", help="a JSON graph file (docs/SPEC.md section 7)")


def add_world_args(p: argparse.ArgumentParser) -> None:
    add_map_args(p)
    p.add_argument("--robots", type=positive_int, required=True, help="number of robots N")
    p.add_argument("--eta-fn", type=eta_arg, default=0.0, help="false-negative rate, in [0, 0.5] (default 0)")
    p.add_argument("--eta-fp", type=eta_arg, default=0.0, help="false-positive rate, in [0, 0.5] (default 0)")
    p.add_argument(
        "--detection",
        choices=DETECTIONS,
        default=None,
        help="detection set D(p): {p}, N[p], or the graph file's sensing table (default: custom where the graph "
        "file has one, `mures map import --sensor-range`, else node; neighbourhood for cepg+; a policy snapshot's "
        "own when evaluating one)",
    )
    p.add_argument(
        "--target",
        default="uniform",
        metavar="MODEL",
        help="target motion: uniform (default, the paper's), lazy:STAY, or a model.json file",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")


def graph_of(args: argparse.Namespace) -> Graph:
    return builtin_graph(args.env) if args.env else load_graph_file(args.graph)


def world_of(args: argparse.Namespace, detection: str | None = None) -> tuple[Graph, TargetModel, Sensor]:
    """The map, the true target model and the sensor; ``detection`` when --detection is not given,
    else the map's ``default_detection``."""
    graph = check_searchable(graph_of(args))
    target = parse_target(graph, args.target)
    chosen = args.detection or detection or default_detection(graph)
    sensor = Sensor(eta_fn=args.eta_fn, eta_fp=args.eta_fp, detection=chosen)
    if sensor.detection == "custom":
        graph.detection_sets("custom")  # raises a clear error when the graph has no table
    return graph, target, sensor


def device_of(name: str) -> Any:
    """``--device``: a torch.device that exists here, else a CliError saying why."""
    import torch

    try:
        dev = torch.device(name)
    except RuntimeError:
        raise CliError(f"unknown device {name!r} (expected cpu or cuda)") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CliError("--device cuda asked for, but no CUDA device is available")
    return dev


def add_continuous_args(p: argparse.ArgumentParser, about: str, noise: bool = False) -> Any:
    """The continuous world's flags (docs/continuous-world.md) in a group of their own, introduced by
    ``about``; ``noise`` adds --speed-cv. Returns the group, for a command's own additions."""
    g = p.add_argument_group("continuous world", about)
    g.add_argument("--world", metavar="MAP.yaml", help="the map the --graph was imported from")
    g.add_argument("--speed", type=positive_number, default=0.5, metavar="M_PER_S", help="robots' speed (0.5)")
    if noise:
        g.add_argument(
            "--speed-cv",
            type=number_between(0.0, 1.0),
            default=0.0,
            metavar="CV",
            help="each move's speed drawn with this coefficient of variation (0: every move at --speed)",
        )
    g.add_argument(
        "--stop-prob",
        type=number_between(0.0, 1.0),
        default=0.0,
        metavar="P",
        help="each move is held up with probability P (a door, a person in the way; default 0)",
    )
    g.add_argument(
        "--stop-seconds", type=positive_number, default=30.0, metavar="S", help="a hold-up's mean length (30)"
    )
    g.add_argument("--stay-seconds", type=positive_number, default=1.0, metavar="S", help="a step that stays (1)")
    g.add_argument("--range", type=positive_number, default=4.0, metavar="M", help="sensor range, metres (4)")
    g.add_argument("--target-speed", type=positive_number, default=0.5, metavar="M_PER_S", help="(0.5)")
    g.add_argument(
        "--target-dwell", type=positive_number, default=10.0, metavar="S", help="target's mean stay on a node (10)"
    )
    return g


def number_between(lo: float, hi: float) -> Callable[[str], float]:
    """An argparse type: a number in [lo, hi]."""
    return lambda text: number_where(text, lambda v: lo <= v <= hi, f"a number in [{lo:g}, {hi:g}]")


def building_of(args: argparse.Namespace, graph: Graph) -> Any:
    """``--world MAP.yaml``'s Building for ``graph`` (shared/world/continuous.py), or a CliError:
    --world without --graph, a graph imported from another map, a map the graph's poses do not fit."""
    import json
    from pathlib import Path

    from shared.floorplan.occupancy import MapError, read_map
    from shared.world.continuous import building

    if not getattr(args, "graph", None):
        raise CliError("--world goes with --graph: the graph `mures map import` made from that map")
    source = json.loads(Path(args.graph).read_text(encoding="utf-8")).get("source") or {}
    try:
        grid = read_map(args.world)
        if source.get("image_sha256") and source["image_sha256"] != grid.source["image_sha256"]:
            raise CliError(f"--graph {args.graph} was not imported from {args.world} (its image differs)")
        return building(grid, graph, args.range)
    except MapError as exc:
        raise CliError(f"--world {args.world}: {exc}") from None
