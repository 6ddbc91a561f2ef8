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
from skimage.graph import MCP_Geometric

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
        px = _path_px(labels, _union(boxes, near), [k + 1 for k in near], centers[i], centers[j])
        if not np.isfinite(px):
            whole = ((0, 0), labels.shape)
            px = _path_px(labels, whole, list(range(1, n + 1)), centers[i], centers[j])
        if not np.isfinite(px):
            raise MapError(f"no free path between node {i} and node {j}, which share a passage")
        out.append(round(max(px, 1.0) * resolution, 3))
    return out


def _path_px(labels: np.ndarray, box: tuple, regions: list[int], a: tuple[int, int], b: tuple[int, int]) -> float:
    """Pixels along the shortest 8-connected path from ``a`` to ``b`` within ``regions`` inside ``box``."""
    (r0, c0), (r1, c1) = box
    cost = np.where(np.isin(labels[r0:r1, c0:c1], regions), 1.0, np.inf)
    start, end = (a[0] - r0, a[1] - c0), (b[0] - r0, b[1] - c0)
    costs, _traceback = MCP_Geometric(cost, fully_connected=True).find_costs([start], [end])
    return float(costs[end])


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
