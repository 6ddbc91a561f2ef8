"""The deployment kit end to end on loopback: `training-server kit` makes every file, and a server
and 4 robot agents start from those files only, with the command lines of deploy/systemd's units
(their settings from the generated environment files), HTTPS and Zenoh over TLS with per-robot
users and access control. Robots added and revoked while the server runs take effect without a
restart; the agents' reconnect time is printed."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

from shared.core.http import ApiClient, ApiError
from shared.tools.fleetsim import _child_env, free_port, reap, wait_until

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parent.parent
UNITS = ROOT / "deploy" / "systemd"
BIN = Path(sys.executable).parent


def read_env(path: Path) -> dict[str, str]:
    """An EnvironmentFile as systemd reads it: KEY=VALUE lines, # comments, a value in double
    quotes taken without them (backslash escapes undone)."""
    out = {}
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            key, _, value = line.partition("=")
            value = value.strip()
            if len(value) >= 2 and value[0] == value[-1] == '"':
                value = re.sub(r"\\(.)", r"\1", value[1:-1])
            out[key.strip()] = value
    return out


def sourced(path: Path) -> dict[str, str]:
    """The same file as a POSIX shell's ``source`` reads it."""
    out = subprocess.run(
        ["env", "-i", "bash", "-c", f"set -a; source {shlex.quote(str(path))}; env -0"],
        capture_output=True,
        timeout=30,
        check=True,
    )
    return dict(
        x.split("=", 1) for x in out.stdout.decode().split("\0") if x and x.split("=", 1)[0].startswith("MURES")
    )


def exec_start(unit: Path, env: dict[str, str]) -> list[str]:
    """The unit's ExecStart as systemd runs it: ${VAR} is one word, $VAR is split at whitespace;
    /opt/mures/.venv/bin/ is this interpreter's bin directory."""
    line = next(x for x in unit.read_text().splitlines() if x.startswith("ExecStart="))[len("ExecStart=") :]
    words: list[str] = []
    for word in shlex.split(line):
        m = re.fullmatch(r"\$([A-Z_]+)", word)
        if m:
            words += env[m.group(1)].split()
        else:
            words.append(re.sub(r"\$\{([A-Z_]+)\}", lambda g: env[g.group(1)], word))
    words[0] = words[0].replace("/opt/mures/.venv/bin", str(BIN))
    return words


def kit(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(BIN / "training-server"), "kit", *args], capture_output=True, text=True, timeout=120, env=_child_env()
    )


