"""The fleet's protections with real processes: HTTPS with a self-signed certificate, and the
server's secured Zenoh router (TLS, per-robot users, access control)."""

from __future__ import annotations

import json
import signal
import ssl
import subprocess
import sys
import time
import urllib.error

import pytest
import zenoh

from shared.core.files import read_token
from shared.core.graph import builtin_graph
from shared.core.http import ApiClient, ApiError
from shared.core.models import Sensor
from shared.core.records import make_record
from shared.core.wire import (
    agent_key,
    detection_key,
    detection_message,
    mission_key,
    observation_key,
    observation_message,
    send_episode,
    zenoh_config,
)
from shared.tools.fleetsim import start_server, wait_until
from training_server.cli import main as server_main

pytestmark = pytest.mark.slow  # starts a training-server process


def self_signed(tmp_path, name="server"):
    """A self-signed certificate for 127.0.0.1 and localhost, made by openssl: (cert, key)."""
    cert, key = tmp_path / f"{name}.pem", tmp_path / f"{name}-key.pem"
    cmd = ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=127.0.0.1"]
    cmd += ["-addext", "subjectAltName=IP:127.0.0.1,DNS:localhost", "-keyout", str(key), "-out", str(cert)]
    subprocess.run(cmd, check=True, capture_output=True)
    return cert, key


def test_rest_api_over_https_with_a_self_signed_certificate(tmp_path):
    cert, key = self_signed(tmp_path)
    logs = tmp_path / "logs"
    logs.mkdir()
    tls = ["--tls-cert", str(cert), "--tls-key", str(key)]
    proc, base, _endpoint = start_server(["--env", "office"], tmp_path / "data", 2, Sensor(), logs, tls, str(cert))
    try:
        assert base.startswith("https://")
        token = read_token(tmp_path / "data" / "agent.token")
        api = ApiClient(base, token, ca_file=str(cert))  # the agent's --ca-file
        assert api.get("/api/v1/policies/current")["version"] == 1
        with pytest.raises(urllib.error.URLError) as exc:  # an unverified certificate is refused
            ApiClient(base, token).get("/api/v1/health")
        assert isinstance(exc.value.reason, ssl.SSLCertVerificationError)
        with pytest.raises(OSError):  # and plaintext gets no answer
            ApiClient(base.replace("https://", "http://"), token, timeout=5).get("/api/v1/health")
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0


def _session(endpoint, ca, user=None, password=None):
    return zenoh.open(zenoh_config("client", connect=[endpoint], tls_ca=str(ca), user=user, password=password))


