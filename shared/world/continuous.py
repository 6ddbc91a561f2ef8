"""A continuous world to measure search in: a building's occupancy map, robots that drive between
the graph's node poses along free space at a speed, a target that walks between them at its own
speed and dwells, detection by range and line of sight, capture time in seconds. Batched: B
missions side by side in numpy, advanced in ticks of ``dt`` seconds.

The geometry (``Building``), built once per map and graph:
- each directed edge's path along free space (the shortest 8-connected path between the two node
  poses, skimage ``MCP_Geometric``), sampled every ``SAMPLE_M`` metres, and its length;
- per node, the pixels a robot standing on its pose sees: within ``sensor_range_m`` and in line of
  sight (rays cast with skimage ``draw.line`` until the first pixel that is not free).

A mission (``fly``):
- the target starts on a node drawn from b0 (uniform), dwells there an exponential time of mean
  ``target_dwell_s``, then walks to a uniformly drawn neighbouring node at ``target_speed`` along
  the edge's path (the uniform walk of the paper, in continuous time);
- every robot starts on the start node; each time it reaches a node it senses: z = 1 with
  probability 1 - eta_fn when the target is in its view, eta_fp otherwise; a z = 1 with the target
  in view captures it (the capture time is that moment); then its searcher picks the next node in
  N[p] and it drives there (length / speed; staying takes ``dwell_s``). Robots decide each on its
  own clock, when it arrives.

Searchers (``SEARCHERS``): ``random`` (uniform over N[p]); ``greedy`` (each robot's own belief on
the paper's step model: updated with each of its readings as if D(p) = {p}, predicted once per own
step with Gamma, the most likely node of N[p] next), the step fleet's decision rule flown in time;
``sweep`` (a closed tour of every node, shortest by nearest neighbour and 2-opt over the lengths
along free space, cut into N arcs of equal length: each robot sweeps its arc back and forth along
shortest paths, whatever it reads), the planner a robotics team would write first; ``fhpe-sa``
(``TeamPlan``: the team's plan on the mission clock, as robot-agent --team-clock seconds flies it,
given every observation at once: one collective belief per mission on 1 s ticks under the uniform
walk made a tick's worth, each reading folded in as it is made, FHPE-SA's move for the robot that
arrives with its teammates counted where they are headed (the robots of a mission arriving in one
tick, as at the start, on one plan). ``plan_time`` (``PLAN_TIMES``) is how the plan's walks take
time: "move", the paper's (the target moves once a move, detections discounted by the move's
index); "discount", detections discounted by when they happen; "travel", the target also
propagated over each move's travel time. Neither of the last two is sooner on every map:
benchmarks/team_plan_in_time.py, docs/continuous-world.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from shared.core.belief_filter import TINY, BeliefFilter
from shared.core.clock import TICK_S, tick_model
from shared.core.fhpe_sa import HORIZON, FhpeSAPlanner
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel, uniform_walk
from shared.floorplan.occupancy import MapError, OccupancyGrid
from shared.floorplan.sight import view
from shared.floorplan.travel import path_length_px, window_path

SEARCHERS = ("random", "greedy", "sweep", "fhpe-sa")
PLAN_TIMES = ("move", "discount", "travel")  # how the fhpe-sa plan's walks take time (module docstring)
SAMPLE_M = 0.1  # a path is sampled every this many metres
WINDOW_MARGIN_M = 3.0  # a path is first searched in the box of its two poses widened by this


@dataclass
class Building:
    """A map and its graph, as the continuous world moves in them (module docstring).

    graph:     the graph (rows 0..n-1).
    node_px:   (n, 2) int64 (row, col) pixel of each node's pose.
    edge_of:   {(u, v): e} the directed edge index of every ordered pair of neighbours.
    edge_end:  (E,) int64 the node each directed edge leads to.
    paths:     per directed edge e, (k_e, 2) int64 pixels along its path from u to v, one every SAMPLE_M.
    length_m:  (E,) float64 metres along each directed edge's path.
    views:     per node, (row0, col0, (h, w) bool): the pixels its robot sees, in a window at row0, col0.
    """

    graph: Graph
    resolution: float
    node_px: np.ndarray
    edge_of: dict[tuple[int, int], int]
    edge_end: np.ndarray
    paths: list[np.ndarray]
    length_m: np.ndarray
    views: list[tuple[int, int, np.ndarray]] = field(repr=False)

    def sees(self, node: np.ndarray, px: np.ndarray) -> np.ndarray:
        """(k,) bool: whether a robot on ``node`` (k,) sees pixel ``px`` (k, 2)."""
        out = np.zeros(len(node), dtype=bool)
        for i, (p, (r, c)) in enumerate(zip(node.tolist(), px.tolist(), strict=True)):
            r0, c0, win = self.views[p]
            rr, cc = r - r0, c - c0
            out[i] = 0 <= rr < win.shape[0] and 0 <= cc < win.shape[1] and bool(win[rr, cc])
        return out


def building(grid: OccupancyGrid, graph: Graph, sensor_range_m: float) -> Building:
    """The Building of ``graph`` (imported from ``grid`` by `mures map import`: its positions are
    poses in the map frame). MapError when a pose is off the free space or two neighbours' poses
    are not joined by it."""
    if len(graph.positions) != graph.n:
        raise MapError(f"{graph.name} has no position for every node: import it with `mures map import`")
    free = grid.free
    node_px = np.array([grid.to_pixel(*graph.positions[p]) for p in range(graph.n)], dtype=np.int64)
    for p, (r, c) in enumerate(node_px.tolist()):
        if not (0 <= r < free.shape[0] and 0 <= c < free.shape[1] and free[r, c]):
            raise MapError(f"node {int(graph.labels[p])}'s pose is not on the map's free space")
    edge_of: dict[tuple[int, int], int] = {}
    paths: list[np.ndarray] = []
    for u, v in graph.edges.tolist():
        pixels = _path(free, node_px[u], node_px[v], grid.resolution)
        for a, b, pts in ((u, v, pixels), (v, u, pixels[::-1])):
            edge_of[a, b] = len(paths)
            paths.append(pts)
    length = np.array([max(path_length_px(p), 1.0) * grid.resolution for p in paths])
    sampled = [_resample(p, grid.resolution) for p in paths]
    views = [view(free, tuple(px), sensor_range_m, grid.resolution) for px in node_px.tolist()]
    edge_end = np.zeros(len(paths), dtype=np.int64)
    for (_u, v), e in edge_of.items():
        edge_end[e] = v
    return Building(graph, grid.resolution, node_px, edge_of, edge_end, sampled, length, views)


def _path(free: np.ndarray, a: np.ndarray, b: np.ndarray, res: float) -> np.ndarray:
    """(k, 2) pixels of the shortest free path from a to b: first in a window around them, else the whole map."""
    margin = math.ceil(WINDOW_MARGIN_M / res)
    r0, c0 = max(0, min(a[0], b[0]) - margin), max(0, min(a[1], b[1]) - margin)
    r1, c1 = min(free.shape[0], max(a[0], b[0]) + margin + 1), min(free.shape[1], max(a[1], b[1]) + margin + 1)
    ends = (int(a[0]), int(a[1])), (int(b[0]), int(b[1]))
    path = window_path(free[r0:r1, c0:c1], (int(r0), int(c0)), *ends)
    if path is None:
        path = window_path(free, (0, 0), *ends)
    if path is None:
        raise MapError(f"no free path between the poses at pixels {ends[0]} and {ends[1]}")
    return path


def _resample(pixels: np.ndarray, res: float) -> np.ndarray:
    """The path's pixels one every SAMPLE_M metres along it (its last pixel last)."""
    if len(pixels) < 2:
        return pixels
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pixels, axis=0), axis=1))]) * res
    at = np.searchsorted(arc, np.arange(0.0, arc[-1], SAMPLE_M))
    return np.concatenate([pixels[at], pixels[-1:]])


