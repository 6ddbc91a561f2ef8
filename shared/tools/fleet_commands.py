"""`mures fleet-sim` and `mures world`: the fleet on loopback, and the simulated world alone."""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path
from typing import Any

from shared.core.choices import DETECTIONS
from shared.core.clock import default_time_limit_s
from shared.core.wire import add_zenoh_arguments
from shared.learning.config import positive_int, seconds, whole_number
from shared.learning.team_snapshot import load_snapshot
from shared.tools.cli_args import (
    CliError,
    add_continuous_args,
    add_map_args,
    add_world_args,
    building_of,
    eta_arg,
    positive_number,
    probability,
    world_of,
)


def cmd_fleet_sim(args: argparse.Namespace) -> int:
    from shared.core.http import ApiError
    from shared.tools.fleetsim import run_fleet_sim

    if args.missions is None:
        if not args.serve:
            raise CliError("fleet-sim: give --missions N, or --serve to keep the fleet up for the console")
        args.missions = 0
    elif args.missions == 0 and not args.serve:
        raise CliError("fleet-sim: --missions must be at least 1 (0 only with --serve)")
    graph, target, sensor = world_of(args)
    graph_args = ["--env", args.env] if args.env else ["--graph", str(Path(args.graph).resolve())]
    if args.server and not (args.zenoh_connect and args.token_file):
        raise CliError("--server needs --zenoh-connect ENDPOINT and --token-file FILE (the operator token)")
    # every K missions: the server's floor of missions before a run (50) lowered to the K flown since the last
    retrain: dict[str, Any] = {"episodes": args.retrain_episodes, "min_missions": max(1, args.retrain_every)}
    named = args.init_policy in (None, "general", "untrained")  # the server's own first versions, else a snapshot
    init = args.init_policy if named else str(Path(args.init_policy).resolve())
    server_extra = [] if init is None else ["--init-policy", init]
    if args.map_image:  # the server checks it against the graph, in one line, before the fleet starts
        if not args.graph:
            raise CliError("fleet-sim: --map-image goes with --graph (a graph made by `mures map import`)")
        server_extra += ["--map-image", str(Path(args.map_image).resolve())]
    if args.step_timeout <= 0:
        raise CliError("fleet-sim: --step-timeout must be more than 0 seconds")
    if (args.max_steps is not None or args.max_seconds is not None) and args.kill:
        raise CliError("fleet-sim: --max-steps and --max-seconds go without --kill")
    if args.max_seconds is not None and not args.world:
        raise CliError("fleet-sim: --max-seconds goes with --world (the continuous world keeps the mission clock)")
    if args.team_clock is None:  # the mission clock where the world has one
        args.team_clock = "seconds" if args.world else "steps"
    if args.kill >= args.robots:
        raise CliError(f"fleet-sim: --kill {args.kill} leaves no robot of {args.robots} to search")
    agent_extra = ["--link-loss", str(args.link_loss)] if args.link_loss else []
    if args.team_clock == "seconds" and not args.world:
        raise CliError("fleet-sim: --team-clock seconds goes with --world (the continuous world keeps the clock)")
    # said either way: an agent left on auto would take the continuous world's clock
    agent_extra += ["--team-clock", args.team_clock, "--speed", str(args.speed)]
    init_clock = None if named else load_snapshot(args.init_policy, graph).clock
    if args.world and (args.team_clock == "seconds" or init_clock is not None):
        retrain["speed"] = args.speed  # the fleet flies on the clock: retrain on the map's travel times
    continuous = {}
    limits: dict[str, Any] = {} if args.max_steps is None else {"max_steps": args.max_steps}
    if args.world:
        if args.step_delay:
            raise CliError("fleet-sim: --step-delay is the step world's; --world moves robots at --speed")
        continuous = {"building": building_of(args, graph), "motion": motion_of(args, target)}
        if args.max_seconds is not None:
            limits["max_seconds"] = args.max_seconds
        elif args.max_steps is None:  # the step limit's horizon on the clock: 3 n moves of the median edge
            limits["max_seconds"] = default_time_limit_s(graph, args.speed)
    try:
        res = run_fleet_sim(
            graph,
            graph_args,
            target,
            sensor,
            args.robots,
            args.missions,
            args.seed,
            args.retrain_every,
            retrain,
            Path(args.workdir) if args.workdir else None,
            serve=args.serve,
            retrains=args.retrains,
            server=args.server,
            zenoh_connect=args.zenoh_connect,
            token_file=args.token_file,
            agent_token_file=args.agent_token_file,
            step_delay=args.step_delay,
            step_timeout=args.step_timeout,
            kill=args.kill,
            kill_by=args.kill_by,
            limits=limits,
            server_extra=server_extra or None,
            agent_extra=agent_extra or None,
            **continuous,
        )
    except (ValueError, TimeoutError, RuntimeError, ApiError) as exc:
        raise CliError(f"fleet-sim: {exc}") from None
    except OSError as exc:  # urllib's URLError included
        raise CliError(
            f"fleet-sim: cannot reach the server {args.server or ''}: {getattr(exc, 'reason', exc)}"
        ) from None
    return _print_fleet_sim(args, res)


