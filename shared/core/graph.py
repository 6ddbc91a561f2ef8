"""Search maps: undirected, connected graphs of rooms (docs/SPEC.md section 1 and 7).

Vocabulary used across the project: ``n`` nodes, ``m`` undirected edges, ``N`` robots,
``B`` episodes in a batch. Nodes carry the *labels* of the published maps (non-negative
integers); internally every array is indexed by the node's *row*, its position in
``Graph.labels``. Conversions happen only at boundaries (files, records, command line).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import deque
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from shared.core.choices import BUILTIN_MAPS

MAX_NODES = 100_000  # the agent's filter is sparse, O(n + m) a step: large maps are fine there
MAX_EDGES = 1_000_000
# EM, the trainer's networks, the planners and model files hold dense (n, n) arrays: at n = 5,000
# one float64 matrix is 200 MB. Asking for one on a larger map is refused with the limit named (the
# simulator and the batched beliefs are sparse above 512 nodes and need none).
DENSE_MAX_NODES = 5_000
MAX_LABEL = 2**63 - 1  # labels are stored as int64


class GraphError(ValueError):
    """A graph description is invalid; the message names the offending node or edge."""


def _is_label(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool) and 0 <= x <= MAX_LABEL


def graph_id_of(labels: list[int], edges: list[tuple[int, int]]) -> str:
    """graph_id exactly as docs/SPEC.md section 5 defines it, from labels and label-pair edges."""
    canon = {
        "nodes": sorted(labels),
        "edges": sorted([min(u, v), max(u, v)] for u, v in edges),
    }
    blob = json.dumps(canon, separators=(",", ":")).encode("utf-8")
    return "sha256:" + hashlib.sha256(blob).hexdigest()


@dataclass(frozen=True, eq=False)
class Graph:
    """An undirected connected graph with precomputed neighbourhood tables.

    Attributes (rows are node indices 0..n-1, ``labels[row]`` is the published label):
        labels:     (n,) node labels in row order.
        edges:      (m, 2) int64 rows of the undirected edges, u < v.
        start:      row of the start node s.
        closed_ptr, closed_idx: CSR of the closed neighbourhoods N[p] (p itself first).
        nbr:        (n, d_max + 1) int64 table of N[p], padded by repeating p.
        deg_closed: (n,) |N[p]|.
        sensing:    optional CSR (ptr, idx) of custom detection sets delta(p) (CE-PG+).
        edge_lengths: optional (m,) float64 metres along free space of each edge (row-aligned with
                    ``edges``), from `mures map import`; None: a graph of unit steps.
    """

    name: str
    labels: np.ndarray
    edges: np.ndarray
    start: int
    positions: dict[int, tuple[float, float]] = field(default_factory=dict)
    sensing_sets: dict[int, list[int]] | None = None
    edge_lengths: np.ndarray | None = None
    index: dict[int, int] = field(init=False)
    closed_ptr: np.ndarray = field(init=False)
    closed_idx: np.ndarray = field(init=False)
    nbr: np.ndarray = field(init=False)
    deg_closed: np.ndarray = field(init=False)
    graph_id: str = field(init=False)

    def __post_init__(self) -> None:
        n = len(self.labels)
        index = {int(lab): i for i, lab in enumerate(self.labels)}
        neighbours: list[list[int]] = [[i] for i in range(n)]
        for u, v in self.edges:
            neighbours[u].append(int(v))
            neighbours[v].append(int(u))
        for i in range(n):
            neighbours[i] = [i, *sorted(neighbours[i][1:])]
        deg = np.array([len(x) for x in neighbours], dtype=np.int64)
        ptr = np.zeros(n + 1, dtype=np.int64)
        np.cumsum(deg, out=ptr[1:])
        idx = np.fromiter((j for x in neighbours for j in x), dtype=np.int64, count=int(ptr[-1]))
        d = int(deg.max())
        nbr = np.repeat(np.arange(n, dtype=np.int64)[:, None], d, axis=1)
        for i, x in enumerate(neighbours):
            nbr[i, : len(x)] = x
        label_edges = [(int(self.labels[u]), int(self.labels[v])) for u, v in self.edges]
        object.__setattr__(self, "index", index)
        object.__setattr__(self, "closed_ptr", ptr)
        object.__setattr__(self, "closed_idx", idx)
        object.__setattr__(self, "nbr", nbr)
        object.__setattr__(self, "deg_closed", deg)
        object.__setattr__(self, "graph_id", graph_id_of([int(x) for x in self.labels], label_edges))

    # ------------------------------------------------------------------ sizes
    @property
    def n(self) -> int:
        return len(self.labels)

    @property
    def m(self) -> int:
        return len(self.edges)

    def closed(self, row: int) -> np.ndarray:
        """Rows of N[p] (p first)."""
        return self.closed_idx[self.closed_ptr[row] : self.closed_ptr[row + 1]]

    def row(self, label: int) -> int:
        try:
            return self.index[label]
        except KeyError:
            raise GraphError(f"node {label} is not in graph {self.name!r}") from None

    def require_dense(self, what: str = "training, EM and the planners") -> None:
        """Refuse (GraphError, the limit named) a dense (n, n) array on a map above DENSE_MAX_NODES."""
        if self.n > DENSE_MAX_NODES:
            raise GraphError(
                f"map {self.name!r} has {self.n} nodes: {what} hold dense n x n arrays "
                f"({self.n**2 * 8 / 1e9:.1f} GB for one float64 matrix) and takes at most {DENSE_MAX_NODES} nodes"
            )

    @cached_property
    def closed_adjacency(self) -> np.ndarray:
        """(n, n) bool, computed once: [p, a] is True when a is in N[p]. Do not modify."""
        return self.adjacency(closed=True)

    def adjacency(self, closed: bool = True) -> np.ndarray:
        """(n, n) bool adjacency; with ``closed`` the diagonal is set (N[p])."""
        self.require_dense()
        a = np.zeros((self.n, self.n), dtype=bool)
        a[self.edges[:, 0], self.edges[:, 1]] = True
        a[self.edges[:, 1], self.edges[:, 0]] = True
        if closed:
            np.fill_diagonal(a, True)
        return a

    def detection_sets(self, detection: str) -> tuple[np.ndarray, np.ndarray]:
        """CSR (ptr, idx) of the detection sets D(p) (docs/SPEC.md section 1).

        ``node``: D(p) = {p}; ``neighbourhood``: D(p) = N[p]; ``custom``: the graph file's
        "sensing" table, N[p] for nodes it does not list.
        """
        if detection == "node":
            return np.arange(self.n + 1, dtype=np.int64), np.arange(self.n, dtype=np.int64)
        if detection == "neighbourhood":
            return self.closed_ptr, self.closed_idx
        if detection == "custom":
            if self.sensing_sets is None:
                raise GraphError(f"graph {self.name!r} has no 'sensing' table for custom detection")
            sets = [self.sensing_sets.get(i, list(self.closed(i))) for i in range(self.n)]
            ptr = np.zeros(self.n + 1, dtype=np.int64)
            np.cumsum([len(s) for s in sets], out=ptr[1:])
            return ptr, np.array([j for s in sets for j in s], dtype=np.int64)
        raise GraphError(f"unknown detection {detection!r} (expected node, neighbourhood or custom)")

    def detection_table(self, detection: str) -> np.ndarray:
        """(n, d) int64: D(p) (``detection_sets``) as a table padded by repeating each set's first
        member, d its largest set: O(n d) where the matrix is O(n^2)."""
        ptr, idx = self.detection_sets(detection)
        sizes = np.diff(ptr)
        table = np.repeat(idx[ptr[:-1]][:, None], int(sizes.max()), axis=1)
        table[np.repeat(np.arange(self.n), sizes), np.arange(len(idx)) - np.repeat(ptr[:-1], sizes)] = idx
        return table

    def detection_matrix(self, detection: str) -> np.ndarray:
        """(n, n) bool: [p, v] is True iff v is in D(p) (the CSR of ``detection_sets`` as a matrix)."""
        self.require_dense()
        ptr, idx = self.detection_sets(detection)
        det = np.zeros((self.n, self.n), dtype=bool)
        det[np.repeat(np.arange(self.n), np.diff(ptr)), idx] = True
        return det

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name,
            "start_node": int(self.labels[self.start]),
            "nodes": [int(x) for x in self.labels],
            "edges": [[int(self.labels[u]), int(self.labels[v])] for u, v in self.edges],
        }
        if self.positions:
            out["positions"] = {str(int(self.labels[k])): list(v) for k, v in self.positions.items()}
        if self.sensing_sets is not None:
            out["sensing"] = {
                str(int(self.labels[k])): [int(self.labels[j]) for j in v] for k, v in self.sensing_sets.items()
            }
        if self.edge_lengths is not None:
            out["edge_lengths_m"] = [round(float(x), 3) for x in self.edge_lengths]
        return out


def graph_from_dict(data: Any, source: str = "graph") -> Graph:
    """Validate a graph description (docs/SPEC.md section 7) and build a Graph.

    Raises GraphError with one line that names the offending node or edge.
    """
    if not isinstance(data, dict):
        raise GraphError(f"{source}: expected a JSON object, got {type(data).__name__}")
    nodes = data.get("nodes")
    edges = data.get("edges")
    if not isinstance(nodes, list) or not nodes:
        raise GraphError(f"{source}: 'nodes' must be a non-empty list of node labels")
    if not isinstance(edges, list):
        raise GraphError(f"{source}: 'edges' must be a list of [u, v] pairs")
    if len(nodes) > MAX_NODES:
        raise GraphError(f"{source}: {len(nodes)} nodes exceed the limit of {MAX_NODES}")
    if len(edges) > MAX_EDGES:
        raise GraphError(f"{source}: {len(edges)} edges exceed the limit of {MAX_EDGES}")
    index: dict[int, int] = {}
    for k, lab in enumerate(nodes):
        if not _is_label(lab):
            raise GraphError(f"{source}: node #{k} ({str(lab)[:40]}) is not an integer label in [0, {MAX_LABEL}]")
        if lab in index:
            raise GraphError(f"{source}: node {lab} is listed twice")
        index[lab] = k
    seen: set[tuple[int, int]] = set()
    rows: list[tuple[int, int]] = []
    for k, e in enumerate(edges):
        if not (isinstance(e, list) and len(e) == 2 and all(_is_label(x) for x in e)):
            raise GraphError(f"{source}: edge #{k} ({str(e)[:40]}) is not a pair of node labels")
        u, v = e
        for x in (u, v):
            if x not in index:
                raise GraphError(f"{source}: edge #{k} [{u}, {v}] names node {x}, which is not in 'nodes'")
        if u == v:
            raise GraphError(f"{source}: edge #{k} [{u}, {v}] is a self-loop")
        key = (min(u, v), max(u, v))
        if key in seen:
            raise GraphError(f"{source}: edge #{k} [{u}, {v}] duplicates an earlier edge")
        seen.add(key)
        a, b = index[u], index[v]
        rows.append((min(a, b), max(a, b)))
    n = len(nodes)
    # connectivity (BFS from the first node)
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in rows:
        adj[a].append(b)
        adj[b].append(a)
    reached = [False] * n
    reached[0] = True
    queue = deque([0])
    while queue:
        u = queue.popleft()
        for v in adj[u]:
            if not reached[v]:
                reached[v] = True
                queue.append(v)
    if not all(reached):
        lost = [nodes[i] for i in range(n) if not reached[i]]
        more = f" and {len(lost) - 5} more" if len(lost) > 5 else ""
        raise GraphError(
            f"{source}: graph is not connected: node(s) {lost[:5]}{more} cannot be reached from node {nodes[0]}"
        )
    start_label = data.get("start_node", nodes[0])
    if not _is_label(start_label) or start_label not in index:
        raise GraphError(f"{source}: start_node {start_label!r} is not one of the graph's nodes")
    positions: dict[int, tuple[float, float]] = {}
    raw_pos = data.get("positions") or {}
    if not isinstance(raw_pos, dict):
        raise GraphError(f"{source}: 'positions' must be an object {{label: [x, y]}}")
    for key, xy in raw_pos.items():
        lab = _parse_label_key(key, index, source, "positions")
        if not (isinstance(xy, list) and len(xy) == 2 and all(isinstance(c, (int, float)) for c in xy)):
            raise GraphError(f"{source}: positions[{key}] must be [x, y] numbers")
        positions[index[lab]] = (float(xy[0]), float(xy[1]))
    sensing: dict[int, list[int]] | None = None
    if data.get("sensing") is not None:
        raw = data["sensing"]
        if not isinstance(raw, dict):
            raise GraphError(f"{source}: 'sensing' must be an object {{label: [labels]}}")
        sensing = {}
        for key, labs in raw.items():
            lab = _parse_label_key(key, index, source, "sensing")
            if not isinstance(labs, list) or not labs:
                raise GraphError(f"{source}: sensing[{key}] must be a non-empty list of labels")
            for x in labs:
                if not _is_label(x) or x not in index:
                    raise GraphError(f"{source}: sensing[{key}] names node {x!r}, which is not in 'nodes'")
            sensing[index[lab]] = sorted({index[x] for x in labs})
    name = data.get("name", source)
    if not isinstance(name, str):
        raise GraphError(f"{source}: 'name' must be a string")
    lengths = _edge_lengths(data.get("edge_lengths_m"), len(edges), source)
    return Graph(
        name=name,
        labels=np.array(nodes, dtype=np.int64),
        edges=np.array(rows, dtype=np.int64).reshape(-1, 2),
        start=index[start_label],
        positions=positions,
        sensing_sets=sensing,
        edge_lengths=lengths,
    )


def _edge_lengths(raw: Any, m: int, source: str) -> np.ndarray | None:
    """'edge_lengths_m': one length in metres (> 0, finite) per edge, in the order of 'edges'."""
    if raw is None:
        return None
    if not isinstance(raw, list) or len(raw) != m:
        raise GraphError(f"{source}: 'edge_lengths_m' must list one length per edge ({m}), in the order of 'edges'")
    for k, x in enumerate(raw):
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x <= 0:
            raise GraphError(f"{source}: edge_lengths_m[{k}] must be a length in metres above 0, got {str(x)[:40]}")
    return np.asarray(raw, dtype=np.float64)


def _parse_label_key(key: str, index: dict[int, int], source: str, table: str) -> int:
    try:
        lab = int(key)
    except (TypeError, ValueError):
        raise GraphError(f"{source}: {table} key {key!r} is not a node label") from None
    if lab not in index:
        raise GraphError(f"{source}: {table} names node {lab}, which is not in 'nodes'")
    return lab


def default_detection(graph: Graph) -> str:
    """D(p) when none is asked for: the graph file's sensing table where it has one (what a robot
    on each node sees, `mures map import --sensor-range`), else {p}."""
    return "custom" if graph.sensing_sets is not None else "node"


def check_searchable(graph: Graph) -> Graph:
    """``graph`` if a team can search it (2 nodes or more), else GraphError saying why: a graph of
    one node is valid as a file but leaves nothing to move to."""
    if graph.n < 2:
        raise GraphError(
            f"{graph.name} has {graph.n} node: there is nothing to search between (a search needs 2 nodes or more; "
            "`mures map import --max-region-m` cuts a building into more)"
        )
    return graph


def load_graph_file(path: str | Path) -> Graph:
    """Read and validate a JSON graph file (docs/SPEC.md section 7)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise GraphError(f"cannot read graph file {str(p)!r}: {exc.strerror or exc}") from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise GraphError(f"{p}: not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None
    return graph_from_dict(data, source=str(p))


def builtin_graph(name: str) -> Graph:
    """OFFICE or MUSEUM (the published labels and start nodes, 43 and 1), or WARD (ours: a corridor of
    12 nodes, 1..12, with two rooms off each, 13..36; start at the corridor's end, node 1)."""
    key = name.lower()
    if key not in BUILTIN_MAPS:
        raise GraphError(f"unknown built-in map {name!r} (expected one of {', '.join(BUILTIN_MAPS)})")
    text = resources.files("shared.core.maps").joinpath(f"{key}.json").read_text(encoding="utf-8")
    return graph_from_dict(json.loads(text), source=key)


def grid_graph(width: int, height: int, name: str | None = None) -> Graph:
    """A 4-connected width x height grid (labels row-major from 0); used by benchmarks and tests."""
    if width < 1 or height < 1:
        raise GraphError("grid sizes must be positive")
    labels = list(range(width * height))
    edges = []
    for y in range(height):
        for x in range(width):
            k = y * width + x
            if x + 1 < width:
                edges.append([k, k + 1])
            if y + 1 < height:
                edges.append([k, k + width])
    return graph_from_dict({"name": name or f"grid{width}x{height}", "nodes": labels, "edges": edges})


def office_graph(n: int, seed: int = 0) -> Graph:
    """An office-like floor of exactly ``n`` nodes (n >= 2), for benchmarks and tests at any size: two
    parallel corridors joined every tenth corridor node (the loops), one or two rooms off each
    corridor node and an inner room behind one room in five, grown corridor node by corridor node
    until n nodes (the seed draws the rooms). Start: the first corridor's first node, label 0."""
    if n < 2:
        raise GraphError(f"an office floor needs at least 2 nodes, got {n}")
    rng = np.random.default_rng(seed)
    edges: list[list[int]] = []
    count = 0

    def add(attach: int | None) -> int | None:
        nonlocal count
        if count >= n:
            return None
        k, count = count, count + 1
        if attach is not None:
            edges.append([attach, k])
        return k

    prev: list[int | None] = [None, None]
    i = 0
    while count < n:
        a = add(prev[0])
        b = add(prev[1] if prev[1] is not None else a)  # the second corridor starts joined to the first
        if a is not None and b is not None and i % 10 == 0 and i > 0:
            edges.append([a, b])  # a loop between the corridors
        for corridor in (a, b):
            for _ in range(int(rng.integers(1, 3))):
                room = add(corridor) if corridor is not None else None
                if room is not None and rng.random() < 0.2:
                    add(room)  # an inner room
        prev = [a, b]
        i += 1
    return graph_from_dict(
        {"name": f"office{n}-{seed}", "nodes": list(range(n)), "edges": edges, "start_node": 0}, source="office_graph"
    )
