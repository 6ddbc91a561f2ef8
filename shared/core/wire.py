"""What the fleet's programs share on the wire (docs/SPEC.md sections 5 and 6): Zenoh key expressions,
session configuration, and the mission-control messages.

Key expressions, segment by segment (``<fleet>`` defaults to ``default``; ids match
``shared.core.records.ID_RE`` so that each is exactly one key segment)::

    mures/<fleet>/agents/<robot_id>                   liveliness token: the agent is up
        e.g. mures/default/agents/r2
    mures/<fleet>/missions/<mission_id>               pub/sub, JSON mission-control messages
        e.g. mures/default/missions/m-000017
    mures/<fleet>/episodes/<robot_id>/<mission_id>    queryable on the server; the query payload
        is one episode record; reply ok {"status": "stored"|"duplicate"} or err {"reason", "error"}
    mures/<fleet>/telemetry/<robot_id>                pub/sub, optional per-step state
    mures/<fleet>/sim/<mission_id>/<robot_id>         queryable of the simulated world (fleet-sim);
        mission "~clock": which clock the world keeps, {"clock": "steps"|"seconds"}
    mures/<fleet>/detections/<robot_id>/<mission_id>  pub/sub: a robot's z = 1, the moment it reads it
        {"mission_id", "robot_id", "t", "node"}; the server decides whether it ends the mission
    mures/<fleet>/observations/<robot_id>/<mission_id>  pub/sub: every step's observation for the
        robot's teammates, {"mission_id", "robot_id", "t", "node", "z"} (best effort: a lost one
        is no observation, shared/core/team.py)
    mures/<fleet>/withdrawals/<robot_id>/<mission_id>  pub/sub: a robot that cannot go on with a
        mission (its backend failed) says so, {"mission_id", "robot_id", "steps", "reason"} (steps: how
        many it flew); the server ends that robot's part of the mission at once

Mission-control messages (JSON objects with a ``type``):

    {"type": "start", "mission_id", "robots": [ids], "seed": int, "max_steps": int[, "max_seconds": float],
     "sensor": {...}, "policy_version": int|null}
    {"type": "captured", "mission_id", "t": int, "captured_by": id[, "time_s"]}  (the mission is over)
    {"type": "stop", "mission_id", "reason": str}                        (the mission is over)
    {"type": "dismissed", "mission_id", "robot_id", "t", "detection": int}  (an operator ruled a
        detection a false alarm; the search goes on)
    {"type": "withdrawn", "mission_id", "robot_id", "reason": str}      (a robot left the mission:
        its teammates and the simulated world go on without it)
"""

from __future__ import annotations

import argparse
import json
import logging
import math
from typing import Any

from shared.core.records import ID_RE, is_seconds

log = logging.getLogger("mures.wire")

DEFAULT_FLEET = "default"
DEFAULT_ZENOH_ENDPOINT = "tcp/127.0.0.1:7447"
DEFAULT_HTTP = "127.0.0.1:8000"


def agent_key(fleet: str, robot: str = "*") -> str:
    return f"mures/{fleet}/agents/{robot}"


def mission_key(fleet: str, mission: str = "*") -> str:
    return f"mures/{fleet}/missions/{mission}"


def episode_key(fleet: str, robot: str = "*", mission: str = "*") -> str:
    return f"mures/{fleet}/episodes/{robot}/{mission}"


def telemetry_key(fleet: str, robot: str = "*") -> str:
    return f"mures/{fleet}/telemetry/{robot}"


def sim_key(fleet: str, mission: str = "*", robot: str = "*") -> str:
    return f"mures/{fleet}/sim/{mission}/{robot}"


# the sim key's mission segment of a robot asking the simulated world which clock it keeps (no
# mission id holds a "~", records.ID_RE): the world answers {"clock": "steps" | "seconds"}
WORLD_CLOCK_PROBE = "~clock"


