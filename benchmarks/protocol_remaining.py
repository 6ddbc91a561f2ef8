"""What remains of the paper's protocol, given a results directory's cache: the teams still to
train and the cells still to evaluate for the parts not yet recorded, each job counted once (a team
that several figures fly is trained once), with `mures experiment --plan`'s estimates of their time
on one core (shared/tools/experiments/costs.py, TRAIN_MS_PER_EPISODE).

Run: python benchmarks/protocol_remaining.py [--results results] [--list] [--calibrate]

`--calibrate` checks the estimates against the cache instead: for each map and method, how many
cached teams there are and the geometric mean, least and greatest of their measured wall time over
their estimate (the snapshot's training summary's wall_seconds against `_train_cost` of the team's map,
robots, algorithm, episodes and eta_fn).

The parts (docs/protocol.md, "What is recorded"): fig11 on MUSEUM (OFFICE's is
recorded), fig13 on both maps and fig7 at N = 1, 2, 3, 5 on MUSEUM. Every part at the full
budget; `--fraction F` prices fig7's N = 1, 2, 3, 5 at F times it (`--train-fraction`).
"""

import argparse
from collections import defaultdict
from pathlib import Path
from statistics import geometric_mean

from shared.core.snapshot_format import META, read_meta
from shared.tools.experiments.budget import budget
from shared.tools.experiments.cells import cell_job
from shared.tools.experiments.costs import MAP_COST, train_cost
from shared.tools.experiments.schedule import outlook
from shared.tools.runner import Job

# (figure, maps, team sizes or None for the figure's own, a budget fraction applies)
PARTS = [
    ("fig11", ("museum",), None, False),
    ("fig13", ("office", "museum"), None, False),
    ("fig7", ("museum",), (1, 2, 3, 5), True),
]


def calibrate(results: Path) -> None:
    """Print, per map and method, the cached teams' measured / estimated training time."""
    ratios: dict[tuple[str, str], list[float]] = defaultdict(list)
    for meta_file in sorted((results / "snapshots").glob(f"*/{META}")):
        meta = read_meta(meta_file.parent)
        env, summary = meta["map"].lower(), meta.get("summary", {})
        if not summary.get("wall_seconds") or env not in MAP_COST:
            continue  # a team without a measured time, or on a map of one's own
        method = meta.get("algorithm", "cepg")
        estimate = train_cost(method, env, meta["robots"], summary["episodes"], meta["sensor"]["eta_fn"])
        ratios[env, method].append(summary["wall_seconds"] / estimate)
    print(f"{results}: cached teams' wall time / --plan's estimate")
    print(f"  {'map':8s} {'method':8s} {'teams':>5s} {'geo mean':>8s} {'least':>6s} {'most':>6s}")
    for (env, method), r in sorted(ratios.items()):
        print(f"  {env:8s} {method:8s} {len(r):5d} {geometric_mean(r):8.2f} {min(r):6.2f} {max(r):6.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", type=Path, default=Path("results"))
    ap.add_argument("--fraction", type=float, default=None, help="fig7's N = 1, 2, 3, 5 at this budget fraction")
    ap.add_argument("--list", action="store_true", help="every job with its estimate")
    ap.add_argument("--calibrate", action="store_true", help="the cached teams' wall time against the estimates")
    args = ap.parse_args()
    if args.calibrate:
        calibrate(args.results)
        return
    jobs: dict[str, Job] = {}
    later: dict[str, float] = {}
    for name, maps, robots, scalable in PARTS:
        b = budget(name, False, None, maps, robots, args.fraction if scalable else None, True)
        planned = outlook(name, args.results, b)
        jobs.update((j.key, j) for j in planned.jobs or [])
        later.update(planned.later.values())
    teams = [j for j in jobs.values() if j.fn is not cell_job]
    cells = [j for j in jobs.values() if j.fn is cell_job]
    team_s = sum(j.weight for j in teams)
    cell_s = sum(j.weight for j in cells) + sum(later.values())
    print(
        f"{args.results}: {len(teams)} teams to train ({team_s / 3600:.1f} h), {len(cells)} cells to evaluate now "
        f"and {len(later)} once their teams exist ({cell_s / 3600:.1f} h): {(team_s + cell_s) / 3600:.1f} "
        "single-core hours in all (K workers: at best that / K)"
    )
    if args.list:
        rows = [(j.weight, j.label) for j in teams + cells] + [(w, label) for label, w in later.items()]
        for w, label in sorted(rows, reverse=True):
            print(f"  {w / 3600:6.2f} h  {label}")


if __name__ == "__main__":
    main()
