"""The general policy in numpy: one network for buildings of any size and teams of any size
(docs/general-policy.md). No torch here: this is what a robot agent loads and runs, and the trainer
(shared/learning/general.py) computes its features with the same code.

The per-map networks (shared/core/snapshot_format.py) read robot i's state s = (onehot(p), b)
through weights shaped by the map (about 6 n^2 a robot). This one scores each move a in N[p] from
features of (a, p, b) that mean the same on every graph, with one set of weights shared by every
node, every building and every robot, so it flies buildings and team sizes it never saw:

    score(a) = MLP(f(a; p, b, i, N)) + skip . f(a; p, b, i, N)        pi_i(a | s) = softmax over N[p]

The features (``FEATURES``) are read from hop distances D on the graph (``Distances``) and the
robot's belief b (Eq. 1): for each scale L in ``SCALES`` the belief mass within about L hops of a,
m_L(a) = sum_v b(v) exp(-D(a, v) / L), as it is and against the same mass around p (the direction
toward the mass at that scale); the change in expected distance to the target, E_b[D(a, .)] -
E_b[D(p, .)]; the change in distance to the most likely node; a's degree; the robot's role i in
a team of N (i / (N - 1), 1 / N), which lets robots with the same belief on the same node split up
(the cross-entropy term of Eq. 9 rewards that, shared/learning/general.py); and how near a is to
its teammates' latest known nodes p_j (``TEAMMATE_FEATURES``: the mean of exp(-D(a, p_j) / 4) over
the teammates known, and its change from p), which lets a robot keep clear of the others. Weights do
not depend on n or N. A general policy reads the first k of ``FEATURES``, k in ``FEATURE_COUNTS``
(w1's rows): the first shipped policy read none of the teammates' features.

A fine-tune on one map and team (shared/learning/train.py) may add what no graph-wide feature says:
each robot's own preference for each node of that map, ``NODE_BIAS`` (N, n), added to the score of
a move there, score_i(a) + node_bias[i, a] (the per-map networks' w2 and b2 hold such a term). It
is learned for that team's roles: a team of another size flies the network without it.

Shapes: n nodes, d = max |N[p]| (the graph's ``nbr`` table, padded by repeating p), F features,
H hidden units. Features are computed for any leading batch shape (...).
"""

from __future__ import annotations

import functools
from collections import OrderedDict

import numpy as np

from shared.core.graph import Graph

SCALES = (1, 2, 4, 8, 16, 32)  # hops; each is half the next, so exp(-D/L) comes from exp(-D/32) by squaring
MASS_EPS = 1e-6
FEATURES = (
    "stay",  # 1 for a = p
    "belief_here_rel",  # b(a) / max b
    *(f"toward_mass_{L}" for L in SCALES),  # L log((m_L(a) + eps) / (m_L(p) + eps)), about [-1, 1]
    *(f"mass_{L}" for L in SCALES),  # log10(m_L(a) + eps) / 6 + 1, in [0, 1]
    "expected_distance_change",  # E_b[D(a, .)] - E_b[D(p, .)], in [-1, 1]
    "mode_distance_change",  # D(a, argmax b) - D(p, argmax b), in {-1, 0, 1}
    "mass_ahead",  # sum_v b(v) [D(a, v) < D(p, v)]: the belief mass the move heads toward
    "mass_behind",  # sum_v b(v) [D(a, v) > D(p, v)]: the mass it leaves behind
    "share_ahead",  # the share of the nodes the move heads toward
    "degree",  # |N[a]| / 8
    "role",  # i / (N - 1), 0 for a robot alone
    "team_inverse",  # 1 / N
    "mass_far",  # E_b[D(p, .)] / (E_b[D(p, .)] + 10)
    "graph_size",  # log10(n) / 4
    "mates_near",  # mean over the teammates known of exp(-D(a, p_j) / MATE_SCALE), 0 with none known
    "mates_toward",  # MATE_SCALE (mates_near(a) - mates_near(p))
)
F = len(FEATURES)
TEAMMATE_FEATURES = 2  # the last two: a policy without them reads the first F - 2
FEATURE_COUNTS = (F - TEAMMATE_FEATURES, F)
MATE_SCALE = 4.0  # hops
PARAMS = ("w1", "b1", "w2", "b2", "w3", "skip")  # shapes in ``param_shapes``
NODE_BIAS = "node_bias"  # (N, n): a fine-tune's learned preference of robot i for node a, added to score(a)
ALL_PAIRS_MAX = 5_000  # above this a graph's hop distances are computed row by row, as moves need them
ROW_CACHE = 4_096  # rows kept when computed row by row (each n float32)


