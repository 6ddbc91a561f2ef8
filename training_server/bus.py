"""The server's Zenoh side: episode ingest, agent presence, mission control, robots' detections.

Callbacks only hand work to queues (docs/zenoh.md); worker threads validate, store
and reply. Ingest drains its queue in batches so one SQLite transaction (and one fsync) covers
many records, then replies to each query: ok {"status": "stored"|"duplicate"} or err
{"reason": <code>, "error": <message>}.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from typing import Any, TypeGuard

import zenoh

from shared.core.records import MAX_RECORD_BYTES, RecordError, canonical_record, parse_record, unexplained
from shared.core.wire import (
    MAX_REASON_CHARS,
    agent_key,
    detection_key,
    episode_key,
    mission_key,
    parse_detection,
    parse_message,
    parse_withdrawal,
    telemetry_key,
    truth_key,
    withdrawal_key,
)

log = logging.getLogger("mures.server.bus")

INGEST_BATCH = 512
# under --capture auto, the server ends a mission this long after the first detection arrives,
# with the earliest one received by then (ties: the robot listed first in the mission), so that
# two robots that see the target at the same step give the same outcome whichever arrived first
CAPTURE_WINDOW_S = 0.2


LIVE_FIELDS = ("state", "mission_id", "t", "node", "z", "goal", "mode", "policy_version", "backend", "ts")


def live_state(msg: dict[str, Any] | None, n: int) -> dict[str, Any] | None:
    """What the server keeps of a telemetry message (docs/SPEC.md section 6): its known fields, a
    down agent's reason, and its beliefs when each is n probabilities; None when it is not a live
    state."""
    if msg is None or msg.get("state") not in ("mission", "idle", "down"):
        return None
    keep = {
        k: msg.get(k)
        for k in ("state", "mission_id", "t", "node", "z", "goal", "mode", "policy_version", "backend", "ts")
    }
    if msg["state"] == "down":  # the agent stopped on an error it cannot retry, and says which
        keep["reason"] = str(msg.get("reason"))[:MAX_REASON_CHARS]
    failure = msg.get("last_failure")  # the last mission it withdrew from (its backend failed)
    if msg["state"] == "idle" and isinstance(failure, dict) and isinstance(failure.get("mission_id"), str):
        keep["last_failure"] = {
            "mission_id": failure["mission_id"][:200],
            "reason": str(failure.get("reason"))[:MAX_REASON_CHARS],
        }
    speed = msg.get("speed")  # a robot on the mission clock says so, with its speed (m/s)
    if msg.get("clock") == "seconds" and _positive(speed):
        keep["clock"], keep["speed"] = "seconds", float(speed)
    for name in ("belief", "team_belief"):
        b = msg.get(name)
        if isinstance(b, list) and len(b) == n and all(_probability(x) for x in b):
            keep[name] = b
    return keep


def _positive(x: Any) -> TypeGuard[float]:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and 0.0 < x < float("inf")


def _probability(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and 0.0 <= x <= 1.0


def _json_object(raw: bytes) -> dict[str, Any] | None:
    """A best-effort message (telemetry, ground truth) as a JSON object; None when it is larger
    than 1 MiB, not JSON, or not an object (such messages are dropped)."""
    try:
        msg = json.loads(raw) if len(raw) <= 1 << 20 else None
    except ValueError:
        return None
    return msg if isinstance(msg, dict) else None


class Bus:
    def __init__(self, server: Any, conf: Any) -> None:
        self.server = server
        self.fleet = server.fleet
        self.session = zenoh.open(conf)
        self.ingest_q: queue.Queue[Any] = queue.Queue()
        self.events_q: queue.Queue[Any] = queue.Queue()
        self.online: dict[str, float] = {}
        self.last_seen: dict[str, float] = {}  # every robot ever online: when it was last heard of
        self.live: dict[str, dict[str, Any]] = {}  # robot -> its last telemetry message
        self.truth: dict[str, dict[str, Any]] = {}  # mission -> the simulated world's last ground truth
        self.online_lock = threading.Lock()
        self.running = True
        self.stats = {"ingest_batches": 0, "ingest_seconds": 0.0}
        self.publisher = self.session.declare_publisher(
            mission_key(self.fleet, "**"), congestion_control=zenoh.CongestionControl.BLOCK
        )
        self.queryable = self.session.declare_queryable(episode_key(self.fleet, "*", "*"), self.ingest_q.put)
        self.missions_sub = self.session.declare_subscriber(mission_key(self.fleet, "*"), self._on_mission)
        self.alive_sub = self.session.liveliness().declare_subscriber(
            agent_key(self.fleet, "*"), self._on_alive, history=True
        )
        self.telemetry_sub = self.session.declare_subscriber(telemetry_key(self.fleet, "*"), self._on_telemetry)
        self.truth_sub = self.session.declare_subscriber(truth_key(self.fleet, "*"), self._on_truth)
        self.detections_sub = self.session.declare_subscriber(detection_key(self.fleet, "*", "*"), self._on_detection)
        self.withdrawals_sub = self.session.declare_subscriber(
            withdrawal_key(self.fleet, "*", "*"), self._on_withdrawal
        )
        # mission -> (when to decide, [(t, robot's index in the mission, detection)]): under "auto"
        self.capturing: dict[str, tuple[float, list[tuple[int, int, dict[str, Any]]]]] = {}
        self.threads = [
            threading.Thread(target=self._ingest_loop, name="ingest", daemon=True),
            threading.Thread(target=self._events_loop, name="mission-events", daemon=True),
        ]
        for t in self.threads:
            t.start()

    # ---------------------------------------------------------------- callbacks: queue only
    def _on_alive(self, sample: zenoh.Sample) -> None:
        robot = str(sample.key_expr).rsplit("/", 1)[-1]
        with self.online_lock:
            self.last_seen[robot] = time.time()
            if sample.kind == zenoh.SampleKind.PUT:
                self.online.setdefault(robot, time.time())
            else:
                self.online.pop(robot, None)

    def _on_mission(self, sample: zenoh.Sample) -> None:
        self.events_q.put(("mission", "", sample.payload.to_bytes()))

    def _on_telemetry(self, sample: zenoh.Sample) -> None:
        self.events_q.put(("telemetry", str(sample.key_expr), sample.payload.to_bytes()))

    def _on_truth(self, sample: zenoh.Sample) -> None:
        self.events_q.put(("truth", str(sample.key_expr), sample.payload.to_bytes()))

    def _on_detection(self, sample: zenoh.Sample) -> None:
        self.events_q.put(("detection", str(sample.key_expr), sample.payload.to_bytes()))

    def _on_withdrawal(self, sample: zenoh.Sample) -> None:
        self.events_q.put(("withdrawal", str(sample.key_expr), sample.payload.to_bytes()))

    # ---------------------------------------------------------------- workers
    def agents_online(self) -> dict[str, float]:
        with self.online_lock:
            return dict(self.online)

    def agents(self) -> dict[str, dict[str, Any]]:
        """Every robot heard of since the server started: online (since when) or not, when last
        heard of, and its last telemetry."""
        with self.online_lock:
            return {
                r: {
                    "online": r in self.online,
                    "since": self.online.get(r),
                    "last_seen": self.last_seen[r],
                    "live": self.live.get(r),
                }
                for r in sorted(self.last_seen)
            }

    def _telemetry(self, key: str, raw: bytes) -> None:
        """Keep a robot's last live state, if it is one (docs/SPEC.md section 6); others are dropped."""
        robot = key.rsplit("/", 1)[-1]
        keep = live_state(_json_object(raw), self.server.graph.n)
        if keep is None:
            return
        with self.online_lock:
            self.live[robot] = {**keep, "received": time.time()}
            self.last_seen[robot] = time.time()

    def _truth(self, key: str, raw: bytes) -> None:
        """Keep the simulated world's last ground truth of a mission (fleet-sim's debugging overlay)."""
        msg = _json_object(raw)
        if msg is None or not isinstance(msg.get("target"), int) or not isinstance(msg.get("t"), int):
            return
        robots = msg.get("robots") if isinstance(msg.get("robots"), dict) else {}
        with self.online_lock:
            self.truth[key.rsplit("/", 1)[-1]] = {
                "t": msg["t"],
                "target": msg["target"],
                "robots": robots,
                "received": time.time(),
            }
            while len(self.truth) > 64:  # the newest missions only
                self.truth.pop(next(iter(self.truth)))

    def truth_of(self, mission_id: str) -> dict[str, Any] | None:
        with self.online_lock:
            return self.truth.get(mission_id)

    def publish_mission(self, msg: dict[str, Any]) -> None:
        self.session.put(
            mission_key(self.fleet, msg["mission_id"]),
            json.dumps(msg).encode(),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def _events_loop(self) -> None:
        """Mission events from the agents, and once a second the missions past their deadline."""
        next_expiry = 0.0
        while self.running:
            if time.monotonic() >= next_expiry:
                next_expiry = time.monotonic() + 1.0
                try:
                    self.server.expire_missions()
                except Exception:
                    log.exception("ending timed-out missions")
            self._decide_captures()
            try:
                kind, key, raw = self.events_q.get(timeout=0.05 if self.capturing else 0.2)
            except queue.Empty:
                continue
            if kind == "telemetry":
                self._telemetry(key, raw)
                continue
            if kind == "truth":
                self._truth(key, raw)
                continue
            if kind == "detection":
                self._detection(key, raw)
                continue
            if kind == "withdrawal":
                self._withdrawal(key, raw)
                continue
            msg = parse_message(raw)
            if msg is None or msg["type"] not in ("captured", "stop"):
                continue
            status = "captured" if msg["type"] == "captured" else "stopped"
            try:
                mission = self.server.store.get_mission(msg["mission_id"])
                if mission is None or (status == "captured" and msg.get("captured_by") not in mission["robots"]):
                    log.warning(
                        "ignored a %s message for %s: no such mission or robot in it", status, msg["mission_id"]
                    )
                    continue
                self.server.store.mission_event(msg["mission_id"], msg, status)
            except Exception:
                log.exception("recording mission event %s", msg)

    def _detection(self, key: str, raw: bytes) -> None:
        """A robot's detection: recorded, and under "auto" the mission ends after CAPTURE_WINDOW_S."""
        det, why = parse_detection(key, raw)
        if det is None:
            log.warning("ignored a detection message on %s: %s", key, why)
            return
        try:
            mode = self.server.on_detection(det)
            if mode == "auto":
                _due, found = self.capturing.setdefault(det["mission_id"], (time.monotonic() + CAPTURE_WINDOW_S, []))
                found.append((det["t"], det["order"], det))
        except Exception:
            log.exception("handling detection %s", det)

    def _withdrawal(self, key: str, raw: bytes) -> None:
        """A robot that cannot go on with a mission: its part of the mission ends at once."""
        msg, why = parse_withdrawal(key, raw)
        if msg is None:
            log.warning("ignored a withdrawal message on %s: %s", key, why)
            return
        try:
            self.server.on_withdrawal(msg)
        except Exception:
            log.exception("handling withdrawal %s", msg)

    def _decide_captures(self) -> None:
        now = time.monotonic()
        for mid, (due, found) in list(self.capturing.items()):
            if now < due:
                continue
            del self.capturing[mid]
            _t, _order, first = min(found, key=lambda f: (f[0], f[1]))
            try:
                self.server.capture(first, by="auto")
            except Exception:
                log.exception("ending mission %s on a detection", mid)

    def _ingest_loop(self) -> None:
        while self.running:
            try:
                first = self.ingest_q.get(timeout=0.2)
            except queue.Empty:
                continue
            batch = [first]
            while len(batch) < INGEST_BATCH:
                try:
                    batch.append(self.ingest_q.get_nowait())
                except queue.Empty:
                    break
            t0 = time.perf_counter()
            try:
                self._ingest(batch)
            except Exception:  # never let one bad batch stop ingest
                log.exception("ingest batch failed")
                for q in batch:
                    self._reply_err(q, "server-error", "the server could not store the record; resend later")
                    q.drop()
            del first, batch
            self.stats["ingest_batches"] += 1
            self.stats["ingest_seconds"] += time.perf_counter() - t0

    def _reply_err(self, q: zenoh.Query, reason: str, error: str) -> None:
        try:
            q.reply_err(json.dumps({"reason": reason, "error": error}).encode())
        except Exception:
            log.debug("could not reply to %s", q.key_expr)

    def _ingest(self, batch: list[zenoh.Query]) -> None:
        graph, fleet, store = self.server.graph, self.fleet, self.server.store
        rows: list[tuple[Any, ...]] = []
        accepted: list[tuple[zenoh.Query, int, bool]] = []  # (query, row, the row's first copy in the batch)
        rejected: list[tuple[zenoh.Query, str, str]] = []
        seen: dict[tuple[str, str], int] = {}
        for q in batch:
            key = str(q.key_expr)
            parts = key.split("/")
            try:
                if len(parts) != 5 or parts[2] != "episodes":
                    raise RecordError("key", f"key {key!r} is not mures/<fleet>/episodes/<robot_id>/<mission_id>")
                payload = q.payload.to_bytes() if q.payload is not None else b""
                if not payload:
                    raise RecordError("empty", "the query carries no episode record")
                if len(payload) > MAX_RECORD_BYTES:
                    raise RecordError("size", f"record of {len(payload)} bytes exceeds {MAX_RECORD_BYTES}")
                try:
                    rec = json.loads(payload)
                except (ValueError, UnicodeDecodeError) as exc:
                    raise RecordError("json", f"payload is not valid JSON ({exc})") from None
                ep = parse_record(rec, graph, fleet=fleet)
                if (ep.robot_id, ep.mission_id) != (parts[3], parts[4]):
                    raise RecordError(
                        "key", f"record is robot {ep.robot_id!r} mission {ep.mission_id!r} but was sent on {key!r}"
                    )
            except RecordError as exc:
                rejected.append((q, exc.reason, str(exc)))
                continue
            if (ep.robot_id, ep.mission_id) in seen:  # the same record twice in one batch
                accepted.append((q, seen[ep.robot_id, ep.mission_id], False))
                continue
            seen[ep.robot_id, ep.mission_id] = len(rows)
            aside = unexplained(ep, graph)  # kept, but never estimated from
            if aside:
                log.warning("record %s/%s set aside: %s", ep.robot_id, ep.mission_id, aside)
            rows.append(
                (
                    fleet,
                    ep.robot_id,
                    ep.mission_id,
                    ep.policy_version,
                    len(ep.nodes),
                    ep.captured,
                    ep.capture_time,
                    json.dumps(canonical_record(ep, graph), separators=(",", ":")),  # unknown fields dropped
                    aside,
                )
            )
            accepted.append((q, len(rows) - 1, True))
        stored = store.add_episodes(rows) if rows else []
        if rejected:
            store.reject(r for _q, r, _e in rejected)
        for q, i, first in accepted:
            if stored[i] is None:  # the database refused this row alone; the agent resends it later
                self._reply_err(q, "server-error", "the server could not store the record; resend later")
                continue
            status = "stored" if stored[i] and first else "duplicate"
            reply: dict[str, Any] = {"status": status}
            if rows[i][-1]:
                reply["set_aside"] = rows[i][-1]
            try:
                q.reply(q.key_expr, json.dumps(reply).encode())
            except Exception:
                log.debug("could not reply to %s", q.key_expr)
        for q, reason, error in rejected:
            log.info("rejected %s: %s", q.key_expr, error)
            self._reply_err(q, reason, error)
        for q in batch:  # finalise now: the querier's get() ends here, not when Python collects q
            q.drop()
        try:
            running = store.running_among({row[2] for row, got in zip(rows, stored, strict=True) if got})
        except Exception:
            log.exception("finding the batch's running missions")
            running = []
        for mission_id in running:
            try:  # robots that ended a mission themselves (step limit): the server ends it too
                self.server.records_complete(mission_id)
            except Exception:
                log.exception("ending mission %s on its records", mission_id)
        if any(stored):
            try:  # a new version on trial: decided once enough pairs of missions are complete
                self.server.check_canary()
            except Exception:
                log.exception("deciding the canary")

    def close(self) -> None:
        self.running = False
        for t in self.threads:
            t.join(2)
        for ent in (
            self.alive_sub,
            self.telemetry_sub,
            self.truth_sub,
            self.detections_sub,
            self.withdrawals_sub,
            self.missions_sub,
            self.queryable,
            self.publisher,
        ):
            try:
                ent.undeclare()
            except Exception:
                log.debug("undeclare failed", exc_info=True)
        self.session.close()
