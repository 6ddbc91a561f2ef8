"""A fleet that loses robots mid-mission (Fig. 13's setting, in `mures fleet-sim`): N robot-agent
processes of which --kill are killed (SIGKILL) in every mission at steps drawn from 1..--kill-by,
flying a version that holds a team per team size (the robots left switch to the team built for
them when a teammate's liveliness goes) against the same seeds flown by a version holding the
N-robot team alone, and the team built for the robots left flown by that many robots from the
start (Fig. 13's "trained for k").

    python benchmarks/team_switching.py [--map office] [--robots 5] [--kill 4 2] [--missions 150]
        [--episodes 100000] [--teams DIR]
    python benchmarks/team_switching.py --simulated [--eval-episodes 1500] [--kill 4 2] --teams DIR

--simulated flies the same in the batched simulator instead (`mures evaluate`'s engine, each robot
a TeamAgent as in the agent): the robots withdrawn at fixed steps (robot N at step 2, N-1 at 4,
...), every setting on the same seeded episodes, so the switch's gain is a paired difference.

The teams: `mures train --belief true` (CE-PG, the robots' belief on the world's own target
model, as the training server trains on its EM model) for 1..N robots, --episodes each, combined
with `mures snapshot combine`; --teams reuses the snapshots DIR/<map>-N<k>. Every robot flies its
own policy (no team searcher). Writes results/team_switching/<map>-N<N>.json and prints each
setting's capture time with its 95% CI.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from shared.engine.evaluate import mean_ci95

OUT = Path("results/team_switching")
MURES = str(Path(sys.executable).with_name("mures"))


def run(argv: list[str]) -> str:
    print("$ " + " ".join(argv), file=sys.stderr, flush=True)
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode:
        sys.exit(f"{argv[1]} failed ({done.returncode}):\n{done.stderr[-3000:]}")
    return done.stdout


def fleet_sim(map_name: str, robots: int, policy: Path, missions: int, kill: int, kill_by: int) -> dict[str, Any]:
    argv = [MURES, "fleet-sim", "--env", map_name, "--robots", str(robots), "--missions", str(missions)]
    argv += ["--init-policy", str(policy), "--seed", "1", "--step-timeout", "1", "--json"]
    if kill:
        argv += ["--kill", str(kill), "--kill-by", str(kill_by)]
    res: dict[str, Any] = json.loads(run(argv))
    return res


def simulated(args: argparse.Namespace, teams: Path, combined: Path) -> None:
    """The settings of ``main`` in the batched simulator (module docstring)."""
    from shared.core.graph import builtin_graph
    from shared.core.models import Sensor, uniform_walk
    from shared.core.snapshot_format import read_snapshot
    from shared.engine.evaluate import evaluate
    from shared.engine.linked_team import LinkedTeamSearcher

    graph, N = builtin_graph(args.map), args.robots
    truth, sensor = uniform_walk(graph), Sensor()
    version = read_snapshot(combined, graph)
    plain = read_snapshot(teams / f"{args.map}-N{N}", graph)
    print(f"{args.map}, N = {N}, {args.eval_episodes} episodes (seed 1), robots withdrawn at steps 2, 4, ...")
    print("| withdrawn | setting | capture time | vs the N-robot team (paired) |")
    print("| --- | --- | --- | --- |")
    rows = []
    for kill in args.kill:
        gone: list[int | None] = [None] * (N - kill) + [2 * (kill - i) for i in range(kill)]
        times = {}
        for name, snap, known in (("switching", version, True), (f"the {N}-robot team", plain, True)):
            r = evaluate(
                graph,
                truth,
                sensor,
                N,
                lambda s, snap=snap, known=known: LinkedTeamSearcher(snap, graph, N, s, None, known_withdrawals=known),
                episodes=args.eval_episodes,
                seed=1,
                withdraw_at=gone,
            )
            times[name] = r.capture_time
        left = N - kill
        ref = evaluate(
            graph,
            truth,
            sensor,
            left,
            lambda s, left=left: LinkedTeamSearcher(version, graph, left, s, None),
            episodes=args.eval_episodes,
            seed=1,
        )
        times[f"the team built for {left}, {left} robots from the start"] = ref.capture_time
        base = times[f"the {N}-robot team"]
        for name, ct in times.items():
            mean, half = mean_ci95(ct)
            paired = mean_ci95([a - b for a, b in zip(ct, base, strict=True)]) if name == "switching" else None
            vs = f"{paired[0]:+.2f} ± {paired[1]:.2f}" if paired else ""
            print(f"| {kill} at {gone[-kill:]} | {name} | {mean:.2f} ± {half:.2f} | {vs} |")
            row = {"withdrawn_at": gone, "setting": name, "mean_capture_time": round(mean, 3), "ci95": round(half, 3)}
            if paired:
                row |= {
                    "paired_difference_to_the_n_robot_team": round(paired[0], 3),
                    "paired_ci95": round(paired[1], 3),
                }
            rows.append(row)
    out = {"map": args.map, "robots": N, "episodes": args.eval_episodes, "seed": 1, "rows": rows}
    out["team_training_episodes"] = args.episodes
    (OUT / f"{args.map}-N{N}-simulated.json").write_text(json.dumps(out, indent=1) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="office", choices=("office", "museum"))
    ap.add_argument("--robots", type=int, default=5)
    ap.add_argument("--kill", type=int, nargs="+", default=[4, 2], help="robots killed per mission (one setting each)")
    ap.add_argument("--kill-by", type=int, default=10)
    ap.add_argument("--missions", type=int, default=150)
    ap.add_argument("--episodes", type=int, default=100_000, help="CE-PG training episodes per team")
    ap.add_argument("--teams", help="reuse the team snapshots DIR/<map>-N<k> (trained if missing)")
    ap.add_argument("--simulated", action="store_true", help="in the batched simulator instead of fleet-sim")
    ap.add_argument("--eval-episodes", type=int, default=1500, help="with --simulated: episodes per setting")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    N = args.robots
    out: dict[str, Any] = {"map": args.map, "robots": N, "kill_by": args.kill_by, "missions": args.missions}
    out["team_training_episodes"] = args.episodes
    with tempfile.TemporaryDirectory(prefix="mures-switch-") as tmp:
        teams = Path(args.teams or tmp)
        for k in range(1, N + 1):
            snap = teams / f"{args.map}-N{k}"
            if not (snap / "policy.json").is_file():
                train = [MURES, "train", "--env", args.map, "--robots", str(k), "--episodes", str(args.episodes)]
                run([*train, "--belief", "true", "--seed", "0", "--quiet", "--out", str(snap)])
        combined = Path(tmp) / "combined"
        run(
            [MURES, "snapshot", "combine", "--env", args.map, str(teams / f"{args.map}-N{N}")]
            + [str(teams / f"{args.map}-N{k}") for k in range(1, N)]
            + ["--out", str(combined)]
        )
        if args.simulated:
            simulated(args, teams, combined)
            return
        rows = []
        for kill in args.kill:
            left = N - kill
            t0 = time.perf_counter()
            settings = {
                "switching": fleet_sim(args.map, N, combined, args.missions, kill, args.kill_by),
                f"the {N}-robot team": fleet_sim(
                    args.map, N, teams / f"{args.map}-N{N}", args.missions, kill, args.kill_by
                ),
                f"the team built for {left}, {left} robots from the start": fleet_sim(
                    args.map, left, combined, args.missions, 0, args.kill_by
                ),
            }
            for name, res in settings.items():
                times = [r["capture_time"] for r in res["results"]]
                mean, half = mean_ci95(times)
                killed = [r.get("killed", []) for r in res["results"]]
                rows.append(
                    {
                        "killed_per_mission": kill,
                        "setting": name,
                        "mean_capture_time": round(mean, 3),
                        "ci95": round(half, 3),
                        "missions": len(times),
                        # missions in which every kill came before the capture (the others ended first)
                        "missions_with_every_kill": sum(len(k) == kill for k in killed) if any(killed) else None,
                        "censored_fraction": res["censored_fraction"],
                        "capture_times": times,
                        "killed": killed,
                    }
                )
            print(f"kill {kill}: {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)
            out["rows"] = rows
            (OUT / f"{args.map}-N{N}.json").write_text(json.dumps(out, indent=1) + "\n")
    print(f"{args.map}, N = {N}, {args.missions} missions each, kills at steps 1..{args.kill_by}")
    print("| killed | setting | capture time | not captured |")
    print("| --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['killed_per_mission']} | {r['setting']} | {r['mean_capture_time']:.2f} ± {r['ci95']:.2f} | {r['censored_fraction']:.3f} |"
        )


if __name__ == "__main__":
    main()