def param_shapes(hidden: int, features: int = F) -> dict[str, tuple[int, ...]]:
    """The network's tensors and their shapes for H = ``hidden`` reading the first ``features`` of
    ``FEATURES``: none depends on n or N."""
    k = features
    return {"w1": (k, hidden), "b1": (hidden,), "w2": (hidden, hidden), "b2": (hidden,), "w3": (hidden,), "skip": (k,)}


def feature_count(weights: dict[str, np.ndarray]) -> int:
    """The features a general policy's ``weights`` read: w1's rows when that is one of
    ``FEATURE_COUNTS``, else F (so that a shape check names the bad tensor)."""
    w1 = weights.get("w1")
    k = int(w1.shape[0]) if w1 is not None and getattr(w1, "ndim", 0) == 2 else F
    return k if k in FEATURE_COUNTS else F


def draw(nbrs: np.ndarray, logits: np.ndarray, rng: np.random.Generator, most_likely: bool = False) -> int:
    """One move of N[p] (``nbrs``) from its logits: sampled from their softmax, or the most likely."""
    if most_likely:
        return int(nbrs[int(np.argmax(logits))])
    w = np.exp(logits - logits.max())
    c = np.cumsum(w)
    return int(nbrs[min(int(np.searchsorted(c, rng.random() * c[-1], side="right")), len(nbrs) - 1)])


def hop_distances(graph: Graph, sources: np.ndarray) -> np.ndarray:
    """Hops from each source row to every node, by breadth-first search from all sources in lockstep:
    sources (k,) -> (k, n) float32. The graph is connected (check_searchable), so every entry is finite."""
    sources = np.asarray(sources, dtype=np.int64).reshape(-1)
    k, n = sources.shape[0], graph.n
    dist = np.full((k, n), -1.0, dtype=np.float32)
    frontier = np.zeros((k, n), dtype=bool)
    frontier[np.arange(k), sources] = True
    level = 0
    while frontier.any():
        dist[frontier] = level
        reached = frontier[:, graph.nbr].any(-1)  # (k, n): some closed neighbour is on the frontier
        frontier = reached & (dist < 0)
        level += 1
    return dist


@functools.lru_cache(maxsize=2)
def distances_of(graph: Graph) -> Distances:
    """The hop distances of ``graph``, built once for the graphs in use (an agent's missions all fly
    one map; at 2,000 nodes the table takes seconds)."""
    return Distances(graph)


