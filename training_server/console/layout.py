"""Node positions for drawing a map: the graph file's own, or an automatic layout when it has none.

The automatic layout is Fruchterman-Reingold (force-directed: edges pull, all pairs push) started
from the Laplacian's spectral embedding, so the same graph always gets the same picture; then nodes
closer than ``GAP`` node radii (the console draws a node with radius ``node_radius(n)``) are pushed
apart, so that no two nodes or their labels overlap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.core.graph import Graph


@dataclass(frozen=True)
class Layout:
    """Where to draw each node: ``positions`` {label: (x, y)} with x, y in [0, 1] (aspect kept, y
    down); ``source`` "file" (the graph file's map-frame positions) or "automatic"; for "file", the
    map frame's place on screen: a map-frame point (x, y) is drawn at ((x - x0) / span, (-y - y0) / span)."""

    positions: dict[int, tuple[float, float]]
    source: str
    x0: float = 0.0
    y0: float = 0.0
    span: float = 1.0

    def to_screen(self, x: float, y: float) -> tuple[float, float]:
        return (x - self.x0) / self.span, (-y - self.y0) / self.span


def node_layout(graph: Graph, iterations: int = 300) -> Layout:
    """The layout of ``graph`` (Layout)."""
    n = graph.n
    if graph.positions and len(graph.positions) == n:
        xy = np.array([graph.positions[i] for i in range(n)], dtype=float)
        xy[:, 1] = -xy[:, 1]  # files use y up; the screen draws y down
        source = "file"
    else:
        xy = _force_directed(graph, iterations if n <= 600 else 60)
        xy = _separated(xy, node_radius(n) * GAP)
        source = "automatic"
    x0, y0 = (float(v) for v in xy.min(axis=0))
    xy -= (x0, y0)
    span = float(xy.max()) or 1.0
    xy /= span
    positions = {int(graph.labels[i]): (round(float(xy[i, 0]), 5), round(float(xy[i, 1]), 5)) for i in range(n)}
    return Layout(positions, source, x0, y0, span)


GAP = 2.6  # the least distance between two nodes' centres, in node radii (a gap of 0.6 r between them)


def node_radius(n: int) -> float:
    """The radius the console draws a node with on a map of ``n`` nodes (layout units, console.js)."""
    return min(0.018, 0.3 / math.sqrt(n))


def _separated(xy: np.ndarray, gap: float, rounds: int = 200) -> np.ndarray:
    """(n, 2) positions scaled to a span of 1, with every pair closer than ``gap`` pushed apart
    (each by half the shortfall, along the line between them) until none is, or ``rounds`` passes."""
    if len(xy) < 2:
        return xy
    for _ in range(rounds):
        xy = xy - xy.min(axis=0)
        xy = xy / (float(xy.max()) or 1.0)
        delta = xy[:, None, :] - xy[None, :, :]
        dist = np.linalg.norm(delta, axis=-1)
        np.fill_diagonal(dist, np.inf)
        short = np.maximum(gap * 1.02 - dist, 0.0)  # a little past the gap: renormalising shrinks it back
        if not (dist < gap).any():
            break
        push = (delta / np.maximum(dist, 1e-9)[..., None] * (short / 2)[..., None]).sum(axis=1)
        xy = xy + push
    return xy


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
