"""fig5 (beta against PG, paired by training seed) on one map, from a results directory's teams:
what `mures experiment fig5` reports for that map, before the other map's teams exist.

Run: python benchmarks/fig5_map.py --results DIR --map office [--quick]

Teams missing from DIR/snapshots are trained first (4x10^5 episodes each at the full budget);
evaluated cells are cached in DIR/cells as the experiment caches them.
"""

import argparse
import json
from pathlib import Path

from shared.tools import experiments as ex


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--results", default="results")
    p.add_argument("--map", choices=("office", "museum"), default="office")
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    root, env, b = Path(args.results), args.map, ex.QUICK if args.quick else ex.FULL
    ex._CELLS = root / "cells"
    sensor = ex.sensor_for("cepg")
    times, trained = {}, {}
    for beta in ex.BETAS:
        for s in b.seeds:
            team = ex._flown(ex._snapshot(root, env, 4, beta, b.train, s), env, sensor, 4)
            cell = ex._cell(env, 4, "pg" if beta == 1.0 else "cepg", team, b.episodes, times=True)
            times[beta, s] = cell.pop("capture_times")
            trained[beta] = cell["train_episodes"]
    rows = [{**ex._beta_row(env, 4, beta, b, times), "train_episodes": trained[beta]} for beta in ex.BETAS]
    for r in rows:
        print(json.dumps(r))
    print("\n".join(ex._beta_reading(rows)))


if __name__ == "__main__":
    main()
