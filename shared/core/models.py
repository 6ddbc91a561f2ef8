"""Target motion models and the sensor model (docs/SPEC.md sections 1 and 2).

Gamma is row-stochastic: ``Gamma(u, v) = P(e_{t+1} = v | e_t = u)``, supported on the
closed neighbourhoods N[u]. It is stored sparsely (COO over the support, sorted by row) so
that maps with 10^4 nodes and more stay cheap; ``dense()`` gives the (n, n) matrix.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.choices import DETECTIONS
from shared.core.graph import DENSE_MAX_NODES, Graph

ROW_SUM_TOL = 1e-6


class ModelError(ValueError):
    """A target or sensor model is invalid; the message names the problem."""


@dataclass(frozen=True, eq=False)
class TargetModel:
    """Gamma on the closed-neighbourhood support plus the initial distribution b0.

    Attributes:
        src, dst: (nnz,) int64 rows/columns of the support, sorted by ``src``.
        prob:     (nnz,) float64 Gamma(src, dst); each row sums to 1.
        b0:       (n,) float64 initial target distribution.
        kind:     how it was made ("uniform-walk", "lazy-walk:0.9", "matrix", ...).
    """

    n: int
    src: np.ndarray
    dst: np.ndarray
    prob: np.ndarray
    b0: np.ndarray
    kind: str

    def dense(self) -> np.ndarray:
        """Gamma as an (n, n) matrix (refused above DENSE_MAX_NODES: shared/core/graph.py)."""
        if self.n > DENSE_MAX_NODES:
            raise ModelError(f"a dense {self.n} x {self.n} Gamma exceeds the limit of {DENSE_MAX_NODES} nodes")
        g = np.zeros((self.n, self.n), dtype=np.float64)
        g[self.src, self.dst] = self.prob
        return g

    def to_json(self, graph: Graph) -> dict[str, Any]:
        """The model.json layout of docs/SPEC.md section 7 (labels in row order)."""
        return {
            "nodes": [int(x) for x in graph.labels],
            "gamma": self.dense().tolist(),
            "b0": self.b0.tolist(),
        }


def _check_b0(b0: Any, n: int) -> np.ndarray:
    arr = np.asarray(b0, dtype=np.float64)
    if arr.shape != (n,):
        raise ModelError(f"b0 must have {n} entries, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ModelError("b0 must hold finite non-negative probabilities")
    total = arr.sum()
    if abs(total - 1.0) > ROW_SUM_TOL:
        raise ModelError(f"b0 must sum to 1, sums to {total:.6g}")
    return arr / total


def uniform_b0(n: int) -> np.ndarray:
    return np.full(n, 1.0 / n)


def _from_rows(graph: Graph, prob: np.ndarray, kind: str, b0: np.ndarray | None) -> TargetModel:
    src = np.repeat(np.arange(graph.n, dtype=np.int64), graph.deg_closed)
    return TargetModel(
        n=graph.n,
        src=src,
        dst=graph.closed_idx.copy(),
        prob=prob,
        b0=uniform_b0(graph.n) if b0 is None else _check_b0(b0, graph.n),
        kind=kind,
    )


def uniform_walk(graph: Graph, b0: np.ndarray | None = None) -> TargetModel:
    """The paper's target: uniform over the closed neighbourhood, Gamma(u, v) = 1/|N[u]|."""
    prob = np.repeat(1.0 / graph.deg_closed, graph.deg_closed)
    return _from_rows(graph, prob, "uniform-walk", b0)


def identity_model(graph: Graph) -> TargetModel:
    """Gamma_hat_0 = I with uniform b0 (paper Table II): the robots' belief model before any EM."""
    return from_matrix(graph, np.eye(graph.n), kind="identity")


def lazy_walk(graph: Graph, stay: float, b0: np.ndarray | None = None) -> TargetModel:
    """Stay with probability ``stay``, else move to a uniformly chosen neighbour (not itself).

    A node with no neighbour (a one-node graph) always stays.
    """
    if not (0.0 <= stay <= 1.0) or math.isnan(stay):
        raise ModelError(f"stay probability must be in [0, 1], got {stay}")
    deg_open = graph.deg_closed - 1
    prob = np.empty(len(graph.closed_idx), dtype=np.float64)
    for u in range(graph.n):
        a, b = graph.closed_ptr[u], graph.closed_ptr[u + 1]
        if deg_open[u] == 0:
            prob[a] = 1.0
            continue
        prob[a] = stay  # N[u] lists u first
        prob[a + 1 : b] = (1.0 - stay) / deg_open[u]
    return _from_rows(graph, prob, f"lazy-walk:{stay:g}", b0)