def detection_key(fleet: str, robot: str = "*", mission: str = "*") -> str:
    """A robot's detections (z = 1) during a mission, published the moment it reads them."""
    return f"mures/{fleet}/detections/{robot}/{mission}"


def detection_message(mission_id: str, robot_id: str, t: int, node: int, time_s: float | None = None) -> dict[str, Any]:
    """A robot's z = 1 at its step ``t`` on ``node``; on the mission clock with the reading's ``time_s``."""
    msg = {"mission_id": mission_id, "robot_id": robot_id, "t": int(t), "node": int(node)}
    if time_s is not None:
        msg["time_s"] = round(float(time_s), 3)
    return msg


def _seconds_or_none(value: Any) -> tuple[float | None, str]:
    """An optional ``time_s``: (None, "") when absent, (seconds, "") when a finite number >= 0, else a reason."""
    if value is None:
        return None, ""
    if not is_seconds(value):
        return None, "'time_s' must be a finite number of seconds >= 0"
    return float(value), ""


def withdrawal_key(fleet: str, robot: str = "*", mission: str = "*") -> str:
    """A robot's word that it cannot go on with a mission (its backend failed)."""
    return f"mures/{fleet}/withdrawals/{robot}/{mission}"


MAX_REASON_CHARS = 500  # a withdrawal's or a down agent's reason is cut to this


def withdrawal_message(mission_id: str, robot_id: str, steps: int, reason: str) -> dict[str, Any]:
    return {
        "mission_id": mission_id,
        "robot_id": robot_id,
        "steps": int(steps),
        "reason": str(reason)[:MAX_REASON_CHARS],
    }


def parse_withdrawal(key: str, payload: bytes) -> tuple[dict[str, Any] | None, str]:
    """A withdrawal message and "" if it is well formed (``steps``: how many steps the robot
    flew, 0 when it failed before z_0; a non-empty ``reason``) and matches its key
    (``mures/<fleet>/withdrawals/<robot_id>/<mission_id>``), else None and what is wrong."""
    msg, why = _step_message(key, payload, "withdrawals", ("steps",))
    if msg is None:
        return None, why
    if not isinstance(msg.get("reason"), str) or not msg["reason"].strip():
        return None, "'reason' must be a non-empty string"
    return withdrawal_message(msg["mission_id"], msg["robot_id"], msg["steps"], msg["reason"]), ""


def observation_key(fleet: str, robot: str = "*", mission: str = "*") -> str:
    """A robot's observation of every step of a mission, for its teammates' collective belief."""
    return f"mures/{fleet}/observations/{robot}/{mission}"


def observation_message(
    mission_id: str,
    robot_id: str,
    t: int,
    node: int,
    z: int,
    time_s: float | None = None,
    goal: int | None = None,
) -> dict[str, Any]:
    """A robot's observation of its step ``t`` (``node`` a label, z 0 or 1); a robot on the mission
    clock (robot-agent --team-clock seconds) adds ``time_s``, the clock of the reading, and
    ``goal``, the label of the node it left for."""
    msg = {"mission_id": mission_id, "robot_id": robot_id, "t": int(t), "node": int(node), "z": int(z)}
    if time_s is not None:
        msg["time_s"] = round(float(time_s), 3)
    if goal is not None:
        msg["goal"] = int(goal)
    return msg


def parse_detection(key: str, payload: bytes) -> tuple[dict[str, Any] | None, str]:
    """A detection message and "" if it is well formed and matches its key
    (``mures/<fleet>/detections/<robot_id>/<mission_id>``), else None and what is wrong."""
    msg, why = _step_message(key, payload, "detections", ("t", "node"))
    if msg is None:
        return None, why
    time_s, why = _seconds_or_none(msg.get("time_s"))
    if why:
        return None, why
    return detection_message(msg["mission_id"], msg["robot_id"], msg["t"], msg["node"], time_s), ""


