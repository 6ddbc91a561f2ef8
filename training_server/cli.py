"""`training-server`: the fleet's central server process, its command line and subcommands
(docs/SPEC.md section 7; docs/operating.md).

    training-server (--env office|museum | --graph FILE) [--data-dir DIR] [--database-url URL]
                    [--http HOST:PORT] [--zenoh-listen ENDPOINT] [--zenoh-config FILE] [--fleet NAME]
                    [--operator-token-file F] [--agent-token-file F] [--robots N] [--init-policy DIR|general|untrained]
                    [--mission-timeout S]
    training-server rotate-token ROLE | robots add|revoke|list [ID] | kit ...

Embedded defaults, no other service needed: SQLite (WAL) under the data directory for episodes,
missions, runs and versions (or PostgreSQL: --database-url postgresql+psycopg://USER@HOST:PORT/DB);
policy snapshots on disk; its own Zenoh session in router mode on tcp/127.0.0.1:7447; HTTP (the
REST API under /api/v1, OpenAPI at /docs) on 127.0.0.1:8000.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import training_server.credentials as credentials
from shared.core.choices import BUILTIN_MAPS, DETECTIONS
from shared.core.files import read_token, write_private
from shared.core.graph import GraphError, builtin_graph, check_searchable, default_detection, load_graph_file
from shared.core.wire import DEFAULT_FLEET, DEFAULT_HTTP, DEFAULT_ZENOH_ENDPOINT, add_zenoh_arguments, check_id
from training_server.security import MAX_FAILURES, ROLES, WINDOW_S, AuditLog, endpoint_host, is_loopback, rotate
from training_server.server import CAPTURE_MODES, MISSION_TIMEOUT_S, Server

log = logging.getLogger("mures.server")


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": round(record.created, 3),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        if record.exc_info:
            out["exc"] = self.formatException(record.exc_info)
        return json.dumps(out)


def setup_logging(json_logs: bool, level: str = "INFO") -> None:
    h = logging.StreamHandler(sys.stderr)
    h.setFormatter(
        JsonFormatter() if json_logs else logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s")
    )
    root = logging.getLogger()
    root.handlers[:] = [h]
    root.setLevel(level)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["rotate-token"]:
        return rotate_token_main(argv[1:])
    if argv[:1] == ["robots"]:
        return robots_main(argv[1:])
    if argv[:1] == ["kit"]:
        from training_server.kit import kit_main

        return kit_main(argv[1:])
    args = build_parser().parse_args(argv)
    setup_logging(args.log_json, args.log_level.upper())
    try:
        return _run(args)
    except (GraphError, ValueError, KeyError, OSError) as exc:
        print(f"training-server: error: {exc}", file=sys.stderr)
        return 2


def rotate_token_main(argv: list[str]) -> int:
    """`training-server rotate-token ROLE [--data-dir DIR | --token-file F]`: a new token now; the
    running server refuses the old one from its next request on."""
    p = argparse.ArgumentParser(prog="training-server rotate-token", description=rotate_token_main.__doc__)
    p.add_argument("role", choices=ROLES)
    p.add_argument("--data-dir", default="mures-data", help="the server's data directory (default ./mures-data)")
    p.add_argument("--token-file", help="the token file the server was started with, if not the data directory's")
    args = p.parse_args(argv)
    path = Path(args.token_file) if args.token_file else Path(args.data_dir) / f"{args.role}.token"
    if not path.exists():
        print(f"training-server: error: no token file {path} to rotate", file=sys.stderr)
        return 2
    rotate(path)
    print(f"rotated the {args.role} token in {path}: give the new one to its users; the old one is refused now")
    return 0


def robots_main(argv: list[str]) -> int:
    """`training-server robots add|revoke|list [ID] [--data-dir DIR]`: each robot's own credentials."""
    p = argparse.ArgumentParser(prog="training-server robots", description=credentials.__doc__.split("\n\n")[0])
    p.add_argument("action", choices=("add", "revoke", "list"))
    p.add_argument("robot_id", nargs="?", help="the robot (add, revoke)")
    p.add_argument("--data-dir", default="mures-data", help="the server's data directory (default ./mures-data)")
    p.add_argument("--out", metavar="DIR", help="add: where to write the robot's token and Zenoh password files")
    args = p.parse_args(argv)
    data_dir = Path(args.data_dir)
    if not data_dir.is_dir():
        print(f"training-server: error: no data directory {data_dir}", file=sys.stderr)
        return 2
    if args.action == "list":
        for robot, entry in credentials.robots(data_dir).items():
            issued = time.strftime("%Y-%m-%d %H:%M", time.gmtime(entry["issued"]))
            print(f"{robot}\tissued {issued} UTC")
        return 0
    try:
        robot = check_id("robot id", args.robot_id or "")
    except ValueError as exc:
        print(f"training-server: error: {exc}", file=sys.stderr)
        return 2
    audit = AuditLog(data_dir / "audit.jsonl")
    if args.action == "revoke":
        if not credentials.revoke(data_dir, robot):
            print(f"training-server: error: robot {robot} holds no credentials", file=sys.stderr)
            return 2
        audit.write(who="admin", client="local", action=f"robots revoke {robot}", status="done")
        print(
            f'revoked {robot}: its HTTP token is refused now ("credentials were revoked"), the fleet lists it as '
            "revoked, a running server's router re-opens without it within seconds, and its agent stops at its next "
            "check with the server (robot-agent --idle-check, 30 s by default)"
        )
        return 0
    token, password = credentials.issue(data_dir, robot)
    out = Path(args.out) if args.out else data_dir / "robots" / f"{robot}-credentials"
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    write_private(out / "token", token + "\n")
    write_private(out / "zenoh-password", password + "\n")
    audit.write(who="admin", client="local", action=f"robots add {robot}", status="done")
    print(
        f"issued credentials for {robot} in {out}: copy 'token' and 'zenoh-password' to /etc/mures/robot/ on the "
        "robot (with the fleet's ca.pem; `training-server kit` writes the whole bundle); a running server's "
        "router takes the new user within seconds"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="training-server", description="MuRES fleet central server (REST + Zenoh)")
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--env", choices=BUILTIN_MAPS, help="a built-in map")
    g.add_argument("--graph", metavar="FILE", help="a JSON graph file (docs/SPEC.md section 7)")
    p.add_argument(
        "--map-image",
        metavar="MAP.yaml",
        help="with --graph from `mures map import`: the map it was imported from, drawn under the graph on the "
        "console's live map (checked against the graph's image sha256)",
    )
    p.add_argument(
        "--data-dir", default="mures-data", help="where the database and policies live (default ./mures-data)"
    )
    p.add_argument(
        "--database-url",
        metavar="URL",
        help="the database: postgresql+psycopg://USER[:PASSWORD]@HOST:PORT/DB (default: SQLite in the data directory)",
    )
    p.add_argument(
        "--mission-timeout",
        type=float,
        default=MISSION_TIMEOUT_S,
        metavar="S",
        help=f"end a mission still running after S seconds (default {MISSION_TIMEOUT_S:.0f}; "
        "a mission may ask for less)",
    )
    p.add_argument(
        "--sign-in-limit",
        type=int,
        default=MAX_FAILURES,
        metavar="N",
        help=f"wrong tokens one address may send within {WINDOW_S:.0f} s before it is refused with 429 for a "
        f"while (default {MAX_FAILURES})",
    )
    p.add_argument(
        "--http", type=parse_hostport, default=DEFAULT_HTTP, help=f"REST API address (default {DEFAULT_HTTP})"
    )
    add_zenoh_arguments(p, "connect to these routers (e.g. zenohd) instead of being the router", router=True)
    p.add_argument("--tls-cert", metavar="PEM", help="serve HTTPS with this certificate (chain) ...")
    p.add_argument("--tls-key", metavar="PEM", help="... and this private key")
    p.add_argument(
        "--insecure",
        action="store_true",
        help="allow listening beyond loopback without TLS (HTTP) or without --zenoh-tls-cert/--zenoh-config (Zenoh): "
        "anyone on the network could then command the robots",
    )
    p.add_argument(
        "--capture",
        choices=CAPTURE_MODES,
        help="what a robot's detection (z = 1) does: auto ends the mission as captured; confirm raises an alert "
        "for an operator to confirm or dismiss (console, POST /api/v1/detections/ID/confirm|dismiss). Default: "
        "auto when the current policy's sensor has no false positives (eta_fp = 0), else confirm; a mission may "
        'say otherwise (POST /api/v1/missions {"capture": ...})',
    )
    p.add_argument(
        "--metrics-without-token",
        action="store_true",
        help="serve /metrics to anyone who reaches the server (default: a fleet token is needed, as for the API; "
        "Prometheus sends one with authorization: {credentials_file: ...})",
    )
    p.add_argument("--fleet", default=DEFAULT_FLEET, help="fleet name (default 'default')")
    p.add_argument("--operator-token-file", help="operator bearer token (default: created in the data dir)")
    p.add_argument("--agent-token-file", help="agent bearer token (default: created in the data dir)")
    p.add_argument("--robots", type=int, default=4, help="networks in the initial policy (default 4)")
    p.add_argument(
        "--init-policy",
        metavar="DIR",
        help="the first version: a snapshot (mures train), `general` (the default: the shipped general policy, for "
        "any building and team size, fine-tuned by the retraining) or `untrained` (a per-map team of random networks)",
    )
    p.add_argument("--eta-fn", type=float, default=0.0, help="sensor false-negative rate of the initial policy")
    p.add_argument("--eta-fp", type=float, default=0.0, help="sensor false-positive rate of the initial policy")
    p.add_argument(
        "--detection",
        choices=DETECTIONS,
        default=None,
        help="D(p) of the initial policy's sensor (default: custom, the sensing table, where the graph file has one "
        "(`mures map import --sensor-range`), else node)",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the initial policy's weights")
    p.add_argument("--log-json", action="store_true", help="structured (JSON Lines) logs")
    p.add_argument("--log-level", default="INFO")
    return p


def parse_hostport(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    return host.strip("[]"), int(port)


def check_exposure(args: argparse.Namespace) -> None:
    """Safe by default: beyond loopback, HTTP needs TLS and Zenoh needs a config file (TLS, user
    and password, access control: `training-server kit` writes them), unless the operator says --insecure."""
    if bool(args.tls_cert) != bool(args.tls_key):
        raise ValueError("--tls-cert and --tls-key go together")
    if bool(args.zenoh_tls_cert) != bool(args.zenoh_tls_key):
        raise ValueError("--zenoh-tls-cert and --zenoh-tls-key go together")
    if args.insecure:
        return
    host, _port = args.http
    if not is_loopback(host) and not args.tls_cert:
        raise ValueError(
            f"--http {host} is reachable from the network: serve it with --tls-cert and --tls-key "
            "(or say --insecure to accept plaintext)"
        )
    for ep in args.zenoh_listen or []:
        proto, zhost = endpoint_host(ep)
        if not is_loopback(zhost) and not (proto == "tls" and args.zenoh_tls_cert):
            raise ValueError(
                f"--zenoh-listen {ep} is reachable from the network without TLS or authentication: use "
                "tls/ with --zenoh-tls-cert/--zenoh-tls-key (training-server kit makes them), or --zenoh-config "
                "with a secured configuration "
                "(or say --insecure)"
            )


def _token_file(path: Path, given: str | None, kind: str) -> Path:
    """The token file to use: ``given``, or ``path`` in the data directory (created if missing)."""
    if given:
        read_token(given)  # a clear error now when it is missing or empty
        return Path(given)
    if not path.exists():
        rotate(path)
        print(f"training-server: created {kind} token in {path} (mode 0600)", file=sys.stderr)
    read_token(path)
    return path


def _run(args: argparse.Namespace) -> int:
    """The server, from its command line to its clean shutdown (SIGINT, SIGTERM)."""
    check_id("fleet", args.fleet)
    check_exposure(args)
    srv = _open_server(args)
    conf, secured_conf = _router_config(args, srv.data_dir)
    return _serve(srv, args, conf, secured_conf)


def _map_picture(args: argparse.Namespace) -> Any:
    """--map-image: the imported graph's map as the console draws it (ValueError: one line)."""
    if not args.graph:
        raise ValueError("--map-image goes with --graph (a graph made by `mures map import` from that map)")
    try:
        from shared.floorplan.graph_file import map_picture
    except ImportError as exc:
        raise ValueError(f"--map-image needs the maps extra (pip install 'mures-fleet[maps]'): {exc}") from None
    source = json.loads(Path(args.graph).read_text(encoding="utf-8")).get("source")
    picture = map_picture(args.map_image, source if isinstance(source, dict) else None)
    log.info("map image %s: %d bytes, map frame %s", args.map_image, len(picture.png), picture.bounds)
    return picture


def _open_server(args: argparse.Namespace) -> Server:
    """The Server of the data directory, its policy versions migrated, an initial policy made if
    there is none, and training runs a restart interrupted ended."""
    from shared.core.models import Sensor

    if args.robots < 1:
        raise ValueError("--robots must be at least 1")
    if not 0 < args.mission_timeout <= 7 * 24 * 3600:
        raise ValueError("--mission-timeout must be more than 0 and at most a week (604800 s)")
    if args.sign_in_limit < 1:
        raise ValueError("--sign-in-limit must be at least 1")
    graph = check_searchable(builtin_graph(args.env) if args.env else load_graph_file(args.graph))
    picture = _map_picture(args) if args.map_image else None
    sensor = Sensor(eta_fn=args.eta_fn, eta_fp=args.eta_fp, detection=args.detection or default_detection(graph))
    data_dir = Path(args.data_dir)
    os.umask(0o077)  # everything the server writes (database, policies, logs of runs) is private
    data_dir.mkdir(parents=True, exist_ok=True)
    srv = Server(
        data_dir,
        graph,
        args.fleet,
        _token_file(data_dir / "operator.token", args.operator_token_file, "operator"),
        _token_file(data_dir / "agent.token", args.agent_token_file, "agent"),
        database_url=args.database_url,
        mission_timeout=args.mission_timeout,
        sign_in_limit=args.sign_in_limit,
        capture=args.capture,
    )
    srv.metrics_without_token = args.metrics_without_token
    srv.map_picture = picture
    srv.migrate_versions()
    srv.ensure_initial_policy(args.robots, args.init_policy, sensor, args.seed)
    return srv


def _router_config(args: argparse.Namespace, data_dir: Path) -> tuple[Any, Any]:
    """The server's Zenoh configuration, and for a secured router (--zenoh-tls-cert) the function
    that makes it again from the robots' current credentials (else None)."""
    from shared.core.wire import zenoh_config

    if args.zenoh_config:
        return zenoh_config("router", config_file=args.zenoh_config), None
    if args.zenoh_tls_cert:
        listen = args.zenoh_listen or []
        if not listen or any(not ep.startswith("tls/") for ep in listen):
            raise ValueError("--zenoh-tls-cert needs --zenoh-listen tls/HOST:PORT endpoints (and only tls/ ones)")

        def secured() -> Any:  # read again whenever the robots' credentials change
            extra = credentials.secured_router(data_dir, args.fleet, args.zenoh_tls_cert, args.zenoh_tls_key)
            return zenoh_config("router", listen=listen, extra=extra)

        log.info("zenoh: TLS, user/password and access control for %d robots", len(credentials.robots(data_dir)))
        return secured(), secured
    if args.zenoh_connect:
        return zenoh_config("client", connect=args.zenoh_connect), None
    return zenoh_config("router", listen=args.zenoh_listen or [DEFAULT_ZENOH_ENDPOINT]), None


def _serve(srv: Server, args: argparse.Namespace, conf: Any, secured_conf: Any) -> int:
    """Open the bus on ``conf``, start the training supervisor (and, for a secured router, the
    watcher that re-opens it when robots are added or revoked), serve HTTP until a signal, then
    close everything."""
    import uvicorn
    import zenoh

    from training_server.api import create_app
    from training_server.bus import Bus
    from training_server.jobs import Supervisor

    try:
        srv.bus = Bus(srv, conf)
    except zenoh.ZError as exc:
        srv.close()
        raise ValueError(f"cannot start Zenoh: {str(exc).split(' at /')[0]}") from None
    srv.supervisor = Supervisor(srv)
    srv.supervisor.start()
    for run_id, status in srv.supervisor.resume_interrupted():
        what = "resumes where it was" if status == "queued" else "stays cancelled, as asked"
        log.warning("training run %s was interrupted by a server restart: it %s", run_id, what)
    stop_watch = threading.Event()
    watcher = None
    if secured_conf is not None:  # robots added or revoked take effect without a restart
        watcher = threading.Thread(
            target=srv.reopen_router_on_credentials, args=(secured_conf, stop_watch), name="credentials", daemon=True
        )
        watcher.start()
    host, port = args.http
    tls = {"ssl_certfile": args.tls_cert, "ssl_keyfile": args.tls_key} if args.tls_cert else {}
    config = uvicorn.Config(
        create_app(srv), host=host, port=port, log_level="warning", access_log=False, timeout_graceful_shutdown=5, **tls
    )
    http = uvicorn.Server(config)
    srv.is_stopping = lambda: http.should_exit  # the console's event streams end when the server stops
    log.info(
        "serving fleet %r on map %s (n=%d): %s://%s:%d/api/v1, zenoh %s, data in %s, database %s, policy version %d",
        args.fleet,
        srv.graph.name,
        srv.graph.n,
        "https" if tls else "http",
        host,
        port,
        args.zenoh_config or args.zenoh_connect or args.zenoh_listen or DEFAULT_ZENOH_ENDPOINT,
        srv.data_dir,
        srv.store.safe_url,
        srv.current_version(),
    )
    # uvicorn handles SIGINT/SIGTERM while serving and re-raises the signal afterwards; these
    # handlers take that re-raise, so the clean shutdown below runs and the exit status is 0
    signal.signal(signal.SIGTERM, lambda *_a: None)
    signal.signal(signal.SIGINT, lambda *_a: None)
    try:
        http.run()  # returns on SIGINT/SIGTERM
    finally:
        log.info("shutting down")
        stop_watch.set()
        if watcher is not None:
            watcher.join(15)  # a router re-opening now finishes first: the bus closed below is the last one
        srv.supervisor.stop()
        srv.bus.close()
        srv.close()
    if srv.router_reopened:
        # A Zenoh session closed at a re-opening can leave its runtime's threads behind, and one of
        # them reaching into Python while the interpreter finalises aborts the process (SIGABRT,
        # "exception not rethrown"). Everything is closed and written by now: end here, with 0.
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0
