"""How well `mures map import` finds rooms: its rooms scored against the true ones, per map.

    python benchmarks/segmentation.py [--floors 20] [--json results/segmentation.json]

Maps: Nav2's depot, warehouse and TurtleBot3 sandbox (examples/maps/nav2; each an open hall, so
its true segmentation, judged by eye from the map, is its free space as one room), and --floors
generated office floors (shared/floorplan/floors.py, seeds 0..F-1) with their known rooms. For each
map, at the default parameters: recall (the mean over true rooms of the share of a room's area in
its best-matching found room), precision (the mean over found rooms of the share of its area in
its best-matching true room; both over the pixels both label; Bormann et al., ICRA 2016), the
graph's nodes and edges, whether it is connected with every node on its region's free space, and
the import's time. Prints a table and the means; writes the figures as JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from shared.floorplan.floors import office_floor, segmentation_scores
from shared.floorplan.occupancy import read_map
from shared.floorplan.rooms import segment

NAV2 = Path(__file__).resolve().parents[1] / "examples" / "maps" / "nav2"
AIM = {"recall": 0.85, "precision": 0.92}


def connected_on_free(grid, regions) -> bool:
    """Every region reachable through the edges, and every node on a free pixel of its region."""
    n = int(regions.labels.max())
    adjacency: dict[int, set[int]] = {k: set() for k in range(n)}
    for i, j, _w in regions.edges:
        adjacency[i].add(j)
        adjacency[j].add(i)
    seen, todo = {regions.start}, [regions.start]
    while todo:
        for j in adjacency[todo.pop()] - seen:
            seen.add(j)
            todo.append(j)
    on_free = all(grid.free[r, c] and regions.labels[r, c] == k + 1 for k, (r, c) in enumerate(regions.centers))
    return len(seen) == n and on_free


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--floors", type=int, default=20, help="generated office floors (seeds 0..F-1)")
    ap.add_argument("--json", type=Path, default=Path("results/segmentation.json"))
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        maps = [(name, NAV2 / f"{name}.yaml", None) for name in ("depot", "warehouse", "tb3_sandbox")]
        for seed in range(args.floors):
            floor = office_floor(seed)
            maps.append((f"office-floor-{seed}", floor.write(tmp, f"floor-{seed}"), floor.rooms))
        for name, path, truth in maps:
            t0 = time.perf_counter()
            grid = read_map(path)
            regions = segment(grid)
            seconds = time.perf_counter() - t0
            truth = grid.free.astype(np.int32) if truth is None else truth  # an open hall: one room
            recall, precision = segmentation_scores(truth, regions.rooms)
            rows.append(
                {
                    "map": name,
                    "pixels": f"{grid.shape[1]} x {grid.shape[0]}",
                    "resolution_m": grid.resolution,
                    "true_rooms": int(truth.max()),
                    "rooms_found": int(len(np.unique(regions.rooms)) - 1),
                    "nodes": int(regions.labels.max()),
                    "edges": len(regions.edges),
                    "recall": round(recall, 4),
                    "precision": round(precision, 4),
                    "connected_on_free": connected_on_free(grid, regions),
                    "seconds": round(seconds, 2),
                }
            )
            r = rows[-1]
            print(
                f"| {name} | {r['pixels']} at {r['resolution_m']:g} m | {r['true_rooms']} | {r['rooms_found']} "
                f"| {r['nodes']} / {r['edges']} | {recall:.3f} | {precision:.3f} | {r['connected_on_free']} "
                f"| {seconds:.2f} |",
                flush=True,
            )
    means = {k: round(float(np.mean([r[k] for r in rows])), 4) for k in ("recall", "precision", "seconds")}
    print(f"means over {len(rows)} maps: recall {means['recall']:.3f}, precision {means['precision']:.3f} "
          f"(aim {AIM['recall']} and {AIM['precision']}), {means['seconds']:.2f} s a map; "
          f"connected with every node on free space: {sum(r['connected_on_free'] for r in rows)} of {len(rows)}")  # fmt: skip
    args.json.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "command": "python benchmarks/segmentation.py" + (f" --floors {args.floors}" if args.floors != 20 else ""),
        "machine": {"platform": platform.platform(), "python": platform.python_version()},
        "aim": AIM,
        "means": means,
        "maps": rows,
    }
    args.json.write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main()