def parse_observation(key: str, payload: bytes) -> tuple[dict[str, Any] | None, str]:
    """An observation message and "" if it is well formed (z 0 or 1) and matches its key
    (``mures/<fleet>/observations/<robot_id>/<mission_id>``), else None and what is wrong."""
    msg, why = _step_message(key, payload, "observations", ("t", "node", "z"))
    if msg is None:
        return None, why
    if msg["z"] not in (0, 1):
        return None, "'z' must be 0 or 1"
    time_s, why = _seconds_or_none(msg.get("time_s"))
    if why:
        return None, why
    goal = msg.get("goal")
    if goal is not None and (isinstance(goal, bool) or not isinstance(goal, int) or goal < 0):
        return None, "'goal' must be a non-negative integer (a node label)"
    return observation_message(msg["mission_id"], msg["robot_id"], msg["t"], msg["node"], msg["z"], time_s, goal), ""


def _step_message(key: str, payload: bytes, kind: str, fields: tuple[str, ...]) -> tuple[dict[str, Any] | None, str]:
    """A robot's message about one step of a mission on ``mures/<fleet>/<kind>/<robot_id>/<mission_id>``:
    a JSON object of at most 4 KiB whose ``fields`` are non-negative integers and whose robot and
    mission are its key's; else None and what is wrong."""
    parts = key.split("/")
    if len(parts) != 5 or parts[2] != kind:
        return None, f"key {key!r} is not mures/<fleet>/{kind}/<robot_id>/<mission_id>"
    try:
        msg = json.loads(payload) if len(payload) <= 4096 else None
    except (ValueError, UnicodeDecodeError):
        msg = None
    if not isinstance(msg, dict):
        return None, "the payload is not a JSON object of at most 4 KiB"
    for field in fields:
        v = msg.get(field)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            return None, f"{field!r} must be a non-negative integer"
    if (msg.get("robot_id"), msg.get("mission_id")) != (parts[3], parts[4]):
        return (
            None,
            f"the message names robot {msg.get('robot_id')!r} mission {msg.get('mission_id')!r}, its key {key!r}",
        )
    return msg, ""


def truth_key(fleet: str, mission: str = "*") -> str:
    """The simulated world's ground truth per step (fleet-sim only; a debugging overlay)."""
    return f"mures/{fleet}/truth/{mission}"


def send_episode(
    session: Any, fleet: str, robot: str, mission: str, payload: bytes, timeout: float = 10.0
) -> tuple[bool | None, dict[str, Any] | None]:
    """Send one episode record as an agent does (the payload of a query on its episode key) and
    read the server's answer: (True, {"status": "stored"|"duplicate", ...}), (False, {"reason",
    "error"}) when it was rejected, (None, None) when nothing answered within ``timeout`` or the
    session failed. For tools and tests; the agent's outbox keeps its own loop (resends, backoff)."""
    import zenoh

    try:
        for reply in session.get(
            episode_key(fleet, robot, mission),
            payload=payload,
            timeout=timeout,
            consolidation=zenoh.ConsolidationMode.NONE,
        ):
            if reply.ok is not None:
                return True, json.loads(reply.ok.payload.to_bytes())
            text = reply.err.payload.to_bytes()
            try:
                return False, json.loads(text)
            except ValueError:  # not the server's answer (a router's, say)
                return False, {"reason": "unknown", "error": text.decode(errors="replace")}
    except zenoh.ZError:
        return None, None
    return None, None


def check_id(kind: str, value: str) -> str:
    if not isinstance(value, str) or not ID_RE.match(value):
        raise ValueError(f"{kind} {value!r} must be 1-128 characters of A-Z a-z 0-9 _ . -")
    return value