@dataclass
class Targets:
    """B targets in a Building, each on node ``at`` dwelling (``edge`` -1, ``left`` seconds more) or
    walking directed edge ``edge``, ``prog`` metres along it (module docstring): the uniform walk
    in continuous time. All (B,)."""

    at: np.ndarray
    edge: np.ndarray
    prog: np.ndarray
    left: np.ndarray

    @classmethod
    def start(
        cls, world: Building, b: int, rng: np.random.Generator, dwell_s: float, model: TargetModel | None = None
    ) -> Targets:
        """B targets on nodes drawn from b0 (uniformly without a ``model``), each dwelling an
        exponential time of mean ``dwell_s``."""
        n = world.graph.n
        at = rng.integers(0, n, size=b) if model is None else rng.choice(n, size=b, p=model.b0 / model.b0.sum())
        return cls(at, np.full(b, -1), np.zeros(b), rng.exponential(dwell_s, size=b))

    def advance(
        self,
        world: Building,
        dt: float,
        moving: np.ndarray,
        rng: np.random.Generator,
        speed: float,
        dwell_s: float,
        model: TargetModel | None = None,
    ) -> None:
        """One tick of ``dt`` seconds for the targets where ``moving`` (B,) bool: a walking target
        goes on (arriving: it dwells anew), a dwelling one waits, and one whose dwell is over sets
        off to a uniformly drawn neighbour (one with no neighbour dwells again): the uniform walk
        in continuous time. With a ``model`` (a lazy walk, a model file; per step) the next node is
        drawn from Gamma_hat's row instead, and drawing its own node means another dwell."""
        g = world.graph
        walking = (self.edge >= 0) & moving
        self.prog[walking] += speed * dt
        arrived = walking & (self.prog >= world.length_m[np.maximum(self.edge, 0)])
        self.at[arrived] = world.edge_end[self.edge[arrived]]
        self.edge[arrived], self.prog[arrived] = -1, 0.0
        self.left[arrived] = rng.exponential(dwell_s, size=int(arrived.sum()))
        dwelling = (self.edge < 0) & moving & ~arrived
        self.left[dwelling] -= dt
        for b in np.flatnonzero(dwelling & (self.left <= 0)):
            u = int(self.at[b])
            if model is not None:
                row = model.src == u
                v = int(rng.choice(model.dst[row], p=model.prob[row] / model.prob[row].sum()))
            else:
                v = int(g.nbr[u, 1 + rng.integers(0, g.deg_closed[u] - 1)]) if g.deg_closed[u] > 1 else u
            self.edge[b] = world.edge_of.get((u, v), -1)
            if self.edge[b] < 0:
                self.left[b] = rng.exponential(dwell_s)

    def pixels(self, world: Building, which: np.ndarray) -> np.ndarray:
        """(k, 2) the pixel of each target ``which`` (k,): its node's pose while it dwells, its
        path's sample while it walks."""
        out = world.node_px[self.at[which]].copy()
        for i, b in enumerate(np.asarray(which).tolist()):
            if self.edge[b] >= 0:
                pts = world.paths[int(self.edge[b])]
                out[i] = pts[min(int(self.prog[b] / SAMPLE_M), len(pts) - 1)]
        return out


