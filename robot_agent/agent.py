"""`robot-agent`: one robot's agent process (docs/operating.md).

    robot-agent --robot-id ID --server URL --zenoh-connect ENDPOINT [--fleet NAME]
                [--token-file F] [--state-dir DIR] [--backend sim|nav2|MODULE:CLASS] [--no-telemetry]

The agent connects to the fleet over Zenoh, declares its liveliness token, waits for missions on
``mures/<fleet>/missions/*``, flies each with the committed policy and its own belief filter
(Algorithm 1: decisions use this robot's own positions and observations only), and reports the
mission's episode record through a durable outbox. It pulls a new policy version over HTTP only
between missions.

State directory (default ./mures-agent-<robot_id>):
    map.json                 the server's map (used when the server is unreachable at start)
    policies/v<k>/           verified policy snapshots; current.json names the one in use
    outbox/<mission>.json    records not yet acknowledged by the server (resent until ok)
    outbox/rejected/         records the server refused as invalid (kept, with the reason)
    journal.jsonl            the mission in progress, step by step; after a crash it becomes a
                             record (outcome: not captured) so that no observation is lost
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import queue
import shutil
import signal
import sys
import tarfile
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from robot_agent.backend import (
    BackendError,
    CheckedBackend,
    MissionOver,
    load_backend,
    resolve_backend,
)
from robot_agent.teamwork import TEAM_WAIT_S, Teamwork
from shared.core.clock import has_edge_lengths, move_seconds
from shared.core.files import atomic_write, read_token
from shared.core.graph import Graph, graph_from_dict
from shared.core.http import ApiClient, ApiError
from shared.core.models import Sensor
from shared.core.records import make_record
from shared.core.snapshot_format import PolicyAgent, SnapshotData, SnapshotError, read_snapshot
from shared.core.team import FALLBACK_AFTER, LinkHistory, TeamAgent, mission_seed, team_searcher_of
from shared.core.timed_team import TimedTeamAgent
from shared.core.wire import (
    DEFAULT_FLEET,
    MAX_REASON_CHARS,
    add_zenoh_arguments,
    agent_key,
    check_id,
    client_config,
    detection_key,
    detection_message,
    episode_key,
    mission_key,
    parse_message,
    telemetry_key,
    time_limit,
    withdrawal_key,
    withdrawal_message,
)

log = logging.getLogger("mures.agent")

END_WAIT_S = 10.0  # how long to wait for the end message after the world said the mission is over
VERDICT_WAIT_S = 3.0  # after a detection (capture "auto", or on the last step): the server's verdict, at most
TELEMETRY_HZ = 5  # live state messages a second at most, during a mission
IDLE_BEAT_S = 5.0  # and one every this many seconds between missions
IDLE_CHECK_S = 30.0  # between missions, the server is asked this often for a new version (--idle-check)
TELEMETRY_MAX_NODES = 2048  # the belief rides along on maps up to this size (a few KB a message)


class Outbox:
    """Records waiting for the server's ok: one file each, written (fsync) before any send."""

    def __init__(self, root: Path) -> None:
        self.root = root
        (root / "rejected").mkdir(parents=True, exist_ok=True)

    def put(self, record: dict[str, Any]) -> Path:
        path = self.root / f"{record['mission_id']}.json"
        atomic_write(path, json.dumps(record, separators=(",", ":")).encode())
        return path

    def pending(self) -> list[Path]:
        return sorted(p for p in self.root.glob("*.json") if not p.name.startswith("."))

    def reject(self, path: Path, reason: str) -> None:
        dest = self.root / "rejected" / path.name
        os.replace(path, dest)
        (dest.with_suffix(".reason.txt")).write_text(reason + "\n", encoding="utf-8")


