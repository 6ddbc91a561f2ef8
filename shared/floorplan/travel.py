"""How far apart a graph's neighbouring nodes are for a robot: each edge's length along the
building's free space, the shortest path between its two nodes' poses (8-connected, diagonal steps
sqrt(2) pixels long: ``skimage.graph.MCP_Geometric``), which is what a navigation stack drives and
what a move's travel time follows from (length / speed).

A path is searched within the two nodes' regions and the regions next to either (a bounding box
of them, the rest walls), which keeps each search small on a large map; a passage between two
regions never needs a detour through a third one far away. Where that finds none (a passage cut by
filled clutter), the whole building is searched.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from skimage.graph import MCP_Geometric  # shortest paths over a cost image

from shared.floorplan.occupancy import MapError


def edge_lengths(
    labels: np.ndarray, centers: list[tuple[int, int]], edges: list[tuple[int, int]], resolution: float
) -> list[float]:
    """Metres along free space of each edge (i, j) between region centres ``centers[i]`` and
    ``centers[j]`` ((row, col) pixels); ``labels`` (H, W): region index + 1 on the building's free
    pixels, 0 elsewhere. MapError when two neighbours' centres are not joined by free space."""
    n = len(centers)
    neighbours: list[set[int]] = [set() for _ in range(n)]
    for i, j in edges:
        neighbours[i].add(j)
        neighbours[j].add(i)
    boxes = _boxes(labels, n)
    out = []
    for i, j in edges:
        near = {i, j} | neighbours[i] | neighbours[j]
        (r0, c0), (r1, c1) = _union(boxes, near)
        path = window_path(np.isin(labels[r0:r1, c0:c1], [k + 1 for k in near]), (r0, c0), centers[i], centers[j])
        if path is None:  # the whole building
            path = window_path(labels > 0, (0, 0), centers[i], centers[j])
        if path is None:
            raise MapError(f"no free path between node {i} and node {j}, which share a passage")
        out.append(round(max(path_length_px(path), 1.0) * resolution, 3))
    return out


def window_path(
    passable: np.ndarray, origin: tuple[int, int], a: tuple[int, int], b: tuple[int, int]
) -> np.ndarray | None:
    """(k, 2) int64 pixels, in the map's coordinates, of the shortest 8-connected path from ``a`` to
    ``b`` over ``passable`` (a window of the map whose top-left pixel is ``origin``, diagonal steps
    sqrt(2) long: skimage MCP_Geometric); None when ``passable`` joins them nowhere."""
    cost = np.where(passable, 1.0, np.inf)
    start, end = (a[0] - origin[0], a[1] - origin[1]), (b[0] - origin[0], b[1] - origin[1])
    mcp = MCP_Geometric(cost, fully_connected=True)
    costs, _traceback = mcp.find_costs([start], [end])
    if not np.isfinite(costs[end]):
        return None
    return np.asarray(mcp.traceback(end), dtype=np.int64) + np.asarray(origin, dtype=np.int64)


def path_length_px(pixels: np.ndarray) -> float:
    """The length of a pixel path (k, 2), in pixels (0 for a single pixel)."""
    return float(np.linalg.norm(np.diff(pixels, axis=0), axis=1).sum()) if len(pixels) > 1 else 0.0


def _boxes(labels: np.ndarray, n: int) -> list[tuple[tuple[int, int], tuple[int, int]]]:
    """Per region k, its bounding box ((row0, col0), (row1, col1)), row1 and col1 exclusive."""
    found = ndimage.find_objects(labels, max_label=n)
    return [((s[0].start, s[1].start), (s[0].stop, s[1].stop)) for s in found]


def _union(boxes: list, regions: set[int]) -> tuple[tuple[int, int], tuple[int, int]]:
    picked = [boxes[k] for k in regions]
    return (
        (min(b[0][0] for b in picked), min(b[0][1] for b in picked)),
        (max(b[1][0] for b in picked), max(b[1][1] for b in picked)),
    )


def length_summary(lengths: list[float], speed: float | None = None) -> str:
    """One line: the edges' lengths (range, median, coefficient of variation), and a move's travel
    time at ``speed`` m/s when given."""
    if not lengths:
        return "no edges"
    x = np.asarray(lengths)
    text = (
        f"edges {x.min():.1f}-{x.max():.1f} m along free space (median {np.median(x):.1f} m, "
        f"coefficient of variation {x.std() / x.mean():.2f})"
    )
    if speed:
        text += f"; at {speed:g} m/s a move takes {x.min() / speed:.0f}-{x.max() / speed:.0f} s"
    return text
