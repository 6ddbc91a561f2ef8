"""How far the trainer's EM lands from the target's true walk, with and without a Dirichlet prior.

    python benchmarks/em_prior.py [--map depot] [--robots 2] [--missions 512] [--priors 0 1 5]
                                  [--workdir DIR]

The map imported with `mures map import`'s defaults (benchmarks/shipped_maps.py), a team trained as
benchmarks/fleet_in_time.py trains one (`mures train --episodes 20000 --team-searcher fhpe-sa --seed
0`), ``--missions`` missions flown by it under the uniform walk (seed 5) and turned into episode
records, then EM (300 passes at most, as the trainer's update) with pseudo-counts P on Gamma_hat's
support and on b0 for each P of ``--priors``. Prints the mean row total-variation distance of each
estimate to the true walk and b0's largest entry in units of 1/n.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from shipped_maps import MAPS, imported  # benchmarks/shipped_maps.py, beside this script

from shared.core.models import Sensor, uniform_walk
from shared.engine.estimate import collect_missions, em, mean_row_tv
from shared.engine.evaluate import episode_records, evaluate
from shared.learning.team_snapshot import PolicySearcher, load_snapshot


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--map", default="depot", choices=sorted(MAPS))
    ap.add_argument("--robots", type=int, default=2)
    ap.add_argument("--missions", type=int, default=512)
    ap.add_argument("--priors", type=float, nargs="+", default=[0.0, 1.0, 5.0])
    ap.add_argument("--workdir", help="keep the graph and the team here (default: a temporary folder)")
    args = ap.parse_args()
    tmp = None if args.workdir else tempfile.TemporaryDirectory(prefix="mures-em-prior-")
    work = Path(args.workdir or tmp.name)  # type: ignore[union-attr]
    work.mkdir(parents=True, exist_ok=True)
    yaml_path = MAPS[args.map]
    graph = imported(yaml_path, work)
    team = work / f"team-{args.map}-N{args.robots}"
    if not team.exists():
        subprocess.run([sys.executable, "-m", "shared.tools.cli", "train", "--graph", str(work / f"{yaml_path.stem}.json"),
                        "--robots", str(args.robots), "--episodes", "20000", "--team-searcher", "fhpe-sa", "--seed",
                        "0", "--out", str(team), "--quiet"], check=True)  # fmt: skip
    truth, sensor = uniform_walk(graph), Sensor()
    snap = load_snapshot(team, graph)

    def searcher(seed: int) -> PolicySearcher:
        return PolicySearcher(snap, graph, sensor, args.robots, seed=seed)

    res = evaluate(graph, truth, sensor, args.robots, searcher, episodes=args.missions, seed=5, record=True)
    data = collect_missions(((0, r) for r in episode_records(graph, res, sensor)), graph)
    print(f"{args.map} (n={graph.n}), N={args.robots}, {len(data.length)} missions")
    print(f"{'pseudo-count':>12} {'mean row TV':>12} {'b0 max x n':>11} {'EM passes':>10}")
    for prior in args.priors:
        est = em(graph, data, max_iter=300, tol=1e-5, pseudo_count=prior, b0_pseudo_count=prior)
        tv = mean_row_tv(est.model, truth)
        print(f"{prior:>12g} {tv:>12.3f} {float(est.model.b0.max()) * graph.n:>11.2f} {est.iterations:>10}")


if __name__ == "__main__":
    main()
