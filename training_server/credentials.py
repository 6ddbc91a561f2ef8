"""Each robot's own credentials, and the secured Zenoh router built from them.

`training-server robots add ID` issues a robot a Zenoh password (its user name is its robot id)
and an HTTP token scoped to that robot; `robots revoke ID` takes both away; `robots list` shows
who holds credentials. They live in ``<data>/robots/<id>.json`` (mode 0600; the HTTP token only as
its sha256). A revoked robot's HTTP token is refused at its next request; its Zenoh password is
refused from the server's next start (the router reads its user list when it opens).

With `--zenoh-tls-cert/--zenoh-tls-key` the server's own session is the fleet's router with
(docs/SPEC.md section 6, docs/deploying.md):
- TLS on its tls/ endpoints;
- user/password authentication: a session without a valid robot's credentials is refused;
- access control, deny by default. A robot may declare its own liveliness token, publish its own
  telemetry, its own detections, its own observations and its own withdrawals, query its own episode keys (and receive
  the replies), subscribe to mission control and to its teammates' observations, and receive
  them. Nothing else: no robot may publish on missions/*, so start, stop and captured
  come only from the server (its own local session, which the rules do not filter).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import secrets
import time
from pathlib import Path
from typing import Any

from shared.core.files import atomic_write, write_private
from shared.core.wire import (
    agent_key,
    detection_key,
    episode_key,
    mission_key,
    observation_key,
    sim_key,
    telemetry_key,
    truth_key,
    withdrawal_key,
)


def _robots_dir(data_dir: Path) -> Path:
    d = data_dir / "robots"
    d.mkdir(mode=0o700, parents=True, exist_ok=True)
    return d


def _sha(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def issue(data_dir: Path, robot_id: str) -> tuple[str, str]:
    """New credentials for ``robot_id`` (replacing any it had): (HTTP token, Zenoh password)."""
    token, password = secrets.token_urlsafe(32), secrets.token_urlsafe(24)
    entry = {"robot_id": robot_id, "token_sha256": _sha(token), "zenoh_password": password, "issued": time.time()}
    write_private(_robots_dir(data_dir) / f"{robot_id}.json", json.dumps(entry) + "\n")
    return token, password


def revoke(data_dir: Path, robot_id: str) -> bool:
    """Take a robot's credentials away. What is kept of them (``robots/revoked/<id>.json``: its
    token's hash, when) lets the server tell its agent "revoked" instead of "wrong token" and list
    it as revoked; issuing it credentials again lifts that."""
    path = _robots_dir(data_dir) / f"{robot_id}.json"
    if not path.exists():
        return False
    entry = json.loads(path.read_text(encoding="utf-8"))
    kept = {"robot_id": robot_id, "token_sha256": entry.get("token_sha256", ""), "revoked": time.time()}
    (_robots_dir(data_dir) / "revoked").mkdir(mode=0o700, exist_ok=True)
    write_private(_robots_dir(data_dir) / "revoked" / f"{robot_id}.json", json.dumps(kept) + "\n")
    path.unlink()
    return True


def revoked(data_dir: Path) -> dict[str, dict[str, Any]]:
    """robot id -> {robot_id, token_sha256, revoked (Unix time)} for every robot revoked and not
    issued credentials since."""
    d = _robots_dir(data_dir) / "revoked"
    have = robots(data_dir)
    out = {}
    for p in sorted(d.glob("*.json")) if d.is_dir() else []:
        try:
            entry = json.loads(p.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        if entry.get("robot_id") not in have:
            out[entry["robot_id"]] = entry
    return out


def revoked_robot_for_token(data_dir: Path, token: bytes) -> str | None:
    """The revoked robot whose HTTP token this was, or None."""
    digest = hashlib.sha256(token).hexdigest().encode()
    found = None
    for robot, entry in revoked(data_dir).items():
        if hmac.compare_digest(digest, str(entry.get("token_sha256", "")).encode()):
            found = robot
    return found


def robots(data_dir: Path) -> dict[str, dict[str, Any]]:
    """robot id -> its credentials entry, for every robot holding credentials."""
    out = {}
    for p in sorted(_robots_dir(data_dir).glob("*.json")):
        entry = json.loads(p.read_text(encoding="utf-8"))
        out[entry["robot_id"]] = entry
    return out


def robot_for_token(data_dir: Path, token: bytes) -> str | None:
    """The robot whose HTTP token this is (constant-time comparison of digests), or None."""
    digest = hashlib.sha256(token).hexdigest().encode()
    found = None
    for robot, entry in robots(data_dir).items():
        if hmac.compare_digest(digest, entry["token_sha256"].encode()):
            found = robot
    return found


WORLD_USER = "world"  # the Zenoh user of a simulated world (`mures world`) on a secured router


def issue_world(data_dir: Path) -> str:
    """A Zenoh password for a simulated world (`training-server kit --world`), replacing any."""
    password = secrets.token_urlsafe(24)
    write_private(data_dir / "world-credentials.json", json.dumps({"zenoh_password": password}) + "\n")
    return password


def world_password(data_dir: Path) -> str | None:
    """The simulated world's Zenoh password, when one was issued."""
    path = data_dir / "world-credentials.json"
    return str(json.loads(path.read_text(encoding="utf-8"))["zenoh_password"]) if path.exists() else None


