"""The `mures` command line (docs/SPEC.md section 7).

    mures evaluate  (--env office|museum | --graph FILE) --robots N --searcher NAME ...
    mures simulate  (--env | --graph) --robots N --missions M --out FILE.jsonl ...
    mures estimate  (--env | --graph) --episodes FILE.jsonl --out model.json ...
    mures train     (--env | --graph) --robots N --out DIR [--beta 0.5] [--episodes 400000] ...
    mures map       (--env | --graph);  mures map import MAP.yaml --out GRAPH.json ...
    mures fleet-sim | world | experiment | report | snapshot convert | snapshot combine ...

Each family of commands adds its own parser: sim_commands (evaluate, simulate), estimate_command,
train_command, fleet_commands (fleet-sim, world), experiment_commands (experiment, report),
map_commands (map, map import); snapshot is here. Bad arguments and bad input files end with one
line ``mures: error: ...`` and exit status 2.
"""

from __future__ import annotations

import argparse
import sys

from shared.core.graph import GraphError
from shared.core.models import ModelError
from shared.core.snapshot_format import SnapshotError
from shared.engine.estimate import EMWorkerError
from shared.tools.cli_args import CliError, add_map_args
from shared.tools.estimate_command import add_estimate_command
from shared.tools.experiment_commands import add_experiment_commands
from shared.tools.fleet_commands import add_fleet_commands
from shared.tools.general_command import add_general_command
from shared.tools.map_commands import add_map_commands
from shared.tools.sim_commands import add_sim_commands
from shared.tools.train_command import add_train_command


# ---------------------------------------------------------------------- snapshot convert
def cmd_snapshot_convert(args: argparse.Namespace) -> int:
    from shared.learning.team_snapshot import convert_snapshot

    for d in args.dirs:
        done = convert_snapshot(d)
        print(f"{d}: {'converted to weights.safetensors' if done else 'already in the numpy-readable format'}")
    return 0


def cmd_snapshot_combine(args: argparse.Namespace) -> int:
    from shared.core.snapshot_format import combine_teams
    from shared.tools.cli_args import graph_of

    snap, gaps = combine_teams(args.main, args.teams, args.out, graph_of(args), args.switch_to)
    sizes = ", ".join(str(k) for k in snap.team_sizes)
    print(f"wrote {args.out}: {args.main}'s team for {snap.robots} robots, with teams for {sizes} robots")
    for where, gap in gaps.items():
        if gap > 1e-9:
            print(
                f"note: {where}'s belief model differs from {args.main}'s (largest |Gamma_hat| gap {gap:.3g}); "
                "its robots fly on the latter's"
            )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mures", description="MuRES fleet: multirobot search for a moving target")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    add_sim_commands(sub)
    add_estimate_command(sub)
    add_train_command(sub)
    add_general_command(sub)
    add_fleet_commands(sub)

    add_experiment_commands(sub)

    add_map_commands(sub)

    p = sub.add_parser("snapshot", help="policy snapshot tools")
    snap_sub = p.add_subparsers(dest="snapshot_command", required=True, metavar="ACTION")
    c = snap_sub.add_parser(
        "convert", help="rewrite an older snapshot's weights.pt as weights.safetensors (the same values)"
    )
    c.add_argument("dirs", nargs="+", metavar="DIR", help="snapshot directories")
    c.set_defaults(func=cmd_snapshot_convert)
    c = snap_sub.add_parser(
        "combine",
        help="one snapshot holding a team per team size: MAIN's and each TEAM's (a mission of k robots flies the "
        "team built for k; give it to training-server --init-policy)",
    )
    add_map_args(c)
    c.add_argument("main", metavar="MAIN", help="the snapshot whose team, model and settings the result keeps")
    c.add_argument("teams", nargs="+", metavar="TEAM", help="snapshots of teams for other team sizes")
    c.add_argument("--out", required=True, metavar="DIR", help="snapshot directory to write")
    c.add_argument(
        "--switch-to",
        type=int,
        nargs="*",
        metavar="K",
        help="the team sizes robots left switch to when teammates drop out mid-mission (default: every team; "
        "none given: never; a training run decides this by measurement, docs/operating.md)",
    )
    c.set_defaults(func=cmd_snapshot_combine)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except (CliError, GraphError, ModelError, SnapshotError) as exc:
        print(f"mures: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"mures: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except EMWorkerError as exc:  # not the input's fault: a worker process was killed
        print(f"mures: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mures: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