def test_secured_router_admits_only_robots_and_only_on_their_own_keys(tmp_path, certificates):
    """The server's own session as a TLS router with per-robot users and access control: no
    session without a robot's credentials; r1 cannot send an episode as r2, declare r2's presence,
    or publish mission control (forged start, stop, captured reach neither robots nor the server)."""
    ca, cert, key = certificates
    data = tmp_path / "data"
    data.mkdir()
    creds = {}
    for r in ("r1", "r2"):
        assert server_main(["robots", "add", r, "--data-dir", str(data), "--out", str(tmp_path / r)]) == 0
        creds[r] = (tmp_path / r / "token").read_text().strip(), (tmp_path / r / "zenoh-password").read_text().strip()
    logs = tmp_path / "logs"
    logs.mkdir()
    tls = ["--zenoh-tls-cert", str(cert), "--zenoh-tls-key", str(key)]
    proc, base, endpoint = start_server(["--env", "office"], data, 2, Sensor(), logs, tls, zenoh_proto="tls")
    api = ApiClient(base, read_token(data / "operator.token"))
    g = builtin_graph("office")
    try:
        assert endpoint.startswith("tls/")
        for user, password in ((None, None), ("r1", "wrong"), ("r9", "any")):
            with pytest.raises(zenoh.ZError):
                _session(endpoint, ca, user, password).close()
        r1, r2 = _session(endpoint, ca, "r1", creds["r1"][1]), _session(endpoint, ca, "r2", creds["r2"][1])
        heard: list[dict] = []
        sub = r2.declare_subscriber(
            mission_key("default", "*"), lambda s: heard.append(json.loads(s.payload.to_bytes()))
        )
        try:
            tok = r1.liveliness().declare_token(agent_key("default", "r1"))
            fake = r1.liveliness().declare_token(agent_key("default", "r2"))  # r1 posing as r2
            wait_until(
                lambda: [a["robot_id"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]] == ["r1"],
                10,
                "r1 online",
            )
            time.sleep(1.0)
            assert [a["robot_id"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]] == ["r1"]

            def rec(robot, mission):
                return make_record(
                    g,
                    fleet="default",
                    mission_id=mission,
                    robot_id=robot,
                    nodes=[g.start],
                    z=[0],
                    sensor=Sensor(),
                    captured=False,
                    capture_time=None,
                    captured_by=None,
                )

            ok, body = send_episode(r1, "default", "r1", "m1", json.dumps(rec("r1", "m1")).encode(), timeout=3)
            assert ok and body == {"status": "stored"}
            ok, body = send_episode(r1, "default", "r2", "m1", json.dumps(rec("r2", "m1")).encode(), timeout=3)
            assert ok is None  # refused by the router: the server never sees it
            assert api.get("/api/v1/episodes/stats")["stored"] == 1
            # the server's mission control reaches the robots ...
            m = api.post("/api/v1/missions", {"robots": ["r1"], "mission_id": "m-sec", "seed": 1})
            wait_until(lambda: any(x.get("mission_id") == "m-sec" for x in heard), 10, "the start message")
            heard.clear()
            # ... a robot's forgeries do not
            forgeries = [
                {"type": "captured", "t": 3, "captured_by": "r1"},
                {"type": "stop", "reason": "forged"},
                {"type": "start", "robots": ["r2"], "seed": 5},
            ]
            for forged in forgeries:
                r1.put(mission_key("default", "m-sec"), json.dumps({**forged, "mission_id": "m-sec"}).encode())
            # a detection in r2's name is refused by the router; r1's own reaches the server and
            # ends the mission (capture auto: the sensor has no false positives)
            r1.put(
                detection_key("default", "r2", "m-sec"), json.dumps(detection_message("m-sec", "r2", 1, 43)).encode()
            )
            # teammates hear each other's observations; an observation in another robot's name is refused
            seen: list[str] = []
            team_sub = r2.declare_subscriber(
                observation_key("default", "*", "m-sec"), lambda s: seen.append(str(s.key_expr))
            )
            time.sleep(0.5)
            for robot in ("r2", "r1"):
                msg = observation_message("m-sec", robot, 0, 43, 0)
                r1.put(observation_key("default", robot, "m-sec"), json.dumps(msg).encode())
            wait_until(lambda: seen, 10, "r1's observation at r2")
            time.sleep(0.5)
            team_sub.undeclare()
            assert seen == [observation_key("default", "r1", "m-sec")]
            time.sleep(1.0)
            assert heard == []
            assert api.get(f"/api/v1/missions/{m['id']}")["status"] == "running" and m["status"] == "running"
            assert api.get("/api/v1/detections")["items"] == []
            r1.put(
                detection_key("default", "r1", "m-sec"), json.dumps(detection_message("m-sec", "r1", 2, 43)).encode()
            )
            wait_until(lambda: api.get(f"/api/v1/missions/{m['id']}")["status"] == "captured", 10, "the capture")
            assert [(d["robot_id"], d["status"]) for d in api.get("/api/v1/detections")["items"]] == [
                ("r1", "confirmed")
            ]
        finally:
            sub.undeclare()
            tok.undeclare()
            fake.undeclare()
            r1.close()
            r2.close()
        # a real robot-agent with its own credentials joins the secured bus and pulls the policy
        agent = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "robot_agent.agent",
                "--robot-id",
                "r2",
                "--server",
                base,
                "--zenoh-connect",
                endpoint,
                "--zenoh-ca",
                str(ca),
                "--zenoh-password-file",
                str(tmp_path / "r2" / "zenoh-password"),
                "--token-file",
                str(tmp_path / "r2" / "token"),
                "--state-dir",
                str(tmp_path / "agent-r2"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=open(logs / "agent-r2.log", "wb"),  # noqa: SIM115 - owned by the process
        )
        try:
            wait_until(
                lambda: [a["robot_id"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]] == ["r2"],
                60,
                "r2 online",
            )
            current = tmp_path / "agent-r2" / "policies" / "current.json"  # it comes online, then pulls
            wait_until(current.exists, 60, "r2 to install the policy")
            assert json.loads(current.read_text())["version"] == 1
        finally:
            agent.send_signal(signal.SIGTERM)
            assert agent.wait(30) == 0
        # the robots' HTTP tokens are scoped to themselves
        robot1 = ApiClient(base, creds["r1"][0])
        assert [e["robot_id"] for e in robot1.get("/api/v1/episodes")["items"]] == ["r1"]
        with pytest.raises(ApiError) as exc:
            robot1.get("/api/v1/episodes/r2/m1")
        assert exc.value.status == 403
        for whole_mission in ("/api/v1/missions/m1/replay", "/api/v1/missions/m1/export.mcap"):  # every robot's
            with pytest.raises(ApiError) as exc:
                robot1.get(whole_mission)
            assert exc.value.status == 403, whole_mission
        assert server_main(["robots", "revoke", "r1", "--data-dir", str(data)]) == 0
        with pytest.raises(ApiError) as exc:
            robot1.get("/api/v1/map")
        assert exc.value.status == 401
    finally:
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