def target_generator(mission_seed: int) -> np.random.Generator:
    """The generator a mission's target walks by, from the mission's seed alone: the world served
    to robot agents (shared/tools/timed_world.py) and ``fly(mission_seeds=...)`` draw the same path
    from the same seed, so a fleet and a searcher flown on one seed meet the same target."""
    return np.random.default_rng([int(mission_seed) % (2**63), 1 << 32])


class SeededTargets:
    """``Targets`` for B missions, each walking by its own mission seed's generator
    (``target_generator``): what ``Targets`` does with one shared generator, mission by mission."""

    def __init__(
        self, world: Building, mission_seeds: list[int], dwell_s: float, model: TargetModel | None = None
    ) -> None:
        self.rngs = [target_generator(seed) for seed in mission_seeds]
        self.each = [Targets.start(world, 1, rng, dwell_s, model) for rng in self.rngs]

    def advance(
        self,
        world: Building,
        dt: float,
        moving: np.ndarray,
        _rng: np.random.Generator,
        speed: float,
        dwell_s: float,
        model: TargetModel | None = None,
    ) -> None:
        """``Targets.advance`` for each mission where ``moving``, with its own generator."""
        for b in np.flatnonzero(moving):
            self.each[b].advance(world, dt, np.ones(1, dtype=bool), self.rngs[b], speed, dwell_s, model)

    def pixels(self, world: Building, which: np.ndarray) -> np.ndarray:
        """(k, 2) the pixel of each mission ``which``'s target."""
        one = np.zeros(1, dtype=np.int64)
        return np.array([self.each[b].pixels(world, one)[0] for b in np.asarray(which).tolist()]).reshape(-1, 2)


