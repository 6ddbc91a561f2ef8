"""`mures evaluate` and `mures simulate`: a searcher flown in simulation, its capture-time
statistics or its missions' episode records."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from shared.core.choices import TEAM_SEARCHERS
from shared.core.clock import TICK_S, TravelTimes
from shared.core.files import atomic_write
from shared.core.graph import Graph
from shared.core.models import Sensor, TargetModel, load_model_file
from shared.core.snapshot_format import SnapshotError
from shared.engine.evaluate import episode_records, evaluate
from shared.engine.searchers import Searcher
from shared.learning.config import positive_int, whole_number
from shared.registry import TeamFlight, searcher_factory
from shared.tools.cli_args import (
    CliError,
    add_continuous_args,
    add_world_args,
    building_of,
    device_of,
    positive_number,
    probability,
    world_of,
)


def _searcher_factory(
    args: argparse.Namespace,
    graph: Graph,
    target: TargetModel,
    sensor: Sensor,
    device: torch.device,
    team: TeamFlight | None = None,
    clock: TravelTimes | None = None,
) -> Callable[[int], Searcher]:
    """seed -> searcher for evaluate(); checks the name (and loads a snapshot) once, before any simulation."""
    try:
        return searcher_factory(
            args.searcher,
            graph,
            target,
            sensor,
            args.robots,
            device,
            note=lambda text: print(f"mures: note: {text}", file=sys.stderr),
            team=team,
            clock=clock,
        )
    except SnapshotError:
        raise
    except ValueError as exc:
        raise CliError(str(exc)) from None


def _snapshot_detection(args: argparse.Namespace) -> str | None:
    """A policy is evaluated with the detection it was trained for unless --detection says otherwise
    (None: not a policy, the map's default)."""
    if args.searcher.startswith("policy:") and args.detection is None:
        meta = Path(args.searcher.removeprefix("policy:")) / "policy.json"
        try:
            return str(json.loads(meta.read_text(encoding="utf-8"))["sensor"]["detection"])
        except (OSError, ValueError, KeyError, TypeError):
            return "node"  # load_snapshot reports the problem
    return None


def _team_flight(args: argparse.Namespace, graph: Graph) -> TeamFlight | None:
    """The team flight the flags ask for, or None (the snapshot flown as the batched searcher)."""
    given = (args.team_searcher, args.link_loss, args.link_delay, args.fallback_after, args.team_model)
    if all(v is None for v in given):
        return None
    return TeamFlight(
        args.team_searcher,
        args.link_loss or 0.0,
        args.link_delay or 0,
        args.fallback_after,
        load_model_file(graph, args.team_model) if args.team_model else None,
    )


def _clock(args: argparse.Namespace, graph: Graph) -> TravelTimes | None:
    """`mures evaluate --clock`'s travel times, or None; a CliError names what is wrong."""
    if not args.clock:
        if args.tick is not None:
            raise CliError("--tick sets the clock of --clock's travel times: give --clock too")
        return None
    if args.world:
        raise CliError("--clock runs the engine on travel times; --world flies the continuous world: give one")
    try:
        return TravelTimes.of(graph, args.speed, args.tick or TICK_S)
    except ValueError as exc:
        raise CliError(f"--clock: {exc}") from None


def cmd_evaluate(args: argparse.Namespace) -> int:
    if args.world and not args.clock:
        return _evaluate_continuous(args)
    graph, target, sensor = world_of(args, _snapshot_detection(args))
    clock = _clock(args, graph)
    if clock is not None:  # the target moves once a tick
        target = clock.model(target)
    device = device_of(args.device)
    team = _team_flight(args, graph)
    factory = _searcher_factory(args, graph, target, sensor, device, team, clock)
    res = evaluate(
        graph, target, sensor, args.robots, factory, episodes=args.episodes, seed=args.seed, device=device, clock=clock
    )
    summary: dict[str, Any] = {
        "map": graph.name,
        "graph_id": graph.graph_id,
        "robots": args.robots,
        "searcher": args.searcher,
        "target": target.kind,
        "sensor": sensor.to_json(),
        **res.summary(),
        "wall_seconds": round(res.wall_seconds, 3),
    }
    if clock is not None:  # capture times above in ticks; in seconds here
        summary["clock"] = clock.summary()
        summary["mean_capture_time_s"] = summary["mean_capture_time"] * clock.tick_s
        summary["ci95_halfwidth_s"] = summary["ci95_halfwidth"] * clock.tick_s
    if team is not None:
        flown = sum(team.steps.values())
        summary["team"] = {
            "searcher": team.searcher,
            "link_loss": team.link_loss,
            "link_delay": team.link_delay,
            "fallback_after": team.fallback_after,
            "team_steps": team.steps["team"],
            "partial_steps": team.steps["partial"],
            "own_steps": team.steps["own"],
            "coordinated_share": (team.steps["team"] + team.steps["partial"]) / flown if flown else None,
        }
    if args.json:
        print(json.dumps(summary))
    else:
        lo, hi = summary["ci95"]
        unit = "" if clock is None else " ticks"
        print(
            f"{graph.name}, N={args.robots}, searcher={args.searcher}, "
            f"{summary['episodes']} episodes, seed {args.seed}"
            + ("" if clock is None else f", on the clock at {args.speed:g} m/s (ticks of {clock.tick_s:g} s)")
            + "\n"
            f"  mean_capture_time         {summary['mean_capture_time']:.2f}{unit}  (95% CI {lo:.2f} .. {hi:.2f})\n"
            + (
                ""
                if clock is None
                else f"  mean_capture_time_s       {summary['mean_capture_time_s']:.1f} s  "
                f"(95% CI half-width {summary['ci95_halfwidth_s']:.1f} s)\n"
            )
            + f"  median                    {summary['median']:.1f}{unit}\n"
            f"  censored_fraction         {summary['censored_fraction']:.4f}  "
            f"(T_max = {3 * graph.n if clock is None else clock.t_max(graph.n)}{unit})\n"
            f"  false_alarms_per_episode  {summary['false_alarms_per_episode']:.3f}\n"
            + (
                f"  robot-steps on the plan   {summary['team']['team_steps']:,} complete, "
                f"{summary['team']['partial_steps']:,} partial, {summary['team']['own_steps']:,} on their own\n"
                if team is not None
                else ""
            )
            + f"  wall_seconds              {summary['wall_seconds']:.2f}"
        )
    return 0


def cmd_simulate(args: argparse.Namespace) -> int:
    graph, target, sensor = world_of(args)
    device = device_of(args.device)
    factory = _searcher_factory(args, graph, target, sensor, device)
    res = evaluate(
        graph, target, sensor, args.robots, factory, episodes=args.missions, seed=args.seed, device=device, record=True
    )
    out = Path(args.out)
    lines = [
        json.dumps(rec, separators=(",", ":")) + "\n"
        for rec in episode_records(graph, res, sensor, fleet=args.fleet, mission_prefix=f"sim-{args.seed}")
    ]
    atomic_write(out, "".join(lines))
    written = len(lines)
    if args.truth:
        atomic_write(args.truth, json.dumps({**target.to_json(graph), "kind": target.kind}) + "\n")
    s = res.summary()
    print(
        f"wrote {written} records of {args.missions} missions to {out} "
        f"(mean capture time {s['mean_capture_time']:.2f}, censored {s['censored_fraction']:.3f})"
    )
    return 0


def _evaluate_continuous(args: argparse.Namespace) -> int:
    """`mures evaluate --world MAP.yaml`: the searcher flown in the continuous world of the map the
    --graph was imported from (shared/world/continuous.py); capture time in seconds."""
    from shared.engine.evaluate import mean_ci95
    from shared.world.continuous import SEARCHERS, fly

    if args.searcher not in SEARCHERS:
        raise CliError(
            f"--world flies {', '.join(SEARCHERS)} (the trained policies fly in it as agents: `mures fleet-sim "
            f"--world`), got {args.searcher!r}"
        )
    graph, target, sensor = world_of(args)
    world = building_of(args, graph)
    flight = fly(
        world,
        args.searcher,
        args.robots,
        args.episodes,
        sensor=sensor,
        speed=args.speed,
        dwell_s=args.stay_seconds,
        target_speed=args.target_speed,
        target_dwell_s=args.target_dwell,
        max_s=args.max_seconds,
        seed=args.seed,
        target_model=None if args.target == "uniform" else target,
        stop_prob=args.stop_prob,
        stop_s=args.stop_seconds,
    )
    mean, half = mean_ci95(flight.capture_s)
    summary = {
        "map": graph.name,
        "graph_id": graph.graph_id,
        "world": str(args.world),
        "robots": args.robots,
        "searcher": args.searcher,
        "sensor": {**sensor.to_json(), "detection": f"within {args.range:g} m in line of sight"},
        **({"plan_detection": sensor.detection} if args.searcher == "fhpe-sa" else {}),  # D(p) of the plan's belief
        "continuous": {
            "speed_m_s": args.speed,
            "stay_s": args.stay_seconds,
            "sensor_range_m": args.range,
            "target_speed_m_s": args.target_speed,
            "target_dwell_s": args.target_dwell,
            "target": target.kind,
            "stop_prob": args.stop_prob,
            "stop_s": args.stop_seconds,
            "max_seconds": args.max_seconds,
        },
        "episodes": args.episodes,
        "seed": args.seed,
        "mean_capture_time_s": mean,
        "ci95_halfwidth_s": half,
        "captured_fraction": float(flight.captured.mean()),
        "decisions_per_episode": flight.decisions / args.episodes,
        "wall_seconds": round(flight.wall_s, 3),
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"{args.searcher} on {graph.name} in the continuous world, N={args.robots}, {args.episodes} episodes: "
            f"mean capture time {mean:.1f} s ± {half:.1f} (95% CI), captured {100 * summary['captured_fraction']:.1f}% "
            f"within {args.max_seconds:g} s"
        )
    return 0


def add_sim_commands(sub: Any) -> None:
    """`mures evaluate` and `mures simulate`, each with its parser."""
    p = sub.add_parser("evaluate", help="evaluate a searcher in simulation and print capture-time statistics")
    add_world_args(p)
    p.add_argument(
        "--searcher",
        required=True,
        help="random, greedy, fhpe, fhpe-sa, milp, d-milp, oracle, general (the shipped general policy), "
        "general:DIR or policy:DIR",
    )
    p.add_argument("--episodes", type=positive_int, default=1500, help="episodes (default 1500)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    team = p.add_argument_group(
        "team flight",
        "fly a policy:DIR as robot agents fly it in a team (their own decision code, shared/core/team.py), "
        "over a simulated network; any of these flags turns it on",
    )
    team.add_argument(
        "--team-searcher",
        choices=(*TEAM_SEARCHERS, "none"),
        help="the team's searcher (default: the snapshot's own; none: each robot on its own policy)",
    )
    team.add_argument(
        "--link-loss", type=probability, metavar="P", help="each observation message is lost with probability P"
    )
    team.add_argument("--link-delay", type=whole_number, metavar="K", help="each message arrives K steps late")
    team.add_argument(
        "--team-model",
        metavar="model.json",
        help="the (Gamma_hat, b0) the team's collective belief and plan use (mures estimate writes one; "
        "default the snapshot's)",
    )
    team.add_argument(
        "--fallback-after",
        type=positive_int,
        metavar="K",
        help="incomplete steps in a row before a robot flies its own policy (default: never while a teammate is "
        "heard: the team's plan on what has come)",
    )
    world = add_continuous_args(
        p,
        "fly random, greedy, sweep or fhpe-sa in the building's map instead of the step model "
        "(docs/continuous-world.md): "
        "robots and target move along free space in metres and seconds, a robot sees within --range in line of sight",
    )
    world.add_argument(
        "--max-seconds", type=positive_number, default=1800.0, metavar="S", help="a mission's end (1800)"
    )
    clock = p.add_argument_group(
        "travel times",
        "the engine on the mission clock (docs/continuous-world.md, 'Training on the clock'): each move takes its "
        "edge's length (the graph's edge_lengths_m) over --speed in whole ticks, the target moves once a tick, "
        "capture times in ticks and seconds; random, greedy and policy:DIR (a team trained with or without --speed; "
        "with --team-searcher, flown as robot agents fly it on the mission clock)",
    )
    clock.add_argument("--clock", action="store_true", help="evaluate on travel times at --speed")
    clock.add_argument("--tick", type=positive_number, metavar="S", help="the clock's tick in seconds (1)")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser("simulate", help="simulate missions and write their episode records (JSON Lines)")
    add_world_args(p)
    p.add_argument("--searcher", default="random", help="searcher that drives the robots (default random)")
    p.add_argument("--missions", type=positive_int, required=True, help="number of missions")
    p.add_argument("--fleet", default="default", help="fleet name written into the records")
    p.add_argument("--out", required=True, metavar="FILE.jsonl", help="output records")
    p.add_argument("--truth", metavar="FILE", help="also write the true target model as model.json")
    p.set_defaults(func=cmd_simulate)