def from_matrix(graph: Graph, gamma: Any, b0: Any = None, kind: str = "matrix") -> TargetModel:
    """An explicit row-stochastic matrix (rows and columns in the graph's row order).

    Validated: (n, n), finite, non-negative, support on closed neighbourhoods, rows sum to 1.
    """
    try:
        g = np.asarray(gamma, dtype=np.float64)
    except (TypeError, ValueError):
        raise ModelError("gamma must be a matrix of numbers") from None
    n = graph.n
    if g.shape != (n, n):
        raise ModelError(f"gamma must be {n} x {n} for this graph, got shape {g.shape}")
    if not np.all(np.isfinite(g)):
        r, c = np.argwhere(~np.isfinite(g))[0]
        raise ModelError(f"gamma[{graph.labels[r]}][{graph.labels[c]}] is not a finite number")
    if np.any(g < 0):
        r, c = np.argwhere(g < 0)[0]
        raise ModelError(f"gamma[{graph.labels[r]}][{graph.labels[c]}] = {g[r, c]} is negative")
    off = (g > 0) & ~graph.closed_adjacency
    if off.any():
        r, c = np.argwhere(off)[0]
        raise ModelError(
            f"gamma[{graph.labels[r]}][{graph.labels[c]}] = {g[r, c]:.3g} but node {graph.labels[c]} "
            f"is not in the closed neighbourhood of {graph.labels[r]}"
        )
    sums = g.sum(axis=1)
    bad = np.abs(sums - 1.0) > ROW_SUM_TOL
    if bad.any():
        r = int(np.argmax(bad))
        raise ModelError(f"gamma row of node {graph.labels[r]} sums to {sums[r]:.6g}, not 1")
    g = g / sums[:, None]
    src = np.repeat(np.arange(n, dtype=np.int64), graph.deg_closed)
    return _from_rows(graph, g[src, graph.closed_idx], kind, b0)


def load_model_file(graph: Graph, path: str | Path) -> TargetModel:
    """Read a model.json ({"nodes", "gamma", optional "b0"}), reordering rows to the graph's."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ModelError(f"cannot read model file {str(p)!r}: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise ModelError(f"{p}: not valid JSON: {exc.msg} at line {exc.lineno}") from None
    if not isinstance(data, dict) or "gamma" not in data:
        raise ModelError(f"{p}: expected an object with 'nodes' and 'gamma'")
    nodes = data.get("nodes", [int(x) for x in graph.labels])
    if not isinstance(nodes, list) or sorted(map(str, nodes)) != sorted(str(int(x)) for x in graph.labels):
        raise ModelError(f"{p}: 'nodes' do not match the graph's nodes")
    try:
        order = [graph.row(int(x)) for x in nodes]
        g = np.asarray(data["gamma"], dtype=np.float64)
        b0 = None if data.get("b0") is None else np.asarray(data["b0"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ModelError(f"{p}: {exc}") from None
    if g.shape != (graph.n, graph.n):
        raise ModelError(f"{p}: gamma must be {graph.n} x {graph.n}, got shape {g.shape}")
    perm = np.empty(graph.n, dtype=np.int64)
    perm[order] = np.arange(graph.n)  # perm[row] = position of that row in the file
    g = g[np.ix_(perm, perm)]
    if b0 is not None:
        if b0.shape != (graph.n,):
            raise ModelError(f"{p}: b0 must have {graph.n} entries")
        b0 = b0[perm]
    try:
        return from_matrix(graph, g, b0, kind=f"file:{p.name}")
    except ModelError as exc:
        raise ModelError(f"{p}: {exc}") from None


def parse_target(graph: Graph, spec: str) -> TargetModel:
    """Command-line target spec: ``uniform``, ``lazy:STAY`` or a model.json path."""
    if spec == "uniform":
        return uniform_walk(graph)
    if spec.startswith("lazy:"):
        try:
            stay = float(spec.split(":", 1)[1])
        except ValueError:
            raise ModelError(f"bad target {spec!r}: expected lazy:STAY with STAY a number in [0, 1]") from None
        return lazy_walk(graph, stay)
    if spec.endswith(".json"):
        return load_model_file(graph, spec)
    raise ModelError(f"bad target {spec!r}: expected uniform, lazy:STAY or a model .json file")


@dataclass(frozen=True)
class Sensor:
    """P(z=1 | e in D(p)) = 1 - eta_fn; P(z=1 | e not in D(p)) = eta_fp.

    Each eta is in [0, 0.5] (the paper's range, Section V-E); both at 0.5 is refused: then
    P(z=1) = 0.5 wherever the target is and the sensor tells nothing.
    """

    eta_fn: float = 0.0
    eta_fp: float = 0.0
    detection: str = "node"

    def __post_init__(self) -> None:
        for name in ("eta_fn", "eta_fp"):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not (0.0 <= v <= 0.5):
                raise ModelError(f"{name} must be in [0, 0.5], got {v!r}")
        if self.eta_fn == 0.5 and self.eta_fp == 0.5:
            raise ModelError("eta_fn = eta_fp = 0.5 makes the sensor uninformative (z does not depend on the target)")
        if self.detection not in DETECTIONS:
            raise ModelError(f"detection must be one of {', '.join(DETECTIONS)}, got {self.detection!r}")

    def likelihoods(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((P(z=0|in), P(z=1|in)), (P(z=0|out), P(z=1|out))): the entries of Lambda (Eq. 2)."""
        return (self.eta_fn, 1.0 - self.eta_fn), (1.0 - self.eta_fp, self.eta_fp)

    def to_json(self) -> dict[str, Any]:
        return {"eta_fn": self.eta_fn, "eta_fp": self.eta_fp, "detection": self.detection}