@dataclass
class Flight:
    """What ``fly`` measured: per mission its capture time in seconds (``max_s`` when not
    captured) and whether it was captured; the decisions made; the wall time."""

    capture_s: np.ndarray
    captured: np.ndarray
    decisions: int
    ticks: int
    wall_s: float


def fly(
    world: Building,
    searcher: str,
    robots: int,
    missions: int,
    sensor: Sensor = Sensor(),  # noqa: B008 - frozen dataclass
    speed: float = 0.5,
    dwell_s: float = 1.0,
    target_speed: float = 0.5,
    target_dwell_s: float = 10.0,
    dt: float = 0.1,
    max_s: float = 1800.0,
    seed: int = 0,
    plan_time: str = "move",
    target_model: TargetModel | None = None,
    stop_prob: float = 0.0,
    stop_s: float = 30.0,
    mission_seeds: list[int] | None = None,
) -> Flight:
    """B = ``missions`` missions of ``robots`` robots with ``searcher`` (``SEARCHERS``). The target
    walks the uniform walk in continuous time, or ``target_model`` (``Targets``), which greedy's
    beliefs and the fhpe-sa plan then use. A move is held up with probability ``stop_prob`` for an
    exponential time of mean ``stop_s`` (as in the world served to the agents). With
    ``mission_seeds`` (one a mission) each target walks by its mission seed's generator, as in the
    world served to the agents (``SeededTargets``): the same missions as a fleet flown on those
    seeds, for comparisons paired mission by mission."""
    if searcher not in SEARCHERS:
        raise ValueError(f"searcher must be one of {', '.join(SEARCHERS)}, got {searcher!r}")
    if plan_time not in PLAN_TIMES:
        raise ValueError(f"plan_time must be one of {', '.join(PLAN_TIMES)}, got {plan_time!r}")
    g, b_n, r_n = world.graph, missions, robots
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    model = target_model or uniform_walk(g)
    gamma = model.dense()  # the step model's Gamma, for the greedy robots' beliefs
    (in0, in1), (out0, out1) = sensor.likelihoods()
    if mission_seeds is not None and len(mission_seeds) != b_n:
        raise ValueError(f"expected one mission seed a mission ({b_n}), got {len(mission_seeds)}")
    target: Targets | SeededTargets = (
        Targets.start(world, b_n, rng, target_dwell_s, target_model)
        if mission_seeds is None
        else SeededTargets(world, mission_seeds, target_dwell_s, target_model)
    )
    # the robots: heading to (or on) r_at, arriving in r_left seconds; their beliefs (greedy)
    r_at = np.full((b_n, r_n), g.start)
    r_left = np.zeros((b_n, r_n))
    belief = np.tile(model.b0 / model.b0.sum(), (b_n, r_n, 1))
    plan = Sweep(world, r_n) if searcher == "sweep" else None
    team = TeamPlan(world, r_n, b_n, sensor, speed, dwell_s, plan_time, model) if searcher == "fhpe-sa" else None
    waypoint = np.zeros((b_n, r_n), dtype=np.int64)  # (sweep) the index of each robot's next waypoint
    done = np.zeros(b_n, dtype=bool)
    capture_s = np.full(b_n, max_s)
    decisions = ticks = 0
    now = 0.0
    while now < max_s and not done.all():
        target.advance(world, dt, ~done, rng, target_speed, target_dwell_s, target_model)
        if team is not None:
            team.predict_to(now)
        # the robots that reach a node now: sense, then decide and go on
        r_left[~done] -= dt
        bs, rs = np.nonzero((r_left <= 0) & ~done[:, None])
        if len(bs):
            here = r_at[bs, rs]
            seen = world.sees(here, target.pixels(world, bs))
            z = rng.random(len(bs)) < np.where(seen, in1, out1)
            for b in np.unique(bs[z & seen]):
                done[b], capture_s[b] = True, now
            go = ~done[bs]
            bs, rs, here, z = bs[go], rs[go], here[go], z[go]
            if plan is not None:
                nxt = plan.next_nodes(waypoint, bs, rs, here)
            elif team is not None:
                nxt = team.decide(bs, rs, here, z, rng)
            else:
                nxt = _decide(searcher, rng, g, gamma, belief, bs, rs, here, z, (in0, in1, out0, out1))
            decisions += len(bs)
            moves = zip(here.tolist(), nxt.tolist(), strict=True)
            travel = np.array([world.length_m[world.edge_of[p, q]] / speed if p != q else dwell_s for p, q in moves])
            if stop_prob:  # hold-ups: a move (not a stay) held up with probability stop_prob (drawn only then)
                held = (rng.random(len(travel)) < stop_prob) & (nxt != here)
                travel = travel + np.where(held, rng.exponential(stop_s, len(travel)), 0.0)
            r_at[bs, rs] = nxt
            r_left[bs, rs] += travel
        now += dt
        ticks += 1
    return Flight(capture_s, done, decisions, ticks, time.perf_counter() - t0)


