"""What the console's live view shows, computed once for every browser watching: the fleet (each
robot's last telemetry with its mission state), the server's status, and the alerts.

Each is cached for a short while (FLEET_EVERY, STATUS_EVERY) with a key that changes when it does,
so twenty browsers cost the database, and the serialisation that tells a change, what one does.
Thread-safe: the event streams call it from FastAPI's thread pool.
"""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from typing import Any

FLEET_EVERY = 0.2  # s: the live view's update period (5 Hz, the agents' telemetry rate)
STATUS_EVERY = 1.0  # s
REJECTION_WINDOW = 60.0  # s: "ingest rejections rising" means some in the last minute
RUN_ALERT_AGE = 24 * 3600.0  # s: failed or gated-out runs are alerts for a day


class Hub:
    def __init__(self, srv: Any) -> None:
        self.srv = srv
        self.lock = threading.Lock()
        self._fleet: tuple[float, dict[str, Any], str] = (0.0, {}, "")
        self._status: tuple[float, dict[str, Any], str] = (0.0, {}, "")
        self._beliefs: dict[str, dict[str, Any]] = {}  # robot -> its last reported belief
        self._rejections: deque[tuple[float, int]] = deque()  # (when, rejected in all)

    # ------------------------------------------------------------------ fleet
    def fleet(self) -> tuple[dict[str, Any], str]:
        """(GET /api/v1/fleet's body with the live extras the map draws: each robot's last
        observation z and goal, and the simulated world's ground truth of running missions
        (fleet-sim only); a key that changes when the body does, "ts" aside). Each refresh also
        keeps every robot's last reported belief for ``belief``."""
        with self.lock:
            when, body, key = self._fleet
            if time.monotonic() - when < FLEET_EVERY:
                return body, key
        from training_server.api.fleet import fleet_view

        body = fleet_view(self.srv).model_dump()
        bus = self.srv.bus
        truth = {}
        for a in body["agents"]:
            mid = a["mission_id"]
            if mid and mid not in truth:
                t = bus.truth_of(mid)
                if t is not None:
                    truth[mid] = t
        body["truth"] = truth
        key = json.dumps(body, sort_keys=True)
        body["ts"] = time.time()
        beliefs = {
            robot: {
                "robot_id": robot,
                "mission_id": live.get("mission_id"),
                "t": live.get("t"),
                "belief": live["belief"],
                "team_belief": live.get("team_belief"),
            }
            for robot, a in bus.agents().items()
            if (live := a["live"] or {}).get("state") == "mission" and "belief" in live
        }
        with self.lock:
            self._fleet = (time.monotonic(), body, key)
            self._beliefs = beliefs
        return body, key

    def belief(self, robot: str) -> dict[str, Any] | None:
        """The robot's last reported beliefs {"robot_id", "mission_id", "t", "belief", "team_belief"
        (null unless it flies with a team searcher)} (None: none reported), as of the last fleet
        refresh."""
        self.fleet()
        with self.lock:
            return self._beliefs.get(robot)

    # ------------------------------------------------------------------ status and alerts
    def status(self) -> tuple[dict[str, Any], str]:
        """(The current policy, running missions, recent runs, episode counts and the alerts; a
        key that changes when they do.)"""
        with self.lock:
            when, body, key = self._status
            if time.monotonic() - when < STATUS_EVERY:
                return body, key
        srv = self.srv
        stats = srv.store.episode_stats(srv.fleet)
        runs = srv.store.runs()[-10:][::-1]  # the ten newest, newest first
        body = {
            "current_policy": srv.current_version(),
            "running_missions": sorted(m["id"] for m in srv.store.running_missions(srv.fleet)),
            "runs": [{k: r[k] for k in ("id", "status", "progress", "version", "error", "finished")} for r in runs],
            "episodes": stats,
            "alerts": self._alerts(stats, runs),
        }
        key = json.dumps(body, sort_keys=True)
        with self.lock:
            self._status = (time.monotonic(), body, key)
        return body, key

    def alerts(self) -> list[dict[str, Any]]:
        return list(self.status()[0]["alerts"])

    def _alerts(self, stats: dict[str, Any], runs: list[dict[str, Any]]) -> list[dict[str, Any]]:
        now = time.time()
        out: list[dict[str, Any]] = []
        for robot, a in self.srv.bus.agents().items():
            if not a["online"]:
                out.append(
                    {
                        "kind": "robot-lost",
                        "level": "error",
                        "subject": robot,
                        "since": a["last_seen"],
                        "text": f"robot {robot} is offline: last heard of {now - a['last_seen']:.0f} s ago",
                    }
                )
        for r in runs:
            if r["status"] != "failed" or now - (r["finished"] or now) > RUN_ALERT_AGE:
                continue
            gated = (r["error"] or "").startswith("evaluation gate")
            out.append(
                {
                    "kind": "run-gated-out" if gated else "run-failed",
                    "level": "warning" if gated else "error",
                    "subject": r["id"],
                    "since": r["finished"],
                    "text": f"training run {r['id']} {'was gated out' if gated else 'failed'}: {r['error']}",
                }
            )
        for p in self.srv.store.policies():
            c = (p["meta"] or {}).get("canary") or {}
            if c.get("state") == "rolled back" and now - c.get("decided", 0) <= RUN_ALERT_AGE:
                out.append(
                    {
                        "kind": "canary-rolled-back",
                        "level": "warning",
                        "subject": str(p["version"]),
                        "since": c["decided"],
                        "text": f"version {p['version']} was rolled back after its trial: {c['canary_mean']:.2f} "
                        f"{c.get('unit', 'steps')} against {c['baseline_mean']:.2f} for version {c['baseline']} "
                        f"over {c['pairs']} pairs of the fleet's missions",
                    }
                )
        for d in self.srv.store.detections(self.srv.fleet, status="pending"):
            out.append(
                {
                    "kind": "detection",
                    "level": "error",
                    "subject": str(d["id"]),
                    "since": d["received"],
                    "text": f"robot {d['robot_id']} reports the target on node {d['node']} at step {d['t']} of "
                    f"mission {d['mission_id']}: confirm (the mission ends as captured) or dismiss (a false alarm)",
                }
            )
        total = sum(stats["rejected"].values())
        self._rejections.append((now, total))
        while len(self._rejections) > 1 and now - self._rejections[1][0] >= REJECTION_WINDOW:
            self._rejections.popleft()
        rising = total - self._rejections[0][1]
        if rising > 0:
            reasons = ", ".join(f"{k} {v}" for k, v in sorted(stats["rejected"].items()) if v)
            out.append(
                {
                    "kind": "ingest-rejections",
                    "level": "warning",
                    "subject": "ingest",
                    "since": self._rejections[0][0],
                    "text": f"{rising} episode records rejected in the last {now - self._rejections[0][0]:.0f} s "
                    f"(all time by reason: {reasons})",
                }
            )
        return out