def _print_fleet_sim(args: argparse.Namespace, res: dict[str, Any]) -> int:
    if args.json:
        print(json.dumps(res, indent=1))
        return 0
    lo, hi = res["ci95"]
    print(
        f"missions: {res['missions']} on {res['map']} with {res['robots']} robots (seed {res['seed']}), "
        f"{res['wall_seconds']:.1f} s"
    )
    if not res["missions"]:
        print("no mission was completed: no capture time to report")
        return 0
    print(
        f"mean capture time: {res['mean_capture_time']:.2f} steps (95% CI {lo:.2f}..{hi:.2f}), "
        f"censored {100 * res['censored_fraction']:.1f}%"
    )
    if "mean_capture_time_s" in res:
        print(f"mean capture time in seconds: {res['mean_capture_time_s']:.1f} s ± {res['ci95_halfwidth_s']:.1f} s")
    if res.get("coordinated_share") is not None:
        print(f"decisions on the team's plan: {100 * res['coordinated_share']:.1f}%")
    for v, d in res["by_policy_version"].items():
        print(
            f"  policy version {v}: {d['missions']} missions, {d['mean_capture_time']:.2f} "
            f"± {d['ci95_halfwidth']:.2f} steps, censored {100 * d['censored_fraction']:.1f}%"
        )
    for t in res.get("trials", []):
        if "canary_mean" in t:
            print(
                f"  trial of version {t['version']}: {t['state']}, {t['canary_mean']:.2f} vs {t['baseline_mean']:.2f} "
                f"steps for version {t['baseline']} on {t['pairs']} pairs (paired difference "
                f"{t['mean_difference']:+.2f} ± {t['ci95']:.2f})"
            )
    print(
        f"episodes stored: {res['episodes_stored']}; rejected: {sum(res['episodes_rejected'].values())}; "
        f"policy versions used: {', '.join(map(str, res['policy_versions_used']))}"
        + (
            f"; lockstep step median {res['lockstep_step_ms_median']:.2f} ms"
            if res["lockstep_step_ms_median"] is not None
            else ""
        )
    )
    return 0