class Journal:
    """The mission in progress, one JSON line per step (the header first)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.fh: Any = None

    def begin(self, header: dict[str, Any]) -> None:
        self.fh = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - kept open for the mission
        self._line(header)

    def step(self, t: int, node: int, z: int) -> None:
        self._line({"t": t, "node": node, "z": z})

    def _line(self, obj: dict[str, Any]) -> None:
        self.fh.write(json.dumps(obj) + "\n")
        self.fh.flush()  # in the OS on every step: survives the agent being killed

    def finish(self) -> None:
        if self.fh:
            self.fh.close()
            self.fh = None
        self.path.unlink(missing_ok=True)

    def recover(self) -> tuple[dict[str, Any], list[dict[str, int]]] | None:
        """The header and steps of a mission cut short by a crash, if any."""
        if not self.path.exists():
            return None
        header: dict[str, Any] | None = None
        steps: list[dict[str, Any]] = []
        for line in self.path.read_text(encoding="utf-8", errors="replace").splitlines():
            try:
                obj = json.loads(line)
            except ValueError:
                break  # a torn last line
            if header is None:
                header = obj
            elif obj.get("t") == len(steps):
                steps.append(obj)
        return (header, steps) if header and steps else None


class PolicyStore:
    """Verified policy snapshots on disk and the one in use."""

    def __init__(self, root: Path, graph: Graph) -> None:
        self.root = root
        self.graph = graph
        root.mkdir(parents=True, exist_ok=True)
        self.version: int | None = None
        self.snapshot: SnapshotData | None = None

    def load_current(self) -> bool:
        cur = self.root / "current.json"
        if not cur.exists():
            return False
        try:
            v = int(json.loads(cur.read_text(encoding="utf-8"))["version"])
            self.snapshot = read_snapshot(self.root / f"v{v}", self.graph)
            self.version = v
            return True
        except (SnapshotError, ValueError, KeyError, OSError) as exc:
            log.warning("cached policy unusable (%s); will download", exc)
            return False

    def use(self, version: int) -> bool:
        """Switch to a version installed before (verified again); False when there is none."""
        if version == self.version:
            return True
        if not (self.root / f"v{version}").is_dir():
            return False
        try:
            snap = read_snapshot(self.root / f"v{version}", self.graph)
        except SnapshotError as exc:
            log.warning("installed version %d unusable (%s); will download", version, exc)
            return False
        self.snapshot, self.version = snap, version
        return True

    def install(self, version: int, tar_path: Path, sha256: str) -> None:
        """Verify and swap in a downloaded artifact; raise ValueError (keeping the last good one)."""
        h = hashlib.sha256(tar_path.read_bytes()).hexdigest()
        if h != sha256:
            raise ValueError(f"artifact sha256 {h[:12]}... does not match the server's {sha256[:12]}...")
        tmp = Path(tempfile.mkdtemp(prefix=f".v{version}.", dir=self.root))
        try:
            with tarfile.open(tar_path) as tar:
                tar.extractall(tmp, filter="data")  # refuses absolute paths, links out, devices
            try:
                snap = read_snapshot(tmp, self.graph)  # graph_id, node order, shapes, weights sha256
                PolicyAgent(snap, self.graph, 0, team=True)  # a policy this agent can run
            except SnapshotError as exc:
                raise ValueError(str(exc)) from None
            final = self.root / f"v{version}"
            shutil.rmtree(final, ignore_errors=True)
            os.replace(tmp, final)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        atomic_write(self.root / "current.json", json.dumps({"version": version, "sha256": sha256}).encode())
        self.snapshot = read_snapshot(self.root / f"v{version}", self.graph)
        self.version = version


RECEIVED = "_received_monotonic"  # the agent's own mark on a control message: when it arrived


class AgentStop(Exception):
    """A reason to stop the agent (exit status 2) that retrying cannot fix."""


class Agent:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.robot_id = check_id("robot id", args.robot_id)
        self.fleet = check_id("fleet", args.fleet)
        token = read_token(args.token_file) if args.token_file else None
        self.api = ApiClient(args.server, token, timeout=10.0, ca_file=args.ca_file)
        self.state = Path(args.state_dir or f"mures-agent-{self.robot_id}")
        self.state.mkdir(parents=True, exist_ok=True)
        self.stop = threading.Event()
        self.control: queue.Queue[dict[str, Any]] = queue.Queue()
        # a start for this robot that came during a mission: flown when that mission ends (the
        # server frees a robot when its mission is captured or stopped, before this agent has
        # finished and sent the record, so an operator's next start can come that early)
        self.next_start: dict[str, Any] | None = None
        self.flush_now = threading.Event()
        self.outbox = Outbox(self.state / "outbox")
        self.journal = Journal(self.state / "journal.jsonl")
        self.session: Any = None
        self.graph: Graph | None = None
        self.team_clock = "steps"  # "steps" or "seconds": --team-clock resolved once the map is fetched (run)
        self.ask_world = False  # --team-clock auto with --backend sim: the simulated world's clock, until it says
        self.policies: PolicyStore | None = None
        self.in_mission = False
        self.telemetry_pub: Any = None
        self.last_telemetry = 0.0
        self.last_node: int | None = None
        self.links = LinkHistory()  # what the links delivered over this agent's missions
        self.team: Teamwork | None = None  # the mission in progress's teamwork
        self.last_failure: dict[str, str] | None = None  # the last mission this robot withdrew from, and why

    # ------------------------------------------------------------------ HTTP
    def _refused(self, exc: ApiError) -> None:
        """A server that refuses this agent's token will not change its mind: stop (exit 2), with
        the reason, instead of retrying while showing as online."""
        if exc.status in (401, 403):
            why = exc.body.get("error") if isinstance(exc.body, dict) else exc.body
            hint = (
                "this agent has no --token-file; give it the agent token (or its own robot token)"
                if self.api.token is None
                else f"check --token-file {self.args.token_file}: the server refuses it"
            )
            raise AgentStop(f"the server answered {exc.status} ({why}): {hint}")

    def fetch_map(self) -> Graph:
        cache = self.state / "map.json"
        while not self.stop.is_set():
            try:
                data = self.api.get("/api/v1/map")
                graph = graph_from_dict(data, "server map")
                if graph.graph_id != data.get("graph_id"):
                    raise ValueError("the server's map does not hash to its graph_id")
                atomic_write(cache, json.dumps(data).encode())
                return graph
            except (OSError, ApiError, ValueError) as exc:
                if isinstance(exc, ApiError):
                    self._refused(exc)
                if cache.exists():
                    log.warning("server unreachable (%s); using the cached map", exc)
                    return graph_from_dict(json.loads(cache.read_text(encoding="utf-8")), str(cache))
                log.warning("waiting for the server's map: %s", exc)
                self.stop.wait(2.0)
        raise SystemExit(0)

    def sync_policy(self, reason: str, version: int | None = None) -> None:
        """Between missions only: take ``version`` (a mission's), else the server's current one, if
        it differs from ours; a version installed before is switched to without a download."""
        assert self.policies is not None and self.graph is not None
        try:
            if version is not None and self.policies.use(version):
                log.info("policy version -> %d (%s; installed before)", version, reason)
                return
            meta = self.api.get("/api/v1/policies/current" if version is None else f"/api/v1/policies/{int(version)}")
            version, sha = int(meta["version"]), str(meta["sha256"])
            if meta.get("meta", {}).get("graph_id") != self.graph.graph_id:
                raise ValueError(f"version {version} is for another map")
            if version == self.policies.version:
                return
            tar_path = self.policies.root / f"v{version}.tar"
            headers = {"If-None-Match": f'"{sha}"'} if tar_path.exists() else {}
            status, resp_headers, body = self.api.request(
                "GET", f"/api/v1/policies/{version}/artifact", headers=headers, timeout=60
            )
            if status != 304:  # 304: the tar we have is this version's
                etag = resp_headers.get("etag", "").strip('"')
                if etag and etag != sha:
                    raise ValueError(f"artifact ETag {etag[:12]}... differs from the version's sha256")
                atomic_write(tar_path, body)
            old = self.policies.version
            self.policies.install(version, tar_path, sha)
            log.info("policy version %s -> %d (%s)", old, version, reason)
        except (OSError, ApiError, ValueError, KeyError, TypeError) as exc:
            if isinstance(exc, ApiError):
                self._refused(exc)
            have = self.policies.version
            log.warning("policy update failed (%s); keeping version %s", exc, have)

    # ------------------------------------------------------------------ Zenoh
    def telemetry(self, msg: dict[str, Any], force: bool = False, belief: Any = None, team_belief: Any = None) -> None:
        """Live state on mures/<fleet>/telemetry/<id> (docs/SPEC.md section 6), at most TELEMETRY_HZ
        a second (``force``: now); during a mission with the robot's own belief and, flying with a
        team searcher, the team's collective belief it holds, rounded. Best effort: a lost message
        is replaced by the next one."""
        now = time.monotonic()
        if self.telemetry_pub is None or (not force and now - self.last_telemetry < 1.0 / TELEMETRY_HZ):
            return
        self.last_telemetry = now
        out = {
            **msg,
            "policy_version": self.policies.version if self.policies else None,
            "backend": self.args.backend,
            "ts": round(time.time(), 3),
        }
        if self.on_the_clock():  # the server's default time limit for a mission over REST is read off it
            out.update(clock="seconds", speed=self.args.speed)
        for key, b in (("belief", belief), ("team_belief", team_belief)):
            if b is not None and len(b) <= TELEMETRY_MAX_NODES:
                out[key] = [round(float(x), 4) for x in np.asarray(b)]
        try:
            self.telemetry_pub.put(json.dumps(out).encode())
        except Exception as exc:  # never let telemetry stop a mission
            log.debug("telemetry: %s", exc)

    def on_the_clock(self) -> bool:
        """Whether this robot's next mission flies on the mission clock: ``--team-clock`` resolved to
        seconds, or a current version trained on the clock (it always flies on it)."""
        snap = self.policies.snapshot if self.policies else None
        return self.team_clock == "seconds" or (snap is not None and snap.clock is not None)

    def ask_world_clock(self, backend: CheckedBackend, timeout: float) -> None:
        """``--team-clock auto`` with ``--backend sim``: the simulated world's own clock (the
        continuous world keeps the mission clock), once it answers; the step index until then."""
        if not self.ask_world:
            return
        clock = backend.world_clock(timeout)
        if clock is None:
            return
        self.ask_world, self.team_clock = False, clock
        log.info(
            "team clock: %s (--team-clock auto: the simulated world keeps %s)",
            "the mission clock" if clock == "seconds" else "step index",
            "the mission clock" if clock == "seconds" else "every robot's step together",
        )

    def report_down(self, reason: str) -> None:
        """The last live state before the agent stops on an error it cannot retry: the server keeps it,
        so the fleet view says why this robot is down. Sent reliably, whatever --telemetry says."""
        msg = {
            "state": "down",
            "reason": reason[:MAX_REASON_CHARS],
            "backend": self.args.backend,
            "ts": round(time.time(), 3),
        }
        try:
            self.session.put(
                telemetry_key(self.fleet, self.robot_id),
                json.dumps(msg).encode(),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except Exception as exc:
            log.debug("down report: %s", exc)

    def withdraw(self, mission_id: str, steps: int, reason: str) -> None:
        """This robot cannot go on with the mission (its backend failed): say why, once, to the
        server (mures/<fleet>/withdrawals/<robot>/<mission>, sent reliably), which ends this
        robot's part of the mission at once and tells its teammates and the simulated world. The
        agent stays up for the next mission; its idle state carries the reason."""
        log.error("mission %s: withdrawn after %d steps: %s", mission_id, steps, reason)
        self.last_failure = {"mission_id": mission_id, "reason": reason[:MAX_REASON_CHARS]}
        try:
            self.session.put(
                withdrawal_key(self.fleet, self.robot_id, mission_id),
                json.dumps(withdrawal_message(mission_id, self.robot_id, steps, reason)).encode(),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except Exception as exc:  # the mission then ends at its deadline, as a robot that vanished
            log.error("mission %s: the withdrawal could not be sent: %s", mission_id, exc)

    def report_detection(self, mission_id: str, t: int, node: int, time_s: float | None = None) -> None:
        """Tell the server that this robot read z = 1 at step t on ``node``
        (mures/<fleet>/detections/<robot>/<mission>); it ends the mission as captured, or asks the
        operator first (``training-server --capture``). Sent reliably (BLOCK); a failure to send is
        logged and the mission goes on: the record still carries the reading."""
        msg = detection_message(mission_id, self.robot_id, t, node, time_s)
        log.info("mission %s: detection at t=%d on node %d reported", mission_id, t, node)
        try:
            self.session.put(
                detection_key(self.fleet, self.robot_id, mission_id),
                json.dumps(msg).encode(),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        except Exception as exc:
            log.error("mission %s: the detection at t=%d could not be sent: %s", mission_id, t, exc)

    def _on_control(self, sample: Any) -> None:  # callback: queue only
        msg = parse_message(sample.payload.to_bytes())
        if msg is not None:
            msg[RECEIVED] = time.monotonic()  # a start's arrival begins this robot's mission clock
            self.control.put(msg)

    def open_session(self) -> None:
        conf = client_config(self.args, self.robot_id)  # the robot's Zenoh user is its id
        while not self.stop.is_set():
            try:
                self.session = zenoh.open(conf)
                return
            except zenoh.ZError as exc:
                log.warning("cannot reach the Zenoh router %s (%s); retrying", self.args.zenoh_connect, exc)
                self.stop.wait(2.0)
        raise SystemExit(0)

    def flush_loop(self) -> None:
        backoff = 0.5
        while not self.stop.is_set():
            sent_all = self.flush_once()
            backoff = 0.5 if sent_all else min(backoff * 2, 10.0)
            self.flush_now.wait(backoff if not sent_all else 5.0)
            self.flush_now.clear()

    def flush_once(self, timeout: float = 10.0) -> bool:
        """Send every pending record; True when the outbox is empty afterwards."""
        ok_all = True
        for path in self.outbox.pending():
            try:
                data = path.read_bytes()
                rec = json.loads(data)
                key = episode_key(self.fleet, rec["robot_id"], rec["mission_id"])
            except (OSError, ValueError, KeyError) as exc:
                self.outbox.reject(path, f"unreadable in the outbox: {exc}")
                continue
            answered = False
            for reply in self.session.get(
                key, payload=data, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE
            ):
                answered = True
                if reply.ok is not None:
                    path.unlink(missing_ok=True)
                    log.debug("%s: %s", path.name, reply.ok.payload.to_bytes().decode())
                else:
                    text = reply.err.payload.to_bytes()
                    try:
                        err = json.loads(text)
                    except ValueError:
                        err = None
                    if not isinstance(err, dict) or "reason" not in err or err["reason"] == "server-error":
                        ok_all = False  # a timeout or a server fault, not a verdict on the record: resend later
                        log.warning("sending %s: %s; will resend", path.name, text.decode(errors="replace")[:200])
                    else:  # invalid record: keep it aside with the reason, do not resend forever
                        log.error("server rejected %s: %s", path.name, err.get("error"))
                        self.outbox.reject(path, json.dumps(err))
                break
            if not answered:
                ok_all = False
                break  # the server is unreachable: try again later
        return ok_all

    # ------------------------------------------------------------------ missions
    def recover_journal(self) -> None:
        got = self.journal.recover()
        if got is None:
            return
        header, steps = got
        rec = self._record(header, steps, None)
        self.outbox.put(rec)
        self.journal.finish()
        log.warning(
            "mission %s was cut short (%d steps recorded); its record is in the outbox",
            header["mission_id"],
            len(steps),
        )

    def _record(
        self, header: dict[str, Any], steps: list[dict[str, Any]], end: dict[str, Any] | None
    ) -> dict[str, Any]:
        graph = self.graph
        assert graph is not None, "the map is fetched before any mission"
        captured, ct, by = False, None, None
        capture_s = header.get("capture_time_s")
        if end and end.get("type") == "captured" and "time_s" in steps[0]:
            # on the mission clock: this robot's readings up to the capture's moment (its step count is its
            # own); a moment it never learned (a lost message) keeps every reading it made
            if capture_s is not None:
                steps = [s for s in steps if s["time_s"] <= capture_s + 1e-6]
            captured, ct, by = True, len(steps) - 1, end.get("captured_by")
        # a robot whose own steps end before the capture (withdrawn, restarted) did not witness it
        elif end and end.get("type") == "captured" and isinstance(end.get("t"), int) and end["t"] <= steps[-1]["t"]:
            captured, ct, by = True, int(end["t"]), end.get("captured_by")
            steps = steps[: ct + 1]
        sensor = Sensor(**header["sensor"])
        return make_record(
            graph,
            fleet=self.fleet,
            mission_id=header["mission_id"],
            robot_id=self.robot_id,
            nodes=[graph.index[s["node"]] for s in steps],
            z=[s["z"] for s in steps],
            sensor=sensor,
            captured=captured,
            capture_time=ct,
            captured_by=by,
            policy_version=header.get("policy_version"),
            coordination=header.get("coordination"),  # decisions on the team's plan and on its own policy
            times=[s["time_s"] for s in steps] if all("time_s" in s for s in steps) else None,
        )

    def run_mission(self, msg: dict[str, Any], backend: CheckedBackend) -> None:
        """Fly one mission (Algorithm 1, this robot's part) from its start message to its end, then
        leave its episode record in the outbox."""
        self.ask_world_clock(backend, 2.0)
        agent, header, max_steps, auto_capture = self._begin_mission(msg)
        max_seconds = time_limit(msg)
        mid = header["mission_id"]
        steps: list[dict[str, Any]] = []
        decide_us: list[float] = []
        end: dict[str, Any] | None = None
        self.in_mission = True
        self.journal.begin(header)
        assert self.graph is not None
        team = Teamwork(
            self.session, self.fleet, self.graph, mid, agent, wait_s=self.args.team_wait, link_loss=self.args.link_loss
        )
        # a simulated world answers together only the robots that wait for each other
        backend.tell_team_wait(0.0 if isinstance(agent, TimedTeamAgent) else self.args.team_wait)
        self.team, self.last_failure = team, None
        try:
            end = self._search(backend, msg, agent, team, (max_steps, max_seconds), auto_capture, steps, decide_us)
        except MissionOver:
            end = self._control_for(mid, wait=END_WAIT_S)
        except BackendError as exc:
            self.withdraw(mid, len(steps), str(exc))
        except Exception as exc:  # a fault of the agent's own: this mission ends for it, the agent stays up
            log.exception("mission %s: the agent failed", mid)
            self.withdraw(mid, len(steps), f"the agent failed ({type(exc).__name__}: {exc})")
        finally:
            self.team = None
            team.close()
            self.in_mission = False
            if steps:
                self.last_node = steps[-1]["node"]
            try:
                backend.end()
            except Exception as exc:
                log.warning("backend end(): %s", exc)
        if not steps:  # not even z_0: there is no record to make (an empty one would be refused)
            log.error("mission %s: no step was recorded, so no record is sent", mid)
            self.journal.finish()
            return
        header["coordination"] = {"team_searcher": agent.searcher, **agent.summary()}
        if (
            isinstance(agent, TimedTeamAgent)
            and end
            and end.get("type") == "captured"
            and isinstance(end.get("t"), int)
        ):
            # the capture's moment: the server's word, else the capturer's observation as heard
            heard = agent.reading_s.get((str(end.get("captured_by")), int(end["t"])))
            header["capture_time_s"] = end["time_s"] if isinstance(end.get("time_s"), int | float) else heard
        self.links.fold(*agent.link_counts())
        self._finish_mission(header, steps, end, decide_us)

    def _begin_mission(self, msg: dict[str, Any]) -> tuple[TeamAgent, dict[str, Any], int, bool]:
        """This robot's TeamAgent for the mission (the policy version it names, fetched first if
        need be; its team searcher the version's, a robot alone's too), the record's header,
        the step limit, and whether detections capture at once."""
        assert self.policies is not None and self.graph is not None
        mid = msg["mission_id"]
        robots = msg.get("robots") or [self.robot_id]
        index = robots.index(self.robot_id)
        if msg.get("policy_version") is not None and msg["policy_version"] != self.policies.version:
            self.sync_policy(f"before mission {mid}", version=int(msg["policy_version"]))  # still between missions
        snap = self.policies.snapshot
        assert snap is not None, "run() waits for a policy before taking missions"
        seed = int(msg.get("seed") or 0)
        team_kw: dict[str, Any] = {
            "seed": seed,
            "searcher": team_searcher_of(snap),  # a robot alone plans on its own belief, the team's
            "fallback_after": self.args.fallback_after,
            "own_seed": mission_seed(seed, index),
            "link_history": self.links,
        }
        # matched by the mission clock (shared/core/timed_team.py); a version trained on the clock
        # (`mures train --speed`, its model per tick) always flies on it
        if self.on_the_clock():
            step_s = move_seconds(self.graph, self.args.speed)
            agent: TeamAgent = TimedTeamAgent(snap, self.graph, robots, self.robot_id, step_s=step_s, **team_kw)
        else:
            agent = TeamAgent(snap, self.graph, robots, self.robot_id, **team_kw)
        header = {
            "mission_id": mid,
            "policy_version": self.policies.version,
            "sensor": snap.sensor.to_json(),
            "seed": msg.get("seed"),
            "index": index,
        }
        log.info("mission %s: robot %d of %d, policy version %s", mid, index + 1, len(robots), self.policies.version)
        return agent, header, int(msg.get("max_steps") or 3 * self.graph.n), msg.get("capture", "auto") != "confirm"

    def _search(
        self,
        backend: CheckedBackend,
        msg: dict[str, Any],
        agent: TeamAgent,
        team: Teamwork,
        limits: tuple[int, float | None],
        auto_capture: bool,
        steps: list[dict[str, Any]],
        decide_us: list[float],
    ) -> dict[str, Any] | None:
        """From the mission's start (``msg``): sense, update the belief, decide and move until the
        mission ends (the end message, or None at the step limit, at the first reading at or past
        the time limit on the mission clock, or on stop); each step is appended to ``steps`` as it
        is taken. ``limits``: (max_steps, max_seconds or None)."""
        assert self.graph is not None
        graph, mid = self.graph, team.mission_id
        max_steps, max_seconds = limits
        timed = agent if isinstance(agent, TimedTeamAgent) else None
        clocked = timed is not None or max_seconds is not None  # readings carry the mission clock
        node = backend.begin(msg)  # a label on the map, z a 0 or 1 (CheckedBackend)
        started = float(msg.get(RECEIVED, time.monotonic()))  # the mission clock's zero: the start's arrival
        t, now_s = 0, 0.0
        while True:
            z = backend.detect()  # z_t at p_t
            t0 = time.perf_counter()
            p = graph.index[node]
            # Eq. 1 (own belief; t = 0: b_0 ∝ Lambda(p_0, z_0) b0) and Eq. 6 (the team's, with the
            # teammates' observations as they come)
            if clocked:  # the reading's time: the backend's mission clock, else this agent's
                clock = backend.clock()  # checked seconds, or None
                now_s = clock if clock is not None else time.monotonic() - started
            if timed is not None:
                timed.observe_at(self.robot_id, t, p, z, now_s)
            else:
                agent.observe(self.robot_id, t, p, z)
                team.publish(t, node, z)
            steps.append({"t": t, "node": node, "z": z, **({"time_s": now_s} if clocked else {})})
            self.journal.step(t, node, z)
            if z:  # the server decides whether this detection ends the mission (docs/SPEC.md section 6)
                self.report_detection(mid, t, node, now_s if clocked else None)
                if timed is not None:  # its teammates learn the moment now, whatever the robot decides next
                    team.publish(t, node, z, time_s=now_s)
            # under "auto" the server's verdict comes at once: wait for it before moving on (a robot
            # that has found the target stays with it); under "confirm" the search goes on meanwhile
            last = t >= max_steps or (max_seconds is not None and now_s >= max_seconds)  # the mission's limit
            wait = z and (auto_capture or last)
            end = self._control_for(mid, wait=VERDICT_WAIT_S if wait else 0.0)
            if end is not None or last or self.stop.is_set():
                return end
            waited = time.perf_counter()
            team.gather(t)  # the teammates' step t, waiting a bounded time for what is missing
            t1 = time.perf_counter()
            # the team's plan, or a_t ~ pi_i(. | onehot(p_t), b_t) (Algorithm 1)
            row, mode = agent.act(t, p) if timed is None else timed.act_at(now_s, p)
            goal = int(graph.labels[row])
            if timed is not None:  # on the clock: the observation goes out with where the robot is headed
                team.publish(t, node, z, time_s=now_s, goal=goal)
            decide_us.append((waited - t0 + time.perf_counter() - t1) * 1e6)  # the wait for teammates left out
            self.telemetry(
                {"state": "mission", "mission_id": mid, "t": t, "node": node, "z": z, "goal": goal, "mode": mode},
                force=t == 0,
                belief=agent.own.belief,
                team_belief=(
                    agent.collective.belief(t if timed is None else timed.tick(now_s))
                    if agent.searcher is not None
                    else None
                ),
            )
            node = backend.move(goal)  # a label on the map (CheckedBackend)
            t += 1

    def _finish_mission(
        self, header: dict[str, Any], steps: list[dict[str, Any]], end: dict[str, Any] | None, decide_us: list[float]
    ) -> None:
        """The mission's episode record into the outbox (durable before it is sent), and what it took."""
        rec = self._record(header, steps, end)
        self.outbox.put(rec)
        self.journal.finish()
        self.flush_now.set()
        med = float(np.median(decide_us)) if decide_us else float("nan")
        out = rec["outcome"]
        log.info(
            "mission %s over after %d steps: %s; decision step median %.1f us",
            header["mission_id"],
            len(rec["steps"]) - 1,
            f"captured at t={out['capture_time']} by {out['captured_by']}"
            if out["captured"]
            else (end or {}).get("type", "not captured"),
            med,
        )
        summary = {"mission_id": header["mission_id"], "decide_us_median": med, "decisions": len(decide_us)}
        atomic_write(self.state / "last_mission.json", json.dumps({**summary, "steps": len(rec["steps"])}).encode())

    def _control_for(self, mid: str, wait: float = 0.0) -> dict[str, Any] | None:
        """The end message (captured/stop) of mission ``mid`` if one has arrived. A start for this
        robot is kept in ``next_start`` (the latest wins; its own end message cancels it); other
        messages are dropped."""
        deadline = time.monotonic() + wait
        while True:
            try:
                msg = (
                    self.control.get(timeout=max(0.0, deadline - time.monotonic()))
                    if wait
                    else self.control.get_nowait()
                )
            except queue.Empty:
                return None
            if msg["mission_id"] == mid and msg["type"] in ("captured", "stop"):
                return msg
            team, robot = self.team, msg.get("robot_id")
            if msg["mission_id"] == mid and msg["type"] == "withdrawn" and team is not None and robot != self.robot_id:
                team.gone.put(str(robot))  # a teammate whose backend failed: dropped from the team's plan at once
            if msg["type"] == "start" and msg["mission_id"] != mid and self._for_me(msg):
                if self.next_start is not None:
                    log.warning(
                        "mission %s replaced by mission %s before it began",
                        self.next_start["mission_id"],
                        msg["mission_id"],
                    )
                log.info("mission %s started while %s is running; it begins when %s ends", msg["mission_id"], mid, mid)
                self.next_start = msg
            elif (
                msg["type"] in ("captured", "stop")
                and self.next_start is not None
                and msg["mission_id"] == self.next_start["mission_id"]
            ):
                log.info("mission %s ended before it began here", msg["mission_id"])
                self.next_start = None

    def _for_me(self, msg: dict[str, Any]) -> bool:
        return self.robot_id in (msg.get("robots") or [self.robot_id])

    def next_control(self, timeout: float) -> dict[str, Any] | None:
        """Between missions: the start deferred during the last mission, else the next message."""
        if self.next_start is not None:
            msg, self.next_start = self.next_start, None
            return msg
        try:
            return self.control.get(timeout=timeout)
        except queue.Empty:
            return None

    # ------------------------------------------------------------------ main loop
    def run(self) -> int:
        self.open_session()
        token = self.session.liveliness().declare_token(agent_key(self.fleet, self.robot_id))
        sub = self.session.declare_subscriber(mission_key(self.fleet, "*"), self._on_control)
        flusher = None
        try:
            self.graph = self.fetch_map()
            self.team_clock = team_clock_for(self.args.team_clock, self.args.backend, self.graph)
            auto_sim = self.args.team_clock == "auto" and self.args.backend == "sim"
            self.ask_world = auto_sim and has_edge_lengths(self.graph)
            if self.team_clock == "seconds":
                move_seconds(self.graph, self.args.speed)  # ValueError: the map has no edge lengths
            log.info(
                "team clock: %s%s",
                "the mission clock" if self.team_clock == "seconds" else "step index",
                " (--team-clock auto)" if self.args.team_clock == "auto" else "",
            )
            self.policies = PolicyStore(self.state / "policies", self.graph)
            self.policies.load_current()
            self.sync_policy("start")
            while self.policies.version is None and not self.stop.is_set():
                self.stop.wait(2.0)
                self.sync_policy("start")
            self.recover_journal()
            flusher = threading.Thread(target=self.flush_loop, name="outbox", daemon=True)
            flusher.start()
            if self.args.telemetry:
                self.telemetry_pub = self.session.declare_publisher(telemetry_key(self.fleet, self.robot_id))
            try:
                backend = load_backend(
                    self.args.backend,
                    graph=self.graph,
                    robot_id=self.robot_id,
                    session=self.session,
                    fleet=self.fleet,
                    args=self.args,
                )
            except ValueError as exc:  # the fleet sees why this robot is down (GET /api/v1/fleet, the console)
                self.report_down(str(exc))
                raise AgentStop(str(exc)) from None
            assert isinstance(backend, CheckedBackend)  # load_backend checks any backend given the map
            log.info("robot %s up in fleet %r with policy version %s", self.robot_id, self.fleet, self.policies.version)
            self.ask_world_clock(backend, 2.0)
            idle_beat, idle_check = 0.0, time.monotonic()
            while not self.stop.is_set():
                if time.monotonic() - idle_check >= self.args.idle_check:  # a new version, or revoked credentials
                    idle_check = time.monotonic()
                    self.sync_policy("idle")
                if time.monotonic() - idle_beat >= IDLE_BEAT_S:  # between missions: alive, idle, where
                    self.ask_world_clock(backend, 0.5)  # (a world started after this robot)
                    idle_beat = time.monotonic()
                    idle: dict[str, Any] = {"state": "idle", "node": self.last_node}
                    if self.last_failure is not None:  # the fleet view shows why its last mission failed
                        idle["last_failure"] = self.last_failure
                    self.telemetry(idle, force=True)
                msg = self.next_control(timeout=0.5)
                if msg is None or msg["type"] != "start" or not self._for_me(msg):
                    continue
                self.run_mission(msg, backend)
                if not self.stop.is_set():
                    self.sync_policy("between missions")
        finally:
            self.stop.set()
            self.flush_now.set()
            if flusher is not None:
                flusher.join(15)
                if self.session is not None:
                    self.flush_once(timeout=3.0)
            sub.undeclare()
            if self.telemetry_pub is not None:
                self.telemetry_pub.undeclare()
            token.undeclare()
            self.session.close()
        log.info("robot %s stopped (%d records waiting in the outbox)", self.robot_id, len(self.outbox.pending()))
        return 0


