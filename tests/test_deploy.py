"""deploy/ and the deployment kit: the zenohd configuration `training-server kit` writes lets a
robot write only its own keys and never mission control, the same holds for the rules the server
builds, and nothing listens in plaintext beyond loopback."""

from __future__ import annotations

import json
from pathlib import Path

import zenoh

from training_server.credentials import access_control
from training_server.kit import zenohd_config

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


def robot_ingress_violations(acl: dict, robots: list[str]) -> list[str]:
    """What a robot's session may send that it should not: anything on missions/*, or another
    robot's keys. Empty when the rules are right."""
    rules = {r["id"]: r for r in acl["rules"]}
    subject_users = {s["id"]: set(s.get("usernames", [])) for s in acl["subjects"]}
    bad = []
    for robot in robots:
        subjects = {sid for sid, users in subject_users.items() if robot in users}
        granted = [rules[rid] for p in acl["policies"] if set(p["subjects"]) & subjects for rid in p["rules"]]
        for rule in granted:
            if rule["permission"] != "allow" or "ingress" not in rule["flows"]:
                continue
            sends = set(rule["messages"]) - {"declare_subscriber", "declare_liveliness_subscriber"}
            for key in rule["key_exprs"] if sends else []:
                segments = key.split("/")
                if "missions" in segments:
                    bad.append(f"{robot} may send {sorted(sends)} on {key}")
                if robot not in segments or set(segments) & (set(robots) - {robot}) or "**" in segments:
                    bad.append(f"{robot} may send {sorted(sends)} on {key}, not only its own keys")
    assert acl["default_permission"] == "deny"
    return bad


def test_the_kits_zenohd_rules_keep_robots_to_their_own_keys(tmp_path):
    """What `training-server kit` writes for zenohd, for any fleet name and robots, read by Zenoh."""
    robots = ["r1", "r2", "r3", "r4"]
    path = tmp_path / "router.json5"
    path.write_text(json.dumps(zenohd_config("site-b", robots, 7447)))
    conf = zenoh.Config.from_file(str(path))
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] is True
    assert robot_ingress_violations(acl, robots) == []
    assert json.loads(conf.get_json("listen/endpoints")) == ["tls/0.0.0.0:7447"]


def test_the_servers_generated_rules_keep_robots_to_their_own_keys():
    assert robot_ingress_violations(access_control("default", ["r1", "r2", "r3"]), ["r1", "r2", "r3"]) == []
    # and the checker sees a bad rule set for what it is
    loose = access_control("default", ["r1", "r2"])
    loose["rules"][0]["messages"].append("put")
    assert robot_ingress_violations(loose, ["r1", "r2"])


def test_deploy_files_never_listen_in_plaintext_beyond_loopback():
    for path in DEPLOY.rglob("*"):
        if not path.is_file():
            continue
        text = path.read_text(encoding="utf-8")
        assert "tcp/0.0.0.0" not in text, path
        if "0.0.0.0:8000" in text:
            assert "--tls-cert" in text or "MURES_TLS_ARGS" in text or "tls-cert" in text, path