# ---------------------------------------------------------------------- world
def cmd_world(args: argparse.Namespace) -> int:
    """The simulated world alone, for agents started by hand with ``--backend sim``: it owns the
    hidden target of every mission the server starts and answers the agents' detections."""
    import threading

    import zenoh

    from shared.core.wire import DEFAULT_ZENOH_ENDPOINT, check_id, client_config
    from shared.tools.world import World

    graph, target, sensor = world_of(args)
    building = building_of(args, graph) if args.world else None
    if args.world and args.step_delay:
        raise CliError("world: --step-delay is the step world's; --world moves robots at --speed")
    for ep in args.zenoh_connect or []:
        if "/" not in ep or not ep.split("/", 1)[0].isalnum():
            raise CliError(f"world: --zenoh-connect {ep!r} is not a Zenoh endpoint such as tcp/127.0.0.1:7447")
    connect = args.zenoh_connect or [DEFAULT_ZENOH_ENDPOINT]
    try:
        check_id("fleet", args.fleet)
        conf = client_config(args, args.zenoh_user, connect)
        session = zenoh.open(conf)
    except (ValueError, OSError, zenoh.ZError) as exc:
        hint = (
            "; a secured (TLS) router needs --zenoh-ca and the kit's world credentials (training-server kit --world: "
            "--zenoh-user world --zenoh-password-file KIT/world/zenoh-password)"
            if any(ep.startswith("tls/") for ep in connect) and not args.zenoh_password_file
            else ""
        )
        raise CliError(f"world: {str(exc).split(' at /')[0]}{hint}") from None
    import logging

    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(levelname)s world: %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_a: stop.set())
    signal.signal(signal.SIGINT, lambda *_a: stop.set())
    if building is not None:
        from shared.tools.timed_world import TimedWorld

        world: World = TimedWorld(session, args.fleet, building, sensor, motion_of(args, target), args.step_timeout)
    else:
        world = World(
            session, args.fleet, graph, target, sensor, step_timeout=args.step_timeout, step_delay=args.step_delay
        )
    how = (
        f"in the continuous world of {args.world} (robots at {args.speed:g} m/s, sensor range {args.range:g} m)"
        if args.world
        else "in steps"
    )
    print(
        f"world: simulating fleet {args.fleet!r} on {graph.name} (n={graph.n}) {how}, target {args.target}, sensor "
        f"eta_fn={sensor.eta_fn} eta_fp={sensor.eta_fp} {sensor.detection}; connected to "
        f"{args.zenoh_config or ', '.join(connect)}; Ctrl-C stops it",
        file=sys.stderr,
        flush=True,
    )
    try:
        stop.wait()
    finally:
        world.close()
        session.close()
    return 0


CONTINUOUS_ABOUT = (
    "with --world MAP.yaml (the map --graph was imported from) the agents fly in the continuous world: each move "
    "takes its travel time along free space, each robot on its own clock, capture times in seconds "
    "(docs/continuous-world.md)"
)


def motion_of(args: argparse.Namespace, target: Any) -> Any:
    """The continuous world's Motion from the command's flags; ``target``: --target's model, which
    decides where the target goes after each dwell unless it is the uniform walk."""
    from shared.tools.timed_world import Motion

    return Motion(
        speed=args.speed,
        speed_cv=args.speed_cv,
        stop_prob=args.stop_prob,
        stop_s=args.stop_seconds,
        stay_s=args.stay_seconds,
        target_speed=args.target_speed,
        target_dwell_s=args.target_dwell,
        target=None if args.target == "uniform" else target,
    )


