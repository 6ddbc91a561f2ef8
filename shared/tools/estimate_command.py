"""`mures estimate`: the target's motion model (Gamma_hat, b0) from episode records, by EM or the
paper's Eq. 8."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

from shared.core.choices import ESTIMATORS
from shared.core.files import atomic_write
from shared.core.models import parse_target
from shared.core.records import read_jsonl
from shared.engine.estimate import collect_missions, em, eq8, mean_row_tv
from shared.learning.config import positive_int
from shared.tools.cli_args import CliError, add_map_args, graph_of, positive_number


def cmd_estimate(args: argparse.Namespace) -> int:
    # EM on 1000 WARD missions (benchmarks/bench_estimate.py, a quiet 2-core machine): 13.7-14.4 s in
    # one process, 8.7-8.9 s shared by two (--threads 2); torch's own threads gained little (18.5 s on
    # two: each small operation waits for the other thread at its end), and lost much under load
    torch.set_num_threads(1)
    graph = graph_of(args)
    if not Path(args.episodes).is_file():
        raise CliError(f"episode file {args.episodes!r} does not exist")
    t0 = time.perf_counter()
    if args.tick is not None and args.method != "em":
        raise CliError("--tick goes with --method em")
    data = collect_missions(read_jsonl(args.episodes), graph, capture_aware=args.method == "em", tick_s=args.tick)
    skipped = sum(data.skipped.values())
    reasons = ", ".join(f"{k}: {v}" for k, v in sorted(data.skipped.items())) or "none"
    print(
        f"read {data.used_records} records in {len(data.length)} missions; skipped {skipped} ({reasons})",
        file=sys.stderr,
    )
    if data.impossible:
        shown = ", ".join(data.impossible[:10]) + (
            f" and {len(data.impossible) - 10} more" if len(data.impossible) > 10 else ""
        )
        print(
            f"set aside {len(data.impossible)} missions that no path of the target explains "
            f"under their sensor: {shown}",
            file=sys.stderr,
        )
    if len(data.length) == 0:
        raise CliError("no usable episode records: nothing estimated, nothing written")
    last = [0.0]

    def progress(it: int, ll: float) -> None:
        now = time.perf_counter()
        if now - last[0] > 2.0:
            last[0] = now
            print(f"  EM pass {it}: log-likelihood {ll:.3f}", file=sys.stderr)

    if args.method == "em":
        est = em(
            graph,
            data,
            max_iter=args.max_iter,
            tol=args.tol,
            pseudo_count=args.pseudo_count,
            b0_pseudo_count=args.b0_pseudo_count,
            progress=progress,
            workers=args.threads,
        )
    else:
        est = eq8(graph, data, rounds=args.rounds)
    out = est.to_json(graph, data)
    if args.tick is not None:
        out["tick_s"] = args.tick  # Gamma_hat is per tick of this many seconds
    if args.truth:
        truth = parse_target(graph, args.truth)
        out["mean_row_tv_to_truth"] = mean_row_tv(est.model, truth)
    path = atomic_write(args.out, json.dumps(out) + "\n")
    msg = (
        f"{args.method}: {est.iterations} passes, converged={est.converged}, "
        f"{time.perf_counter() - t0:.1f} s; wrote {path}"
    )
    if est.log_likelihood:
        msg += f"; log-likelihood {est.log_likelihood[-1]:.3f}"
    if args.truth:
        msg += f"; mean row TV to truth {out['mean_row_tv_to_truth']:.4f}"
    print(msg)
    return 0


def add_estimate_command(sub: Any) -> None:
    """`mures estimate` and its parser."""
    p = sub.add_parser("estimate", help="estimate Gamma_hat and b0 from episode records")
    add_map_args(p)
    p.add_argument("--episodes", required=True, metavar="FILE.jsonl", help="episode records (JSON Lines)")
    p.add_argument("--out", required=True, metavar="model.json")
    p.add_argument("--method", choices=ESTIMATORS, default="em", help="EM (default) or the paper's Eq. 8")
    p.add_argument("--max-iter", type=positive_int, default=1000, help="EM forward-backward passes at most")
    p.add_argument("--tol", type=float, default=1e-6, help="EM relative log-likelihood tolerance")
    p.add_argument(
        "--pseudo-count",
        type=float,
        default=0.0,
        help="Dirichlet prior: expected transitions added to each entry of Gamma_hat's support (default 0: "
        "maximum likelihood; the training server uses 1)",
    )
    p.add_argument(
        "--b0-pseudo-count",
        type=float,
        default=0.0,
        help="Dirichlet prior: expected starts added to every node of b0 (default 0; the training server uses 1)",
    )
    p.add_argument(
        "--tick",
        type=positive_number,
        default=None,
        metavar="S",
        help="fit Gamma_hat per tick of S seconds from the records' times (steps[k].time_s: each reading at the "
        "tick it was made, none in between; records without times are skipped), instead of per step",
    )
    p.add_argument("--rounds", type=positive_int, default=1, help="Eq. 8 rounds (filter <-> Eq. 8)")
    p.add_argument("--truth", metavar="MODEL", help="a known model (lazy:STAY, uniform, or .json): report the TV")
    p.add_argument(
        "--threads",
        type=positive_int,
        default=1,
        help="cores EM runs on: its missions shared by that many processes, each on one torch thread "
        "(default 1; the estimate differs only by rounding, about 1e-9)",
    )
    p.set_defaults(func=cmd_estimate)
