"""Node positions for drawing a map: the graph file's own, or an automatic layout when it has none.

The automatic layout is Fruchterman-Reingold (force-directed: edges pull, all pairs push) started
from the Laplacian's spectral embedding, so the same graph always gets the same picture.
"""

from __future__ import annotations

import numpy as np

from shared.core.graph import Graph


def node_layout(graph: Graph, iterations: int = 300) -> tuple[dict[int, tuple[float, float]], str]:
    """({label: (x, y)} with x, y in [0, 1] (aspect kept), "file" | "automatic") for ``graph``."""
    n = graph.n
    if graph.positions and len(graph.positions) == n:
        xy = np.array([graph.positions[i] for i in range(n)], dtype=float)
        xy[:, 1] = -xy[:, 1]  # files use y up; the screen draws y down
        source = "file"
    else:
        xy = _force_directed(graph, iterations if n <= 600 else 60)
        source = "automatic"
    xy -= xy.min(axis=0)
    span = float(xy.max()) or 1.0
    xy /= span
    return {int(graph.labels[i]): (round(float(xy[i, 0]), 5), round(float(xy[i, 1]), 5)) for i in range(n)}, source


def _force_directed(graph: Graph, iterations: int) -> np.ndarray:
    """(n, 2) positions: spectral start (eigenvectors 1 and 2 of L = D - A), then force-directed."""
    n = graph.n
    if n == 1:
        return np.zeros((1, 2))
    a = graph.adjacency(closed=False).astype(float)
    lap = np.diag(a.sum(axis=1)) - a
    _w, vec = np.linalg.eigh(lap)
    pos = vec[:, 1:3] if n > 2 else np.c_[vec[:, -1], np.zeros(n)]
    pos = pos + np.random.default_rng(0).normal(scale=1e-3, size=pos.shape)  # separates equal rows
    pos /= np.abs(pos).max() or 1.0
    k = 1.0 / np.sqrt(n)  # the ideal edge length in the unit square
    temp = 0.1
    for _ in range(iterations):
        delta = pos[:, None, :] - pos[None, :, :]  # (n, n, 2)
        dist = np.maximum(np.linalg.norm(delta, axis=-1), 1e-3)
        force = k * k / dist - a * dist * dist / k  # repulsion minus attraction along each pair
        disp = (delta / dist[..., None] * force[..., None]).sum(axis=1)
        length = np.maximum(np.linalg.norm(disp, axis=1), 1e-9)
        pos += disp / length[:, None] * np.minimum(length, temp)[:, None]
        temp *= 0.985
    return pos