def test_a_server_and_four_robots_from_the_generated_files_only(tmp_path):
    out, data = tmp_path / "kit", tmp_path / "var-lib-mures"
    http, zport = free_port(), free_port()
    common = ["--out", str(out), "--host", "127.0.0.1", "--host", "localhost", "--fleet", "lab-3"]
    common += ["--map-args", "--env office", "--data-dir", str(data), "--http-port", str(http)]
    common += ["--zenoh-port", str(zport), "--backend", "scripted_backend:ScriptedBackend"]
    made = kit(*common, "--robots", "r1,r2,r3,r4")
    assert made.returncode == 0, made.stderr
    assert "bundles for r1, r2, r3, r4" in made.stdout
    assert f"no server runs on {data} now" in made.stdout  # none runs yet
    for f in ("server/server.env", "robots/r1/robot.env"):  # systemd and a shell read the same values
        assert sourced(out / f) == read_env(out / f), f
    assert read_env(out / "server" / "server.env")["MURES_MAP_ARGS"] == "--env office"
    for f in ("ca/ca-key.pem", "server/tls/server-key.pem", "server/zenohd/users.txt", "robots/r3/token"):
        assert (out / f).stat().st_mode & 0o077 == 0, f  # secrets are private
    router = json.loads((out / "server" / "zenohd" / "router.json5").read_text().split("\n", 1)[1])
    assert {s["id"] for s in router["access_control"]["subjects"]} >= {"server", "robot-r1", "robot-r4"}
    assert "mures/lab-3/detections/r4/*" in json.dumps(router["access_control"])
    assert len((out / "server" / "zenohd" / "users.txt").read_text().splitlines()) == 5
    # bad input: one line, exit status 2, nothing written
    bad = kit("--out", str(tmp_path / "bad"), "--host", "x", "--robots", "r1,r 2")
    assert bad.returncode == 2 and bad.stderr.startswith("training-server kit: error: robot id 'r 2'")
    assert not (tmp_path / "bad").exists()

    # the server, as its unit starts it; on one machine it listens on loopback only
    env = read_env(out / "server" / "server.env")
    assert env["MURES_DATA_DIR"] == str(data) and env["MURES_FLEET"] == "lab-3"
    env.update(MURES_SERVER_DIR=str(out / "server"), MURES_HTTP=f"127.0.0.1:{http}")
    env["MURES_ZENOH_LISTEN"] = env["MURES_ZENOH_LISTEN"].replace("0.0.0.0", "127.0.0.1")
    logs = tmp_path / "logs"
    logs.mkdir()
    procs: dict[str, subprocess.Popen] = {}

    def start(name: str, cmd: list[str], extra_env: dict[str, str] | None = None) -> None:
        log = open(logs / f"{name}.log", "ab")  # noqa: SIM115 - owned by the process
        penv = {**_child_env(agent=name != "server"), **(extra_env or {})}
        procs[name] = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=penv)

    start("server", exec_start(UNITS / "mures-training-server.service", env))
    api = ApiClient(f"https://localhost:{http}", None, ca_file=str(out / "operators" / "ca.pem"))

    def up() -> bool:
        try:
            return api.get("/api/v1/health")["fleet"] == "lab-3"
        except (OSError, ApiError):
            return False

    try:
        wait_until(up, 90, "the server over HTTPS", every=0.2)
        api.token = (data / "operator.token").read_text().strip()
        scripted = {"PYTHONPATH": f"{ROOT / 'tests'}:{ROOT}", "MURES_TEST_DETECT": "r2:3", "MURES_TEST_STEP_S": "0.02"}

        def start_robot(robot: str, bundle: Path) -> None:
            renv = read_env(bundle / "robot.env")
            assert renv["MURES_ROBOT_ID"] == robot and renv["MURES_SERVER_URL"] == f"https://127.0.0.1:{http}"
            renv["MURES_ROBOT_DIR"] = str(bundle)  # where its bundle is installed
            renv["MURES_BACKEND_ARGS"] = "--idle-check 1"  # revoked credentials stop it within a second or so
            cmd = exec_start(UNITS / "mures-robot-agent.service", renv)
            cmd[cmd.index("--state-dir") + 1] = str(tmp_path / f"state-{robot}")
            start(robot, cmd, scripted)

        def online() -> set[str]:
            return {a["robot_id"] for a in api.get("/api/v1/fleet")["agents"] if a["online"]}

        for r in ("r1", "r2", "r3", "r4"):
            start_robot(r, out / "robots" / r)
        wait_until(lambda: online() == {"r1", "r2", "r3", "r4"}, 90, "4 robots online", every=0.2)
        m = api.post("/api/v1/missions", {"robots": ["r1", "r2", "r3", "r4"], "seed": 1, "max_steps": 30})
        done = wait_until(
            lambda: (x := api.get(f"/api/v1/missions/{m['id']}"))["status"] == "completed" and x, 60, "mission"
        )
        assert done["outcome"]["capture_time"] == 3 and done["event"]["captured_by"] == "r2"
        assert done["episodes_received"] == ["r1", "r2", "r3", "r4"]

        # a fifth robot while the server runs: the kit again (the others keep their credentials)
        t0 = time.monotonic()
        more = kit(*common, "--robots", "r1,r2,r3,r4,r5")
        assert more.returncode == 0 and "new credentials for r5" in more.stdout, more.stdout
        assert "kept the credentials of r1" in more.stdout and "the running server takes the change" in more.stdout
        wait_until(lambda: "router re-opened" in (logs / "server.log").read_text(), 30, "the router to re-open")
        reopened = time.monotonic() - t0
        wait_until(lambda: online() >= {"r1", "r2", "r3", "r4"}, 60, "the robots to reconnect", every=0.05)
        back = time.monotonic() - t0
        start_robot("r5", out / "robots" / "r5")
        wait_until(lambda: "r5" in online(), 60, "r5 online", every=0.2)
        print(f"robots add (kit): router re-opened {reopened:.2f} s after, 4 robots back after {back:.2f} s")
        m = api.post("/api/v1/missions", {"seed": 2, "max_steps": 10})
        done = wait_until(
            lambda: (x := api.get(f"/api/v1/missions/{m['id']}"))["status"] == "completed" and x, 60, "mission"
        )
        assert done["episodes_received"] == ["r1", "r2", "r3", "r4", "r5"]

        # r6 added by hand first, then named to the kit with a simulated world: the kit writes r6 a
        # bundle (new credentials: the hand-issued token cannot be read back), and `mures world`
        # joins the TLS router with the world's credentials and flies r6 on --backend sim
        add = subprocess.run(
            [
                str(BIN / "training-server"),
                "robots",
                "add",
                "r6",
                "--data-dir",
                str(data),
                "--out",
                str(tmp_path / "r6"),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert add.returncode == 0, add.stderr
        sim = kit(*common, "--robots", "r1,r2,r3,r4,r5,r6", "--world")
        assert sim.returncode == 0 and "r6 held credentials from `robots add`" in sim.stdout, sim.stdout + sim.stderr
        assert (out / "robots" / "r6" / "token").is_file() and (out / "world" / "zenoh-password").is_file()
        wait_until(
            lambda: (logs / "server.log").read_text().count("router re-opened") >= 2, 30, "the router to re-open"
        )
        assert sourced(out / "world" / "world.env") == read_env(out / "world" / "world.env")
        wenv = read_env(out / "world" / "world.env")
        world_cmd = [str(BIN / "mures"), "world", *shlex.split(wenv["MURES_MAP_ARGS"]), "--fleet", wenv["MURES_FLEET"]]
        world_cmd += ["--zenoh-connect", wenv["MURES_ZENOH_CONNECT"], "--zenoh-ca", str(out / "world" / "ca.pem")]
        world_cmd += ["--zenoh-password-file", str(out / "world" / "zenoh-password")]
        start("world", world_cmd)
        wait_until(lambda: "simulating fleet" in (logs / "world.log").read_text(), 60, "the world up")
        r6 = read_env(out / "robots" / "r6" / "robot.env")
        r6.update(MURES_ROBOT_DIR=str(out / "robots" / "r6"), MURES_BACKEND="sim")
        cmd = exec_start(UNITS / "mures-robot-agent.service", r6)
        cmd[cmd.index("--state-dir") + 1] = str(tmp_path / "state-r6")
        start("r6", cmd)
        wait_until(lambda: "r6" in online(), 60, "r6 online", every=0.2)
        m = api.post("/api/v1/missions", {"robots": ["r6"], "seed": 3, "max_steps": 8})
        done = wait_until(
            lambda: (x := api.get(f"/api/v1/missions/{m['id']}"))["status"] == "completed" and x,
            60,
            "simulated mission",
        )
        assert done["episodes_received"] == ["r6"] and not done["withdrawn"], done

        # r4 revoked: the router no longer admits it; the others reconnect
        t0 = time.monotonic()
        rv = subprocess.run(
            [str(BIN / "training-server"), "robots", "revoke", "r4", "--data-dir", str(data)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert rv.returncode == 0, rv.stderr
        wait_until(
            lambda: (logs / "server.log").read_text().count("router re-opened") == 3, 30, "the router to re-open"
        )
        wait_until(lambda: online() == {"r1", "r2", "r3", "r5", "r6"}, 60, "the others back, without r4", every=0.05)
        print(f"robots revoke: 5 robots back after {time.monotonic() - t0:.2f} s")
        # r4 is listed as revoked, and its agent stops with status 2 (systemd does not restart it), saying why
        r4 = next(a for a in api.get("/api/v1/fleet")["agents"] if a["robot_id"] == "r4")
        assert r4["state"] == "revoked" and r4["revoked"] is not None
        assert reap(procs["r4"], 30) == 2
        assert "credentials were revoked" in (logs / "r4.log").read_text().splitlines()[-1]
        assert "r4" not in online()
    finally:
        for name, p in procs.items():
            if name != "server":
                p.terminate()
                reap(p, 20)
        procs["server"].terminate()
        assert reap(procs["server"], 30) == 0