class TeamPlan:
    """The fhpe-sa searcher (module docstring) for B missions of N robots: ``predict_to(now)`` once
    a world tick, ``decide(bs, rs, here, z, rng)`` for the robots that arrive."""

    def __init__(
        self,
        world: Building,
        robots: int,
        missions: int,
        sensor: Sensor,
        speed: float,
        stay_s: float,
        plan_time: str,
        model: TargetModel | None = None,
        tick_s: float = TICK_S,
    ) -> None:
        g = world.graph
        model = model or uniform_walk(g)
        self.step_s = float(np.median(world.length_m)) / speed  # a step of the model: the median move
        self.gamma_tick = tick_model(model, self.step_s, tick_s).dense()
        steps = None
        if plan_time != "move":  # each move's steps' worth of time; only neighbours' entries are read
            steps = np.full((g.n, g.n), stay_s / self.step_s)
            for (u, v), e in world.edge_of.items():
                steps[u, v] = world.length_m[e] / speed / self.step_s
        self.planner = FhpeSAPlanner(g, model, sensor, HORIZON, move_steps=steps, travel=plan_time == "travel")
        self.filter = BeliefFilter(g, model, sensor)  # its weigh: Lambda(p, z) (Eq. 2)
        self.belief = np.tile(model.b0, (missions, 1))
        self.goal = np.full((missions, robots), g.start)
        self.tick_s, self.next_tick = tick_s, tick_s

    def predict_to(self, now: float) -> None:
        """The beliefs predicted over every tick that has begun by ``now`` (Gamma_tick^T b)."""
        while now + 1e-9 >= self.next_tick:
            self.belief = self.belief @ self.gamma_tick
            self.next_tick += self.tick_s

    def decide(
        self, bs: np.ndarray, rs: np.ndarray, here: np.ndarray, z: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """Fold in the arriving robots' readings, then each one's move on the team's plan."""
        for b, p, zz in zip(bs.tolist(), here.tolist(), z.tolist(), strict=True):
            x = self.filter.weigh(self.belief[b].copy(), p, int(zz))
            total = x.sum()
            if total <= TINY:  # vanished mass: from the reading alone (shared/core/belief_filter.py)
                x = self.filter.weigh(np.ones(len(x)), p, int(zz))
                total = x.sum()
            self.belief[b] = x / total
        # the robots of one mission that arrive together share one plan (at the start, all of them),
        # as robot agents arriving at one moment each take their own entry of the same plan
        out = np.empty(len(bs), dtype=np.int64)
        active = np.ones(self.goal.shape[1], dtype=bool)
        for b in np.unique(bs).tolist():
            mine = np.flatnonzero(bs == b)
            pos = self.goal[b].copy()
            pos[rs[mine]] = here[mine]
            plan = self.planner.plan(self.belief[b], pos, active, rng)
            out[mine] = plan[rs[mine]]
            self.goal[b, rs[mine]] = out[mine]
        return out


class Sweep:
    """The sweep searcher's plan (module docstring): per robot its arc of a shortest closed tour,
    and the next hop of every shortest path along free space."""

    def __init__(self, world: Building, robots: int) -> None:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import shortest_path

        g = world.graph
        rows = [u for (u, _v) in world.edge_of]
        cols = [v for (_u, v) in world.edge_of]
        weights = [world.length_m[e] for e in world.edge_of.values()]
        lengths = coo_matrix((weights, (rows, cols)), shape=(g.n, g.n)).tocsr()
        dist, pred = shortest_path(lengths, return_predecessors=True)
        self.next_hop = pred.T.copy()  # next_hop[u, v]: the node after u on a shortest path to v (pred[v, u])
        np.fill_diagonal(self.next_hop, np.arange(g.n))
        tour = _two_opt(_nearest_tour(dist, g.start), dist)
        self.arcs = _arcs(tour, dist, robots)

    def next_nodes(self, waypoint: np.ndarray, bs: np.ndarray, rs: np.ndarray, here: np.ndarray) -> np.ndarray:
        """The next node of each deciding robot; a robot on its waypoint moves on to the next one."""
        out = np.empty(len(bs), dtype=np.int64)
        for i, (b, r, p) in enumerate(zip(bs.tolist(), rs.tolist(), here.tolist(), strict=True)):
            arc = self.arcs[r]
            if arc[waypoint[b, r] % len(arc)] == p:
                waypoint[b, r] += 1
            goal = arc[waypoint[b, r] % len(arc)]
            out[i] = self.next_hop[p, goal]
        return out


def _nearest_tour(dist: np.ndarray, start: int) -> list[int]:
    """A closed tour of every node from ``start``, always to the nearest node not yet visited."""
    tour, left = [start], set(range(len(dist))) - {start}
    while left:
        here = tour[-1]
        nxt = min(left, key=lambda v: dist[here, v])
        tour.append(nxt)
        left.remove(nxt)
    return tour


def _two_opt(tour: list[int], dist: np.ndarray, rounds: int = 20) -> list[int]:
    """``tour`` shortened by reversing stretches while that helps (2-opt), at most ``rounds`` passes."""
    t = list(tour)
    n = len(t)
    for _ in range(rounds):
        better = False
        for i in range(1, n - 1):
            for j in range(i + 1, n):
                a, b, c, d = t[i - 1], t[i], t[j], t[(j + 1) % n]
                if dist[a, c] + dist[b, d] < dist[a, b] + dist[c, d] - 1e-9:
                    t[i : j + 1] = t[i : j + 1][::-1]
                    better = True
        if not better:
            break
    return t


def _arcs(tour: list[int], dist: np.ndarray, robots: int) -> list[list[int]]:
    """The closed ``tour`` cut into ``robots`` arcs of about equal length (each at least one node);
    a robot sweeps its arc forth and back (its waypoints: the arc, then the arc reversed)."""
    legs = [dist[tour[k], tour[(k + 1) % len(tour)]] for k in range(len(tour))]
    total = float(sum(legs)) or 1.0
    cuts, acc = [0], 0.0
    for k, leg in enumerate(legs[:-1]):
        acc += leg
        if len(cuts) < robots and acc >= total * len(cuts) / robots:
            cuts.append(k + 1)
    while len(cuts) < robots:  # fewer nodes than robots: the last ones share the last node
        cuts.append(min(cuts[-1] + 1, len(tour) - 1))
    bounds = [*cuts, len(tour)]
    out = []
    for i in range(robots):
        arc = tour[bounds[i] : max(bounds[i + 1], bounds[i] + 1)]
        out.append(arc + arc[-2:0:-1] if len(arc) > 2 else arc)
    return out


def _decide(
    searcher: str,
    rng: np.random.Generator,
    g: Graph,
    gamma: np.ndarray,
    belief: np.ndarray,
    bs: np.ndarray,
    rs: np.ndarray,
    here: np.ndarray,
    z: np.ndarray,
    lam: tuple[float, float, float, float],
) -> np.ndarray:
    """The next node (k,) of each deciding robot (bs, rs) on node ``here`` having read ``z``."""
    deg, nbr = g.deg_closed[here], g.nbr[here]
    if searcher == "random":
        return nbr[np.arange(len(here)), (rng.random(len(here)) * deg).astype(np.int64)]
    in0, in1, out0, out1 = lam
    b = belief[bs, rs]  # (k, n): the step model, D(p) = {p}
    like = np.where(z[:, None], out1, out0) * np.ones_like(b)
    like[np.arange(len(here)), here] = np.where(z, in1, in0)
    b = b * like  # Eq. 1's update with this reading
    b /= np.maximum(b.sum(axis=1, keepdims=True), 1e-300)
    pred = b @ gamma  # one step of the model per own step
    belief[bs, rs] = pred
    score = np.where(np.arange(nbr.shape[1])[None, :] < deg[:, None], pred[np.arange(len(here))[:, None], nbr], -1.0)
    score = score + rng.random(score.shape) * 1e-12  # ties broken at random
    return nbr[np.arange(len(here)), score.argmax(axis=1)]
