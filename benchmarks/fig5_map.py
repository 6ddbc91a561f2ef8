"""fig5 (beta against PG, paired by training seed) on one map, from a results directory's teams:
what `mures experiment fig5` reports for that map, before the other map's teams exist.

Run: python benchmarks/fig5_map.py --results DIR --map office [--quick]

Teams missing from DIR/snapshots are trained first (4x10^5 episodes each at the full budget);
evaluated cells are cached in DIR/cells as the experiment caches them.
"""

import argparse
import json
from pathlib import Path

from shared.tools.experiments import FULL, QUICK, Context
from shared.tools.experiments.figures.beta import fig5_rows
from shared.tools.experiments.report.readings import beta_reading


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--results", default="results")
    p.add_argument("--map", choices=("office", "museum"), default="office")
    p.add_argument("--quick", action="store_true")
    args = p.parse_args()
    root = Path(args.results)
    rows = fig5_rows(Context(root, QUICK if args.quick else FULL, cells=root / "cells"), args.map)
    for r in rows:
        print(json.dumps(r))
    print("\n".join(beta_reading(rows)))


if __name__ == "__main__":
    main()