class Distances:
    """Hop distances of one graph, (n,) float32 rows: the whole (n, n) table at once up to
    ``ALL_PAIRS_MAX`` nodes (4 bytes n^2: 100 MB at 5,000), above it rows computed as moves need them
    and the last ``ROW_CACHE`` kept (``all_pairs`` chooses instead of the size)."""

    def __init__(self, graph: Graph, all_pairs: bool | None = None) -> None:
        self.graph = graph
        self.table: np.ndarray | None = None
        self.cache: OrderedDict[int, np.ndarray] = OrderedDict()
        if graph.n <= ALL_PAIRS_MAX if all_pairs is None else all_pairs:
            self.table = np.concatenate(
                [hop_distances(graph, np.arange(a, min(a + 256, graph.n))) for a in range(0, graph.n, 256)]
            )

    def rows(self, nodes: np.ndarray) -> np.ndarray:
        """D(nodes, .): (..., n) float32 for node rows of any shape (...)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        if self.table is not None:
            return self.table[nodes]
        flat = nodes.reshape(-1)
        missing = np.unique([v for v in flat.tolist() if v not in self.cache])
        if missing.size:
            for v, row in zip(missing.tolist(), hop_distances(self.graph, missing), strict=True):
                self.cache[v] = row
        out = np.stack([self.cache[v] for v in flat.tolist()])
        for v in flat.tolist():
            self.cache.move_to_end(v)
        while len(self.cache) > ROW_CACHE:
            self.cache.popitem(last=False)
        return out.reshape(*nodes.shape, self.graph.n)


def move_features(
    graph: Graph,
    dist: Distances,
    pos: np.ndarray,
    belief: np.ndarray,
    role: np.ndarray,
    team: np.ndarray,
    mates: np.ndarray | None = None,
) -> np.ndarray:
    """f(a; p, b, i, N) for every slot a of the ``nbr`` table at p: pos (...,) node rows, belief (..., n),
    role (...,) i / (N - 1), team (...,) N, mates (..., M) the teammates' latest known node rows (-1:
    not known; None: none) -> (..., d, F) float32 (padded slots repeat p's stay)."""
    pos = np.asarray(pos, dtype=np.int64)
    belief = np.asarray(belief, dtype=np.float32)
    cand = graph.nbr[pos]  # (..., d)
    d_cand = dist.rows(cand)  # (..., d, n); N[p] lists p first, so slot 0 holds D(p, .)
    b = belief[..., None, :]  # (..., 1, n)
    scales = np.exp(-d_cand / SCALES[-1])  # exp(-D/32), then squared down the scales
    mass = np.empty((*cand.shape, len(SCALES)), dtype=np.float32)  # (..., d, scales): m_L(a)
    for k in range(len(SCALES) - 1, -1, -1):
        mass[..., k] = (scales * b).sum(-1)
        if k:
            scales = scales * scales
    mass_here = mass[..., :1, :]  # m_L(p)
    toward = np.asarray(SCALES, dtype=np.float32) * np.log((mass + MASS_EPS) / (mass_here + MASS_EPS))
    expected = (d_cand * b).sum(-1)  # (..., d): E_b[D(a, .)]
    closer = d_cand < d_cand[..., :1, :]  # (..., d, n): v nearer a than p
    farther = d_cand > d_cand[..., :1, :]
    mode = belief.argmax(-1)[..., None, None]  # (..., 1, 1)
    mode_dist = np.take_along_axis(d_cand, np.broadcast_to(mode, (*cand.shape, 1)), -1)[..., 0]  # (..., d)
    b_cand = np.take_along_axis(belief, cand, -1)  # (..., d)
    d = cand.shape[-1]
    slot = np.broadcast_to(np.arange(d), cand.shape)
    role_f = np.broadcast_to(np.asarray(role, dtype=np.float32)[..., None], cand.shape)
    team_f = np.broadcast_to(1.0 / np.asarray(team, dtype=np.float32)[..., None], cand.shape)
    far = expected[..., :1]
    near = np.zeros((*cand.shape, 1), dtype=np.float32)  # mates_near: 0 with no teammate known
    if mates is not None and np.shape(mates)[-1]:
        m = np.asarray(mates, dtype=np.int64)
        known = np.broadcast_to((m >= 0)[..., None, :], (*cand.shape, m.shape[-1]))  # (..., d, M)
        cols = np.broadcast_to(np.maximum(m, 0)[..., None, :], known.shape)
        weight = np.where(known, np.exp(-np.take_along_axis(d_cand, cols, -1) / MATE_SCALE), 0.0)
        near = (weight.sum(-1) / np.maximum(known.sum(-1), 1))[..., None].astype(np.float32)
    parts = [
        (slot == 0).astype(np.float32)[..., None],
        (b_cand / np.maximum(belief.max(-1, keepdims=True), 1e-12))[..., None],
        toward,
        np.log10(mass + MASS_EPS) / 6.0 + 1.0,
        (expected - far)[..., None],
        (mode_dist - mode_dist[..., :1])[..., None],
        (closer * b).sum(-1)[..., None],
        (farther * b).sum(-1)[..., None],
        closer.mean(-1, dtype=np.float32)[..., None],
        (graph.deg_closed[cand] / 8.0)[..., None],
        role_f[..., None],
        team_f[..., None],
        np.broadcast_to(far / (far + 10.0), cand.shape)[..., None],
        np.full((*cand.shape, 1), np.log10(graph.n) / 4.0),
        near,
        MATE_SCALE * (near - near[..., :1, :]),
    ]
    return np.concatenate(parts, axis=-1).astype(np.float32)


def roles(team: int) -> np.ndarray:
    """The role feature of robots 0..N-1 in a team of N: i / (N - 1), 0 for one robot. (N,) float32."""
    return np.arange(team, dtype=np.float32) / max(team - 1, 1)


def scores(weights: dict[str, np.ndarray], feats: np.ndarray) -> np.ndarray:
    """The network: (..., d, F) -> (..., d) scores (logits before the mask to N[p]), on the first
    ``feature_count(weights)`` features."""
    feats = feats[..., : weights["w1"].shape[0]]
    h = np.maximum(feats @ weights["w1"] + weights["b1"], 0.0)
    h = np.maximum(h @ weights["w2"] + weights["b2"], 0.0)
    return h @ weights["w3"] + feats @ weights["skip"]


class GeneralAgent:
    """One robot's decisions with the general policy, in numpy: robot ``robot`` of a team of
    ``team`` on ``graph``, with the network's float32 ``weights`` (``param_shapes``) and, from a
    fine-tune on this map, ``NODE_BIAS`` (team, n): robot i's score of a move to a gains
    node_bias[i, a]. ``act(p, b, mates)`` -> next node row in N[p], b the robot's belief (Eq. 1) or
    the team's collective one, ``mates`` its teammates' latest known node rows (as heard; None or
    empty: none known)."""

    def __init__(
        self,
        weights: dict[str, np.ndarray],
        graph: Graph,
        robot: int,
        team: int,
        rng: np.random.Generator | None = None,
        greedy_actions: bool = False,
        distances: Distances | None = None,
    ) -> None:
        if not 0 <= robot < team:
            raise ValueError(f"robot index {robot} is not in a team of {team}")
        self.weights = {k: np.asarray(weights[k], dtype=np.float64) for k in PARAMS}
        self.node_bias: np.ndarray | None = None  # (n,): this robot's row
        if NODE_BIAS in weights:
            bias = np.asarray(weights[NODE_BIAS], dtype=np.float64)
            if bias.shape != (team, graph.n):
                raise ValueError(f"{NODE_BIAS} has shape {bias.shape}, expected ({team}, {graph.n}): a team of {team}")
            self.node_bias = bias[robot]
        self.graph = graph
        self.dist = distances or distances_of(graph)
        self.role, self.team = float(roles(team)[robot]), team
        self.rng = rng or np.random.default_rng(0)
        self.greedy_actions = greedy_actions

    def logits(self, p: int, belief: np.ndarray, mates: np.ndarray | None = None) -> np.ndarray:
        """The scores of N[p] in ``graph.closed(p)``'s order: (|N[p]|,) float64."""
        m = None if mates is None else np.asarray(mates, dtype=np.int64).reshape(-1)
        feats = move_features(
            self.graph, self.dist, np.asarray(p), belief, np.asarray(self.role), np.asarray(self.team), m
        )
        out = scores(self.weights, feats.astype(np.float64))
        if self.node_bias is not None:
            out = out + self.node_bias[self.graph.nbr[p]]
        return out[: int(self.graph.deg_closed[p])]

    def act(self, p: int, belief: np.ndarray, mates: np.ndarray | None = None) -> int:
        """a ~ pi_i(. | p, b) over N[p] (the most likely with ``greedy_actions``) -> node row."""
        return draw(self.graph.closed(p), self.logits(p, belief, mates), self.rng, self.greedy_actions)