def team_clock_for(choice: str, backend: str, graph: Graph) -> str:
    """``--team-clock`` resolved: "seconds" or "steps". ``auto`` is the mission clock for a robot
    whose moves take their travel time (any backend but ``sim``) on a map with edge lengths, the
    step index otherwise; a ``sim`` robot on such a map then takes its world's clock when the world
    answers (``Agent.ask_world_clock``)."""
    if choice != "auto":
        return choice
    return "seconds" if backend != "sim" and has_edge_lengths(graph) else "steps"


def positive_seconds(text: str) -> float:
    """A number of seconds above 0 (argparse type)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not 0.0 < v < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number of seconds above 0, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="robot-agent", description="MuRES fleet robot agent")
    p.add_argument("--robot-id", required=True, help="this robot's id (A-Z a-z 0-9 _ . -)")
    p.add_argument("--server", required=True, metavar="URL", help="the training server, e.g. http://10.0.0.2:8000")
    add_zenoh_arguments(
        p, "Zenoh router endpoint, e.g. tcp/10.0.0.2:7447 (repeatable)", connect_required=True, robot=True
    )
    p.add_argument("--fleet", default=DEFAULT_FLEET)
    p.add_argument("--token-file", help="the agent bearer token for the REST API")
    p.add_argument("--ca-file", metavar="PEM", help="CA certificate to verify an https --server with")
    p.add_argument("--state-dir", help="outbox, journal and policies (default ./mures-agent-<robot_id>)")
    p.add_argument(
        "--team-wait",
        type=float,
        default=TEAM_WAIT_S,
        metavar="S",
        help=f"the longest a decision waits for the teammates' observations of its step (default {TEAM_WAIT_S} s)",
    )
    p.add_argument(
        "--fallback-after",
        type=int,
        default=FALLBACK_AFTER,
        metavar="K",
        help="steps in a row without every live teammate's observation before the robot flies its own policy "
        "(default: never while a teammate is heard: the team's plan on what has come)",
    )
    p.add_argument(
        "--team-clock",
        choices=("auto", "steps", "seconds"),
        default="auto",
        help="how the robot matches its teammates' observations: by step index, waiting --team-wait for the "
        "current step's (the paper's model), or by the mission clock, never waiting for a teammate that is "
        "travelling (shared/core/timed_team.py; needs a graph with edge lengths); auto (default): the mission "
        "clock for a robot whose moves take their travel time (a --backend other than sim) on a map with edge "
        "lengths, and for --backend sim in a world that keeps one (mures world --world, asked when the robot "
        "starts, between missions and before each until it answers), step index otherwise; a version trained "
        "on the clock (mures train --speed) always flies on it",
    )
    p.add_argument(
        "--speed",
        type=float,
        default=0.5,
        metavar="M_PER_S",
        help="on the mission clock: the robot's typical travel speed, for how long a step of the model lasts (0.5)",
    )
    p.add_argument(
        "--link-loss",
        type=float,
        default=0.0,
        metavar="P",
        help="simulation only: drop each outgoing observation with probability P (default 0)",
    )
    p.add_argument(
        "--backend",
        default="sim",
        help="sim (fleet simulator), nav2 (a Nav2 robot through zenoh-bridge-ros2dds: robot_agent/nav2.py) or "
        "MODULE:CLASS (robot_agent/backend.py)",
    )
    nav2 = p.add_argument_group("--backend nav2 (docs/connecting-a-robot.md)")
    nav2.add_argument(
        "--nav2-regions", metavar="PNG", help="`mures map import --regions`: a pose's node is its region's"
    )
    nav2.add_argument("--nav2-map", metavar="MAP.yaml", help="with --nav2-regions: the map it was imported from")
    nav2.add_argument(
        "--nav2-connect", metavar="ENDPOINT", help="the robot's zenoh-bridge-ros2dds (default: the fleet's session)"
    )
    nav2.add_argument(
        "--nav2-namespace", metavar="NS", help="the robot's ROS namespace in the bridge (default: its id)"
    )
    nav2.add_argument(
        "--nav2-pose-topic", default="amcl_pose", help="its PoseWithCovarianceStamped (default amcl_pose)"
    )
    nav2.add_argument(
        "--nav2-detection-topic", default="detection", help="its detector's std_msgs/Bool (default detection)"
    )
    nav2.add_argument(
        "--nav2-goal-timeout", type=positive_seconds, default=120.0, metavar="S",
        help="cancel a navigation goal after S seconds; the robot stays where it was (default 120)",
    )  # fmt: skip
    nav2.add_argument(
        "--nav2-answer-timeout", type=positive_seconds, default=10.0, metavar="S",
        help="a robot that leaves a goal or its pose unanswered this long ends the mission for itself (default 10)",
    )  # fmt: skip
    p.add_argument(
        "--telemetry",
        action=argparse.BooleanOptionalAction,
        default=True,
        help=f"publish live state on mures/<fleet>/telemetry/<id>: each step (at most {TELEMETRY_HZ} a second) "
        f"with the robot's belief, and every {IDLE_BEAT_S:.0f} s between missions (default on)",
    )
    p.add_argument(
        "--idle-check",
        type=positive_seconds,
        default=IDLE_CHECK_S,
        metavar="S",
        help=f"between missions, ask the server every S seconds for a new policy version; revoked credentials stop "
        f"the agent then (default {IDLE_CHECK_S:.0f})",
    )
    p.add_argument("--log-level", default="INFO")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=args.log_level.upper(),
        stream=sys.stderr,
        format=f"%(asctime)s %(levelname)s agent[{args.robot_id}]: %(message)s",
    )
    try:
        if not 0.0 <= args.link_loss <= 1.0 or args.team_wait < 0 or (args.fallback_after or 1) < 1:
            raise ValueError("--link-loss takes a probability, --team-wait seconds >= 0, --fallback-after at least 1")
        if not 0.0 < args.speed < float("inf"):
            raise ValueError(f"--speed takes metres a second above 0, got {args.speed}")
        resolve_backend(args.backend)  # a backend that cannot be loaded stops the agent before it connects
        agent = Agent(args)
    except ValueError as exc:
        print(f"robot-agent: error: {exc}", file=sys.stderr)
        return 2

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("signal %d: %s", signum, "ending the mission and stopping" if agent.in_mission else "stopping")
        agent.stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        return agent.run()
    except (ValueError, AgentStop) as exc:
        print(f"robot-agent: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
