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
    root, b = Path(args.results), ex.QUICK if args.quick else ex.FULL
    ex._CELLS = root / "cells"
    rows = ex.fig5_rows(root, args.map, b)
    for r in rows:
        print(json.dumps(r))
    print("\n".join(ex._beta_reading(rows)))


if __name__ == "__main__":
    main()