def add_fleet_commands(sub: Any) -> None:
    """The fleet-sim and world subcommands of `mures` (``sub``: its subparsers)."""
    p = sub.add_parser("fleet-sim", help="run server, simulated world and N robot agents on loopback; fly missions")
    add_world_args(p)
    p.add_argument("--missions", type=whole_number, default=None, help="missions to fly (0 with --serve)")
    p.add_argument(
        "--serve",
        action="store_true",
        help="then keep the fleet up for the operator console (http://HOST:PORT/) until Ctrl-C",
    )
    p.add_argument(
        "--retrain-every",
        type=int,
        default=0,
        metavar="K",
        help="retrain over HTTP every K missions, on the records of at least K missions (with --world on the "
        "clock: on the map's travel times at --speed, EM per tick from the records' times)",
    )
    p.add_argument("--retrain-episodes", type=positive_int, default=20_000, help="CE-PG episodes per retrain")
    p.add_argument(
        "--retrains", type=positive_int, default=None, metavar="R", help="retrain at most R times (default: no limit)"
    )
    p.add_argument(
        "--init-policy",
        metavar="DIR",
        help="the server's first policy: a snapshot, `general` (the default: the shipped general policy) or "
        "`untrained`",
    )
    p.add_argument(
        "--map-image",
        metavar="MAP.yaml",
        help="with --graph from `mures map import`: the map it came from, drawn under the graph on the console's map",
    )
    p.add_argument(
        "--step-delay", type=seconds, default=0.0, help="simulated travel time per step, seconds (default 0)"
    )
    p.add_argument(
        "--link-loss",
        type=probability,
        default=0.0,
        metavar="P",
        help="each agent drops each of its observations to its teammates with probability P (robot-agent --link-loss)",
    )
    p.add_argument(
        "--max-steps",
        type=positive_int,
        default=None,
        metavar="K",
        help="each mission's step limit per robot (default the server's, 3 n; with --world, a time limit instead: "
        "--max-seconds); on the mission clock a step that stays takes --stay-seconds, so a robot that waits uses "
        "its steps fast",
    )
    p.add_argument(
        "--max-seconds",
        type=positive_number,
        default=None,
        metavar="S",
        help="with --world: each mission's time limit on the mission clock; each robot stops at its first reading "
        "at or past it (default, unless --max-steps is given: 3 n moves of the map's median edge at --speed)",
    )
    p.add_argument(
        "--team-clock",
        choices=("steps", "seconds"),
        default=None,
        help="how the agents match their teammates' observations (robot-agent --team-clock): by the mission clock "
        "(the default with --world, docs/continuous-world.md) or by step index (the default without)",
    )
    p.add_argument(
        "--kill",
        type=whole_number,
        default=0,
        metavar="K",
        help="in every mission, kill K robots (SIGKILL, drawn from the mission seed) at steps drawn from 1..--kill-by; "
        "they are started again after the mission (default 0)",
    )
    p.add_argument(
        "--kill-by", type=positive_int, default=10, metavar="T", help="the latest step of a kill (default 10)"
    )
    p.add_argument(
        "--step-timeout",
        type=seconds,
        default=10.0,
        metavar="S",
        help="the world withdraws a robot that has not reported its step within S seconds (default 10)",
    )
    p.add_argument("--workdir", help="keep the server's data, agents' state and logs here (default: a temp dir)")
    p.add_argument("--server", metavar="URL", help="attach to this running server instead of starting one")
    p.add_argument("--zenoh-connect", metavar="ENDPOINT", help="with --server: the fleet's Zenoh router")
    p.add_argument("--token-file", metavar="FILE", help="with --server: the operator token")
    p.add_argument("--agent-token-file", metavar="FILE", help="with --server: the agent token (default --token-file)")
    p.add_argument("--json", action="store_true", help="print one JSON object (progress still goes to stderr)")
    add_continuous_args(p, CONTINUOUS_ABOUT, noise=True)
    p.set_defaults(func=cmd_fleet_sim)

    p = sub.add_parser(
        "world", help="the simulated world alone (the target, the detections) for agents run by hand with --backend sim"
    )
    add_map_args(p)
    add_zenoh_arguments(p, "the fleet's router (repeatable; default the server's own, tcp/127.0.0.1:7447)", robot=True)
    p.add_argument(
        "--zenoh-user",
        default="world",
        help="the Zenoh user of --zenoh-password-file (default world: `training-server kit --world`'s)",
    )
    p.add_argument("--fleet", default="default", help="fleet name (default 'default')")
    p.add_argument("--eta-fn", type=eta_arg, default=0.0, help="false-negative rate, in [0, 0.5] (default 0)")
    p.add_argument("--eta-fp", type=eta_arg, default=0.0, help="false-positive rate, in [0, 0.5] (default 0)")
    p.add_argument("--detection", choices=DETECTIONS, default=None, help="detection set D(p) (default node)")
    p.add_argument("--target", default="uniform", metavar="MODEL", help="uniform (default), lazy:STAY or a model.json")
    p.add_argument(
        "--step-timeout", type=seconds, default=10.0, help="withdraw a robot silent this long (s, default 10)"
    )
    p.add_argument("--step-delay", type=seconds, default=0.0, help="simulated travel time per step (s, default 0)")
    add_continuous_args(p, CONTINUOUS_ABOUT, noise=True)
    p.set_defaults(func=cmd_world)
