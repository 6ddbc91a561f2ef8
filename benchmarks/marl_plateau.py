"""Has a team reached its plateau? Teams of one method trained for growing budgets, flown on the
same episodes as a reference team (CE-PG), with the paired difference to it.

Train the teams first with the CLI, e.g. (OFFICE, N = 4, the protocol's seed 0):

    mures train --env office --robots 4 --algorithm mappo --episodes 100000 --seed 0 --threads 1 --out T/mappo-1e5
    mures train --env office --robots 4 --algorithm mappo --episodes 400000 --seed 0 --threads 1 --out T/mappo-4e5
    mures train --env office --robots 4 --episodes 400000 --seed 0 --out T/cepg-4e5

then

    python benchmarks/marl_plateau.py --env office --robots 4 --reference T/cepg-4e5 T/mappo-1e5 T/mappo-4e5 [--out results/marl/plateau.json]

Every team flies the same --episodes episodes (seed --seed: the same target paths and draws), on
the paper's setup (uniform-walk target, perfect node sensor). Prints, per team, the episodes it
was trained for, its mean capture time (95% CI), its paired difference to the reference
(team - reference, 95% CI over the episodes; negative: it captures sooner), and its learning
curve's capture time over the tenth of its run ending at the middle and over the last tenth
(still falling at the end: not yet its plateau); with --out, also
writes them as JSON.

Each row also keeps its capture times, episode by episode, so that a team is paired with the same
method's next shorter budget in the file as well (team - shorter team, 95% CI): the plateau test
proper, since a budget that no longer captures sooner than half of it is past the plateau.

With --add, the teams' rows are added to the --out file already written (a team of the same name
replaces its row), so that a longer budget can be compared without flying the others again. The
setup (map, N, episodes, seed) must be the file's, and the reference must fly exactly as the
file's did (its capture times, episode by episode, or for files written before they were kept its
mean and CI): the paired differences are to the same episodes of the same team, or the command
stops before it writes anything.
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np
import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.core.snapshot_format import read_meta
from shared.engine.evaluate import evaluate, mean_ci95
from shared.learning.team_snapshot import PolicySearcher, load_snapshot


def _curve_mean(curve: list[dict], lo: float, hi: float) -> float | None:
    """Mean training capture time of the learning-curve points between fractions lo and hi of the run."""
    if not curve:
        return None
    total = curve[-1]["episodes"]
    pts = [p["mean_capture_time"] for p in curve if lo * total < p["episodes"] <= hi * total]
    return round(float(np.mean(pts)), 3) if pts else None


def fly(path: Path, env: str, robots: int, episodes: int, seed: int) -> tuple[dict, np.ndarray]:
    """A snapshot's capture times over the seeded episodes, and what it says of its training."""
    g = builtin_graph(env)
    snap, sensor = load_snapshot(path, g), Sensor()
    res = evaluate(
        g, uniform_walk(g), sensor, robots, lambda s: PolicySearcher(snap, g, sensor, robots, seed=s), episodes, seed
    )
    meta = read_meta(path)
    curve = meta.get("summary", {}).get("learning_curve", [])
    info = {
        "team": path.name,
        "algorithm": meta.get("algorithm", "cepg"),
        "train_episodes": meta.get("summary", {}).get("episodes"),
        "training_seed": meta.get("training", {}).get("seed"),
        "train_wall_seconds": meta.get("summary", {}).get("wall_seconds"),
        # is it still learning at the end of its budget? its training capture time (the learning
        # curve: exploring policies, training episodes) over the tenth of the run ending at its
        # middle, and over the last tenth
        "curve_at_half": _curve_mean(curve, 0.4, 0.5),
        "curve_at_end": _curve_mean(curve, 0.9, 1.0),
    }
    return info, res.capture_time.astype(np.float64)


def _said(x: float | None) -> str:
    return "—" if x is None else f"{x:.2f}"


def pair_budgets(rows: list[dict]) -> list[dict]:
    """The reference first, then each method's rows by budget (the reference's method first); every row that has capture times and
    a shorter budget of its method with them gets its paired difference to the longest such one:
    diff_to_shorter_budget (this team - that team, steps; negative: the longer run captures sooner),
    its 95% CI half-width, and shorter_budget_episodes (that team's training episodes)."""
    first = sorted(rows, key=lambda r: not r.get("reference"))  # the reference's method, then by appearance
    order = {a: i for i, a in enumerate(dict.fromkeys(r["algorithm"] for r in first))}
    out = sorted(rows, key=lambda r: (not r.get("reference"), order[r["algorithm"]], r["train_episodes"] or 0))
    keys = ("diff_to_shorter_budget", "diff_to_shorter_budget_ci95", "shorter_budget_episodes")
    for r in out:
        for k in keys:
            r.pop(k, None)
        shorter = [
            q
            for q in out
            if q["algorithm"] == r["algorithm"]
            and "capture_times" in q
            and (q["train_episodes"] or 0) < (r["train_episodes"] or 0)
        ]
        if "capture_times" in r and shorter:
            q = max(shorter, key=lambda q: q["train_episodes"])
            dm, dh = mean_ci95(np.asarray(r["capture_times"], float) - np.asarray(q["capture_times"], float))
            r.update(zip(keys, (round(dm, 3), round(dh, 3), q["train_episodes"]), strict=True))
    return out


