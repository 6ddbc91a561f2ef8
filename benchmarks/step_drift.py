"""How far a team's step clocks drift apart when each move takes its own travel time, and how often
today's teamwork rule then still decides on the team's plan.

    python benchmarks/step_drift.py [--robots 4] [--missions 2000] [--steps 50] [--speed 0.5]
                                    [--dwell 1.0] [--speed-cv 0.1] [--equal-steps] [--seed 0]
                                    [--json results/step_drift/step_drift.json]

Maps: Nav2's depot and warehouse (examples/maps/nav2) and AWS's bookstore and small house
(shared/reference/maps/aws, when present), each imported with `mures map import`'s defaults, so each
edge has its length along free space (edge_lengths_m). Per mission, N robots start on the start
node and each flies T steps: every step it picks a node of N[p] uniformly (an untrained policy's
moves; staying takes --dwell seconds, a move length / speed, the speed drawn per move with
coefficient of variation --speed-cv). As robot-agent decides today (robot_agent/teamwork.py), robot
i arriving at its step t at time A_i(t) waits at most TEAM_WAIT_S (0.5 s) for its teammates'
step-t observations: it decides on the team's plan when all are in by then (max_j A_j(t) <=
A_i(t) + 0.5, the network taken as instant), else on what has come; it leaves when it decides.
Prints, per map, the share of decisions on the full team plan over steps 1-10 and 11-T and the
spread of the robots' step-t arrival times (max - min) at t = 10 and T, each a mean over missions
with its 95 % CI half-width. --equal-steps gives every step the map's median move time and no speed
noise: the paper's model, in which the rule decides on the full plan every time. Writes the figures
as JSON.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
from pathlib import Path

import numpy as np
from shipped_maps import shipped_graphs  # benchmarks/shipped_maps.py, beside this script

from robot_agent.teamwork import TEAM_WAIT_S
from shared.core.graph import Graph
from shared.engine.evaluate import mean_ci95


def move_seconds(graph: Graph, dwell: float, speed: float) -> np.ndarray:
    """(n, d_max + 1) seconds of the move from row p to graph.nbr[p, k] at ``speed`` (staying: ``dwell``)."""
    assert graph.edge_lengths is not None, "a graph imported by `mures map import` has edge lengths"
    length = {}
    for (u, v), metres in zip(graph.edges, graph.edge_lengths, strict=True):
        length[int(u), int(v)] = length[int(v), int(u)] = float(metres)
    out = np.full(graph.nbr.shape, dwell)
    for p in range(graph.n):
        for k, q in enumerate(graph.nbr[p]):
            if q != p:
                out[p, k] = length[p, int(q)] / speed
    return out


def fly(graph: Graph, robots: int, missions: int, steps: int, seconds: np.ndarray, speed_cv: float, seed: int) -> dict:
    """B missions side by side (numpy over B): the share of team-plan decisions and the arrival spread."""
    rng = np.random.default_rng(seed)
    b, n_r = missions, robots
    pos = np.full((b, n_r), graph.start)
    arrive = np.zeros((b, n_r))  # A_i(t): when robot i reads z at its step t
    team = np.zeros((b, steps), dtype=bool)  # per mission and step: every robot decided on the full plan
    team_share = np.zeros((b, steps))
    spread = np.zeros((b, steps + 1))
    deg = graph.deg_closed
    for t in range(steps + 1):
        spread[:, t] = arrive.max(axis=1) - arrive.min(axis=1)
        if t == steps:
            break
        last = arrive.max(axis=1, keepdims=True)
        full = last <= arrive + TEAM_WAIT_S  # every teammate's step-t observation in within the wait
        team_share[:, t] = full.mean(axis=1)
        team[:, t] = full.all(axis=1)
        decide = np.minimum(arrive + TEAM_WAIT_S, np.maximum(arrive, last))
        k = (rng.random((b, n_r)) * deg[pos]).astype(np.int64)  # a node of N[p], uniformly
        dur = seconds[pos, k]
        moving = graph.nbr[pos, k] != pos
        if speed_cv > 0:
            dur = np.where(moving, dur / rng.lognormal(0.0, speed_cv, size=dur.shape), dur)
        arrive = decide + dur
        pos = graph.nbr[pos, k]
    early, late = team_share[:, 1:10].mean(axis=1), team_share[:, 10:].mean(axis=1)
    return {
        "team_plan_share_steps_1_10": mean_ci95(early),
        "team_plan_share_steps_11_T": mean_ci95(late),
        "spread_s_t10": mean_ci95(spread[:, 10]),
        "spread_s_tT": mean_ci95(spread[:, steps]),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--robots", type=int, default=4)
    p.add_argument("--missions", type=int, default=2000)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--speed", type=float, default=0.5, help="m/s")
    p.add_argument("--dwell", type=float, default=1.0, help="seconds a step that stays takes")
    p.add_argument("--speed-cv", type=float, default=0.1, help="coefficient of variation of a move's speed")
    p.add_argument("--equal-steps", action="store_true", help="every step the median move time (the paper's model)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", metavar="FILE")
    args = p.parse_args()
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, _path, graph in shipped_graphs(Path(tmp)):
            seconds = move_seconds(graph, args.dwell, args.speed)
            if args.equal_steps:
                seconds = np.full(seconds.shape, float(np.median(graph.edge_lengths)) / args.speed)
            cv = 0.0 if args.equal_steps else args.speed_cv
            res = fly(graph, args.robots, args.missions, args.steps, seconds, cv, args.seed)
            lengths = graph.edge_lengths
            rows[name] = {"nodes": graph.n, "edges": graph.m, "median_edge_m": float(np.median(lengths)), **res}
    print(
        f"N = {args.robots}, {args.missions} missions of {args.steps} steps, {args.speed} m/s "
        f"(cv {args.speed_cv}), staying {args.dwell} s, teammates waited for at most {TEAM_WAIT_S} s"
        + (": every step the median move time" if args.equal_steps else "")
    )
    print("map          n    team plan, steps 1-10   steps 11-T        spread at t=10 (s)   at t=T (s)")
    for name, r in rows.items():

        def fmt(pair: tuple[float, float], pct: bool = False) -> str:
            m, h = pair
            return f"{100 * m:5.1f} ± {100 * h:3.1f} %" if pct else f"{m:6.1f} ± {h:4.1f}"

        print(
            f"{name:<12} {r['nodes']:<4} {fmt(r['team_plan_share_steps_1_10'], True):<23} "
            f"{fmt(r['team_plan_share_steps_11_T'], True):<17} {fmt(r['spread_s_t10']):<20} {fmt(r['spread_s_tT'])}"
        )
    if args.json:
        out = {"settings": vars(args), "team_wait_s": TEAM_WAIT_S, "machine": platform.machine(), "maps": rows}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