def zenoh_config(
    mode: str,
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    config_file: str | None = None,
    tls_ca: str | None = None,
    user: str | None = None,
    password: str | None = None,
    extra: dict[str, Any] | None = None,
) -> Any:
    """A zenoh.Config: from ``config_file`` if given (its own settings win), else built here with
    multicast scouting off and explicit endpoints (docs/zenoh.md); ``tls_ca`` verifies a tls/
    router's certificate, ``user``/``password`` authenticate this session, ``extra`` sets further
    keys (the server's router: TLS listener, users, access control)."""
    import zenoh

    if config_file:
        return zenoh.Config.from_file(config_file)
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if tls_ca:
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(tls_ca))
    if user is not None:
        conf.insert_json5("transport/auth/usrpwd/user", json.dumps(user))
        conf.insert_json5("transport/auth/usrpwd/password", json.dumps(password or ""))
    for key, value in (extra or {}).items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def client_config(args: argparse.Namespace, user: str, connect: list[str] | None = None) -> Any:
    """A client session's zenoh.Config from the flags ``add_zenoh_arguments(..., robot=True)`` adds
    (``connect`` in place of --zenoh-connect when given), authenticated as ``user`` when
    --zenoh-password-file is given (a robot's user is its id, a simulated world's ``world``)."""
    from shared.core.files import read_token

    password = read_token(args.zenoh_password_file) if args.zenoh_password_file else None
    return zenoh_config(
        "client",
        connect=connect or args.zenoh_connect,
        config_file=args.zenoh_config,
        tls_ca=args.zenoh_ca,
        user=user if password else None,
        password=password,
    )


def add_zenoh_arguments(
    parser: argparse.ArgumentParser,
    connect_help: str,
    connect_required: bool = False,
    router: bool = False,
    robot: bool = False,
) -> None:
    """The Zenoh flags of the fleet's programs, one spelling for all: --zenoh-connect (repeatable)
    and --zenoh-config; a ``router`` (the training server) adds --zenoh-listen and its TLS
    listener's --zenoh-tls-cert/--zenoh-tls-key, a ``robot`` (the agent) what a secured router
    asks of it, --zenoh-ca and --zenoh-password-file. Their values go to ``zenoh_config``."""
    if router:
        parser.add_argument(
            "--zenoh-listen",
            action="append",
            metavar="ENDPOINT",
            help=f"Zenoh endpoint to listen on as the router (default {DEFAULT_ZENOH_ENDPOINT})",
        )
    parser.add_argument(
        "--zenoh-connect", action="append", required=connect_required, metavar="ENDPOINT", help=connect_help
    )
    parser.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="a full Zenoh config file instead of the flags above (TLS, credentials; its own settings win)",
    )
    if router:
        parser.add_argument(
            "--zenoh-tls-cert",
            metavar="PEM",
            help="be the fleet's secured Zenoh router: TLS with this certificate on the tls/ --zenoh-listen "
            "endpoints, only robots with credentials (training-server robots add), each limited to its own keys",
        )
        parser.add_argument("--zenoh-tls-key", metavar="PEM", help="the private key of --zenoh-tls-cert")
    if robot:
        parser.add_argument("--zenoh-ca", metavar="PEM", help="CA certificate to verify a tls/ Zenoh router with")
        parser.add_argument(
            "--zenoh-password-file", metavar="F", help="this robot's Zenoh password (training-server robots add)"
        )


def parse_message(payload: bytes) -> dict[str, Any] | None:
    """A mission-control message, or None when it is not one (ignored, never fatal)."""
    try:
        msg = json.loads(payload)
    except (ValueError, UnicodeDecodeError):
        return None
    if not isinstance(msg, dict) or msg.get("type") not in ("start", "captured", "stop", "dismissed", "withdrawn"):
        return None
    if not isinstance(msg.get("mission_id"), str):
        return None
    return msg


def time_limit(msg: dict[str, Any]) -> float | None:
    """A start message's time limit on the mission clock (``max_seconds``, seconds), or None: none
    given, or not a positive finite number (then the step limit alone ends the mission, and the
    agent says why)."""
    value = msg.get("max_seconds")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value <= 0:
        log.warning(
            "mission %s: max_seconds %r is not a positive number of seconds; ignored", msg.get("mission_id"), value
        )
        return None
    return float(value)