def _dumps(d: dict) -> str:
    """JSON, indented, with each row's capture times on one line."""
    text = json.dumps(d, indent=1)
    return re.sub(r"\[\n\s*(-?\d+(?:,\n\s*-?\d+)*)\n\s*\]", lambda m: "[" + re.sub(r"\s+", " ", m.group(1)) + "]", text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("teams", nargs="+", type=Path, help="snapshot directories to compare")
    ap.add_argument("--reference", type=Path, required=True, help="the snapshot the differences are taken to")
    ap.add_argument("--env", default="office", choices=["office", "museum", "ward"])
    ap.add_argument("--robots", type=int, default=4)
    ap.add_argument("--episodes", type=int, default=1500)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, help="write the rows as JSON here")
    ap.add_argument("--add", action="store_true", help="add the teams' rows to the --out file (module docstring)")
    args = ap.parse_args()
    setup = {"map": args.env, "robots": args.robots, "episodes": args.episodes, "seed": args.seed}
    old_rows: list[dict] = []
    if args.add:
        if args.out is None or not args.out.is_file():
            ap.error("--add needs --out naming the JSON file that an earlier run wrote")
        try:
            old = json.loads(args.out.read_text())
            old_rows = list(old["rows"])
            old_setup = {k: old[k] for k in setup}
        except (ValueError, KeyError, TypeError) as e:
            ap.error(f"{args.out} is not a plateau file written by this script: {e}")
        if old_setup != setup:
            ap.error(f"{args.out} was flown with {old_setup}, this run with {setup}: the rows would not be paired")
    missing = [str(p) for p in (args.reference, *args.teams) if not (p / "policy.json").is_file()]
    if missing:  # before any team is flown: a typo should not cost the others' minutes
        ap.error(f"not a snapshot directory (no policy.json): {', '.join(missing)}")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    ref_info, ref = fly(args.reference, args.env, args.robots, args.episodes, args.seed)
    m, h = mean_ci95(ref)
    rows = [
        {
            **ref_info,
            "reference": True,
            "mean_capture_time": round(m, 3),
            "ci95_halfwidth": round(h, 3),
            "capture_times": ref.astype(int).tolist(),
        }
    ]
    if args.add:
        before = next((r for r in old_rows if r.get("reference")), {})
        same = (
            before["capture_times"] == ref.astype(int).tolist()
            if "capture_times" in before
            else (before.get("mean_capture_time"), before.get("ci95_halfwidth")) == (round(m, 3), round(h, 3))
        )
        if not same:
            ap.error(
                f"the reference {args.reference} captures in {m:.3f} ± {h:.3f} on these episodes, the one in "
                f"{args.out} ({before.get('team')}) in {before.get('mean_capture_time')} ± "
                f"{before.get('ci95_halfwidth')}: not the same team, so the paired differences would not compare"
            )
        # the file's reference row stays as it was written (its team's training record included)
        rows = [
            {**before, "capture_times": ref.astype(int).tolist()},
            *(r for r in old_rows if not r.get("reference")),
        ]
    print(f"{args.env.upper()} N={args.robots}, {args.episodes} episodes, seed {args.seed}")
    print(f"  reference {ref_info['algorithm']:<7} {ref_info['train_episodes']:>9,} episodes  {m:6.2f} ± {h:.2f}")
    for path in args.teams:
        info, t = fly(path, args.env, args.robots, args.episodes, args.seed)
        m, h = mean_ci95(t)
        dm, dh = mean_ci95(t - ref)
        rows = [r for r in rows if r.get("reference") or r["team"] != info["team"]]
        rows.append(
            {
                **info,
                "mean_capture_time": round(m, 3),
                "ci95_halfwidth": round(h, 3),
                "diff_to_reference": round(dm, 3),
                "diff_to_reference_ci95": round(dh, 3),
                "capture_times": t.astype(int).tolist(),
            }
        )
        print(
            f"  {info['algorithm']:<17} {info['train_episodes']:>9,} episodes  {m:6.2f} ± {h:.2f}   "
            f"paired vs reference {dm:+.2f} ± {dh:.2f}   training curve {_said(info['curve_at_half'])} at half, "
            f"{_said(info['curve_at_end'])} at the end"
        )
    rows = pair_budgets(rows)
    for r in rows:
        if "diff_to_shorter_budget" in r:
            print(
                f"  {r['algorithm']} {r['train_episodes']:,} - {r['shorter_budget_episodes']:,} episodes, paired: "
                f"{r['diff_to_shorter_budget']:+.2f} ± {r['diff_to_shorter_budget_ci95']:.2f}"
            )
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(_dumps({**setup, "rows": rows}) + "\n")
        print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