def users_file(data_dir: Path) -> Path:
    """The router's ``user:password`` dictionary (0600) for the robots holding credentials (and the
    simulated world, when it holds some)."""
    path = data_dir / "zenoh-users.txt"
    lines = [f"{r}:{e['zenoh_password']}" for r, e in robots(data_dir).items()]
    world = world_password(data_dir)
    if world is not None:
        lines.append(f"{WORLD_USER}:{world}")
    atomic_write(path, "".join(line + "\n" for line in lines), mode=0o600)
    return path


def access_control(fleet: str, robot_ids: list[str], world: bool = False) -> dict[str, Any]:
    """Zenoh ``access_control``: deny by default; each robot only its own keys (module docstring).
    ``world``: a simulated world (user ``world``) may answer the robots' sim queries, hear mission
    control and publish its ground truth, and each robot may query its own sim key."""
    rules: list[dict[str, Any]] = [
        {
            "id": "missions-to-robots",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ["declare_subscriber"],
            "key_exprs": [mission_key(fleet, "*")],
        },
        {
            "id": "missions-delivered",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put"],
            "key_exprs": [mission_key(fleet, "*")],
        },
        {  # every robot hears its teammates' observations (robot r sends only its own: below)
            "id": "observations-to-robots",
            "permission": "allow",
            "flows": ["ingress", "egress"],
            "messages": ["declare_subscriber"],
            "key_exprs": [observation_key(fleet, "*", "*")],
        },
        {
            "id": "observations-delivered",
            "permission": "allow",
            "flows": ["egress"],
            "messages": ["put"],
            "key_exprs": [observation_key(fleet, "*", "*")],
        },
    ]
    shared_rules = ["missions-to-robots", "missions-delivered", "observations-to-robots", "observations-delivered"]
    subjects: list[dict[str, Any]] = [{"id": "robots", "usernames": list(robot_ids) or ["-nobody-"]}]
    policies: list[dict[str, Any]] = [{"rules": shared_rules, "subjects": ["robots"]}]
    for r in robot_ids:
        rules.append(
            {
                "id": f"own-keys-{r}",
                "permission": "allow",
                "flows": ["ingress"],
                "messages": ["liveliness_token", "put", "query"],
                "key_exprs": [
                    agent_key(fleet, r),
                    telemetry_key(fleet, r),
                    detection_key(fleet, r, "*"),
                    observation_key(fleet, r, "*"),
                    withdrawal_key(fleet, r, "*"),
                    episode_key(fleet, r, "*"),
                ],
            }
        )
        rules.append(
            {
                "id": f"own-replies-{r}",
                "permission": "allow",
                "flows": ["egress"],
                "messages": ["reply"],
                "key_exprs": [episode_key(fleet, r, "*")],
            }
        )
        subjects.append({"id": f"robot-{r}", "usernames": [r]})
        policies.append({"rules": [f"own-keys-{r}", f"own-replies-{r}"], "subjects": [f"robot-{r}"]})
        if world:
            rules.append(
                {
                    "id": f"own-sim-{r}",
                    "permission": "allow",
                    "flows": ["ingress", "egress"],
                    "messages": ["query", "reply"],
                    "key_exprs": [sim_key(fleet, "*", r)],
                }
            )
            policies[-1]["rules"].append(f"own-sim-{r}")
    if world:
        rules.append(
            {
                "id": "simulated-world",
                "permission": "allow",
                "flows": ["ingress", "egress"],
                "messages": ["declare_queryable", "query", "reply", "declare_subscriber", "put"],
                "key_exprs": [sim_key(fleet, "*", "*"), mission_key(fleet, "*"), truth_key(fleet, "*")],
            }
        )
        subjects.append({"id": "simulated-world", "usernames": [WORLD_USER]})
        policies.append({"rules": ["simulated-world"], "subjects": ["simulated-world"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def secured_router(data_dir: Path, fleet: str, cert: str, key: str) -> dict[str, Any]:
    """The extra Zenoh settings of the server's secured router (``zenoh_config(..., extra=...)``)."""
    ids = list(robots(data_dir))
    world = world_password(data_dir) is not None
    return {
        "transport/link/tls/listen_certificate": cert,
        "transport/link/tls/listen_private_key": key,
        "transport/auth/usrpwd/dictionary_file": str(users_file(data_dir)),
        "access_control": access_control(fleet, ids, world=world),
    }
