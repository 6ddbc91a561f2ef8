"""The maps the benchmarks measure on: Nav2's depot and warehouse (examples/maps/nav2) and AWS's
bookstore and small house (shared/reference/maps/aws, beside the repository, when present), each
imported with `mures map import`'s defaults."""

from __future__ import annotations

import json
import platform
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from shared.core.graph import Graph, load_graph_file
from shared.floorplan.floors import office_floor
from shared.tools.cli import main as mures_main

ROOT = Path(__file__).resolve().parents[1]
MAPS = {
    "depot": ROOT / "examples" / "maps" / "nav2" / "depot.yaml",
    "warehouse": ROOT / "examples" / "maps" / "nav2" / "warehouse.yaml",
    "bookstore": ROOT.parent / "shared" / "reference" / "maps" / "aws" / "bookstore.yaml",
    "small-house": ROOT.parent / "shared" / "reference" / "maps" / "aws" / "small-house.yaml",
}


def map_yaml(name: str, workdir: Path) -> Path:
    """A benchmark map by its name: one of MAPS, or ``office-K``, the generated office floor
    ``office_floor(K)`` written into ``workdir``."""
    if name in MAPS:
        return MAPS[name]
    seed = name.removeprefix("office-")
    if not name.startswith("office-") or not seed.isdigit():
        raise SystemExit(f"unknown map {name!r}: one of {', '.join(MAPS)} or office-K")
    return office_floor(int(seed)).write(workdir, name)


def imported(yaml_path: Path, workdir: Path, sensor_range: float | None = None) -> Graph:
    """The map imported with default flags into ``workdir`` (its graph has edge lengths), and with
    ``sensor_range`` (metres) the sensing table of what each node's robot sees (`--sensor-range`)."""
    out = workdir / f"{yaml_path.stem}.json"
    extra = [] if sensor_range is None else ["--sensor-range", f"{sensor_range:g}"]
    if mures_main(["map", "import", str(yaml_path), "--out", str(out), "--quiet", *extra]) != 0:
        raise SystemExit(f"importing {yaml_path} failed")
    return load_graph_file(out)


def shipped_graphs(workdir: Path) -> Iterator[tuple[str, Path, Graph]]:
    """(name, map YAML, its graph) of each map in MAPS that is here, imported into ``workdir``; a map
    that is not here is said so and skipped."""
    for name, path in MAPS.items():
        if not path.exists():
            print(f"{name}: {path} not here; skipped")
            continue
        yield name, path, imported(path, workdir)


def write_rows(path: str | Path, settings: dict[str, Any], rows: list[dict[str, Any]]) -> Path:
    """A benchmark's table as JSON: its settings, the machine and one object per row."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"settings": settings, "machine": platform.machine(), "rows": rows}, indent=1) + "\n")
    return out
