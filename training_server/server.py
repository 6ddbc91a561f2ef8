"""``Server``: the fleet's central state, the data directory, the store, policy versions (publish,
promote, roll back, the trial of a new version), detections and capture, and the router's
re-opening when robots' credentials change. training_server/cli.py runs it as a process."""

from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import shutil
import tarfile
import threading
import time
from pathlib import Path
from typing import Any

import training_server.credentials as credentials
from shared.core.graph import Graph, GraphError
from shared.core.snapshot_format import WEIGHTS, SnapshotData, read_meta, read_snapshot
from training_server.security import (
    MAX_FAILURES,
    AuditLog,
    SignInGuard,
    TokenFile,
)
from training_server.store import DB_FILE, Store, sqlite_url

log = logging.getLogger("mures.server")

ARTIFACT = "policy.tar"
MISSION_TIMEOUT_S = 1800.0  # a mission still running after this long is ended (--mission-timeout)
CAPTURE_MODES = ("auto", "confirm")


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class Server:
    """State shared by the REST API, the Zenoh bus and the training supervisor."""

    def __init__(
        self,
        data_dir: Path,
        graph: Graph,
        fleet: str,
        operator_token_file: Path,
        agent_token_file: Path,
        database_url: str | None = None,
        mission_timeout: float = MISSION_TIMEOUT_S,
        sign_in_limit: int = MAX_FAILURES,
        capture: str | None = None,
    ) -> None:
        self.data_dir = data_dir
        self.capture_mode = capture  # "auto", "confirm", or None: by the current version's sensor
        self.mission_timeout = mission_timeout
        self.graph = graph
        self.fleet = fleet
        # re-read when rotated (training-server rotate-token); compared in constant time
        self.tokens = {"operator": TokenFile(operator_token_file), "agent": TokenFile(agent_token_file)}
        self.sign_ins = SignInGuard(max_failures=sign_in_limit)
        self.audit = AuditLog(data_dir / "audit.jsonl")
        data_dir.mkdir(parents=True, exist_ok=True)
        data_dir.chmod(0o700)  # private: the database, tokens and policies are the fleet's
        self._lock = _lock_data_dir(data_dir)
        (data_dir / "policies").mkdir(exist_ok=True)
        (data_dir / "staging").mkdir(exist_ok=True)
        try:
            self.store = Store(database_url or sqlite_url(data_dir))
        except BaseException:
            self._lock.close()
            raise
        for f in data_dir.glob(f"{DB_FILE}*"):  # the database and its WAL files, also when created earlier
            f.chmod(0o600)
        self._clean_leftovers()
        self.version_lock = threading.Lock()
        self.bus: Any = None
        self.supervisor: Any = None
        self.is_stopping: Any = lambda: False  # main() points it at uvicorn's should_exit
        self.started = time.time()
        self.router_reopened = 0  # times the secured router re-opened (credentials changed)
        self.metrics_without_token = False  # `training-server --metrics-without-token`: /metrics needs no token
        self.map_picture: Any = None  # `training-server --map-image`: the building's map under the console's graph
        map_id = self.store.get_setting("graph_id")
        if map_id is None:
            self.store.set_setting("graph_id", graph.graph_id)
        elif map_id != graph.graph_id:
            raise GraphError(
                f"data directory {data_dir} belongs to another map ({map_id[:20]}...); "
                f"this one is {graph.name!r} ({graph.graph_id[:20]}...). Use another --data-dir."
            )

    def close(self) -> None:
        """Close the database and release the data directory's lock."""
        self.store.close()
        self._lock.close()

    def _clean_leftovers(self) -> None:
        """What a killed server left behind: training staging directories, half-copied versions
        (``.vN.tmp``) and the directory of the one version whose publication never reached the
        database (the next number; never served, and the number is given again). Other version
        directories the database does not know mean that the data directory and the database do
        not belong together (a wrong --database-url): the server refuses to start, deleting
        nothing."""
        known = {int(p["version"]) for p in self.store.policies()}
        stale = list((self.data_dir / "staging").iterdir())
        strangers: list[Path] = []
        for d in (self.data_dir / "policies").iterdir():
            name = d.name.removeprefix("v")
            if d.name.startswith("."):
                stale.append(d)
            elif name.isdigit() and int(name) not in known:
                (stale if int(name) == max(known, default=0) + 1 else strangers).append(d)
        if strangers:
            raise ValueError(
                f"the data directory {self.data_dir} holds policy versions the database "
                f"{self.store.safe_url} does not know ({', '.join(sorted(d.name for d in strangers))}): "
                "is --database-url the one this data directory was used with?"
            )
        for d in stale:
            shutil.rmtree(d, ignore_errors=True) if d.is_dir() else d.unlink(missing_ok=True)
            log.warning("removed %s, left by an interrupted server", d)

    # ------------------------------------------------------------------ missions
    def expire_missions(self) -> list[str]:
        """End the running missions past their deadline: the robots are told to stop (reason
        "timeout") and the mission's status becomes "timed-out". Returns their ids."""
        out = []
        for m in self.store.expired_missions(self.fleet, time.time()):
            msg = {"type": "stop", "mission_id": m["id"], "reason": "timeout"}
            if self.bus is not None:
                self.bus.publish_mission(msg)
            if self.store.mission_event(m["id"], msg, "timed-out"):
                log.warning(
                    "mission %s timed out after %.0f s; its robots were told to stop",
                    m["id"],
                    time.time() - m["created"],
                )
                out.append(m["id"])
        return out

    def default_capture(self) -> str:
        """How a robot's detection ends a mission when the mission does not say: the server's
        ``--capture``, else "auto" when the current version's sensor has no false positives
        (eta_fp = 0: a z = 1 is the target) and "confirm" (an operator decides) when it has."""
        if self.capture_mode is not None:
            return self.capture_mode
        try:
            sensor = (self.store.policy(self.current_version()) or {}).get("meta", {}).get("sensor") or {}
        except RuntimeError:
            sensor = {}
        return "confirm" if float(sensor.get("eta_fp") or 0.0) > 0 else "auto"

    def on_detection(self, det: dict[str, Any]) -> str | None:
        """A robot's detection (wire.parse_detection's message), from the bus's worker. Checked
        against the mission (running, the robot in it, t within its step limit, a node of the map)
        and recorded (``det`` gains its "id" and the robot's "order" in the mission); under "auto"
        the caller ends the mission (returns "auto"), under "confirm" it waits for an operator
        (returns "confirm"). None: ignored, with the reason logged."""
        mid, robot = det["mission_id"], det["robot_id"]
        m = self.store.get_mission(mid)
        if m is None:
            why = "no such mission"
        elif robot not in m["robots"]:
            why = f"{robot} is not in it"
        elif det["t"] > m["params"]["max_steps"]:
            why = f"t={det['t']} is past its step limit {m['params']['max_steps']}"
        elif det["node"] not in self.graph.index:
            why = f"node {det['node']} is not on the map"
        elif m["status"] != "running":
            why = f"the mission is {m['status']}"
        else:
            why = ""
        if m is None or why:
            log.info("detection by %s at t=%s in mission %s ignored: %s", robot, det["t"], mid, why)
            return None
        det["order"] = m["robots"].index(robot)  # its place in the mission's list: the capture window's tie-break
        mode = m["params"].get("capture") or self.default_capture()
        # "pending" awaits an operator; under "auto" the capture window decides (confirmed or closed)
        status = "pending" if mode == "confirm" else "closed"
        det_id = self.store.add_detection(self.fleet, mid, robot, det["t"], det["node"], status)
        det["id"] = det_id
        if mode == "confirm":
            log.warning(
                "mission %s: %s reports a detection at t=%d on node %d (detection %d): confirm or dismiss it",
                mid,
                robot,
                det["t"],
                det["node"],
                det_id,
            )
        return mode

    def capture(self, detection: dict[str, Any], by: str) -> bool:
        """End the detection's mission as captured at its t by its robot, and tell the fleet.
        False when the mission had already ended (the first end is kept)."""
        mid = detection["mission_id"]
        msg = {"type": "captured", "mission_id": mid, "t": int(detection["t"]), "captured_by": detection["robot_id"]}
        if detection.get("time_s") is not None:  # a robot on the mission clock: when its reading was made
            msg["time_s"] = detection["time_s"]
        if not self.store.mission_event(mid, msg, "captured"):
            self.store.decide_detection(detection["id"], "closed", by)  # (when it was pending)
            return False
        self.store.decide_detection(detection["id"], "confirmed", by, only_if=None)
        if self.bus is not None:
            self.bus.publish_mission(msg)
        log.info("mission %s captured at t=%d by %s (%s)", mid, msg["t"], msg["captured_by"], by)
        return True

    def dismiss(self, detection: dict[str, Any], by: str) -> bool:
        """Rule a pending detection a false alarm: recorded, and the search goes on."""
        if not self.store.decide_detection(detection["id"], "dismissed", by):
            return False
        if self.bus is not None:
            self.bus.publish_mission(
                {
                    "type": "dismissed",
                    "mission_id": detection["mission_id"],
                    "robot_id": detection["robot_id"],
                    "t": detection["t"],
                    "detection": detection["id"],
                }
            )
        log.info(
            "detection %d of mission %s dismissed as a false alarm (%s)", detection["id"], detection["mission_id"], by
        )
        return True

    def records_complete(self, mission_id: str) -> None:
        """No robot is left flying a running mission: each has sent its record or withdrawn
        (docs/operating.md). The robots ended it themselves (at its step limit or its time limit,
        or a robot's own end), or their backends failed; the server ends it too, as "stopped" with the reason."""
        m = self.store.get_mission(mission_id)
        if m is None or m["status"] != "running" or mission_id in getattr(self.bus, "capturing", {}):
            return  # (a detection's verdict is due: it ends the mission)
        recs = self.store.mission_records(self.fleet, mission_id)
        if not set(m["robots"]) <= {r for r, *_ in recs} | set(m["withdrawn"]):
            return
        steps = self.store.mission_steps(self.fleet, mission_id)
        limit, seconds = m["params"]["max_steps"], m["params"].get("max_seconds")
        last_s = self.store.mission_last_reading_s(self.fleet, mission_id) if seconds else None
        if steps >= limit + 1:
            reason = "step limit"
        elif last_s is not None and last_s >= seconds:
            reason = "time limit"
        elif m["withdrawn"]:
            reason = "no robot left: " + "; ".join(
                f"{r} withdrew ({w['reason']})" for r, w in sorted(m["withdrawn"].items())
            )
        else:
            reason = "ended by the robots"
        msg = {"type": "stop", "mission_id": mission_id, "reason": reason}
        if self.store.mission_event(mission_id, msg, "stopped") and m["withdrawn"]:
            log.warning("mission %s stopped: %s", mission_id, reason)
            if self.bus is not None:
                self.bus.publish_mission(msg)  # the simulated world and any robot still waiting

    def on_withdrawal(self, msg: dict[str, Any]) -> bool:
        """A robot left a running mission (wire.parse_withdrawal's message, from the bus's worker):
        recorded, so that it is no longer busy; its teammates and the simulated world are told
        (a "withdrawn" mission message); the mission ends when no robot is left flying it.
        False: ignored (no such running mission, or the robot is not in it), with the reason logged."""
        mid, robot = msg["mission_id"], msg["robot_id"]
        mission = self.store.withdraw(mid, robot, msg["steps"], msg["reason"])
        if mission is None:
            log.info("withdrawal of %s from mission %s ignored: not a running mission of that robot", robot, mid)
            return False
        log.warning("mission %s: %s withdrew after %d steps: %s", mid, robot, msg["steps"], msg["reason"])
        if self.bus is not None:
            self.bus.publish_mission(
                {"type": "withdrawn", "mission_id": mid, "robot_id": robot, "reason": msg["reason"]}
            )
        self.records_complete(mid)
        return True

    def reopen_router_on_credentials(self, make_conf: Any, stop: threading.Event, every: float = 1.0) -> None:
        """While the server is its fleet's secured router: whenever the robots holding credentials
        change (`training-server robots add|revoke`, `training-server kit`), re-open the Zenoh
        session with the new users and access rules. Robots reconnect by themselves (their clients
        retry) and declare their tokens and subscriptions again; a record sent in the gap is resent
        from the outbox. Checked every ``every`` seconds."""
        from training_server.bus import Bus

        def fingerprint() -> list[tuple[str, str]]:
            users = [(r, str(e.get("zenoh_password"))) for r, e in credentials.robots(self.data_dir).items()]
            world = credentials.world_password(self.data_dir)
            return sorted(users + ([(credentials.WORLD_USER, world)] if world else []))

        seen = fingerprint()
        while not stop.wait(every):
            now = fingerprint()
            if now == seen:
                continue
            added = sorted({r for r, _ in now} - {r for r, _ in seen})
            gone = sorted({r for r, _ in seen} - {r for r, _ in now})
            seen = now
            t0 = time.perf_counter()
            try:
                conf = make_conf()
                with self.version_lock:  # no mission start in between (it takes this lock)
                    self.bus.close()  # frees the listening port for the new session
                    self.bus = Bus(self, conf)
                    self.router_reopened += 1
            except Exception:
                log.exception("re-opening the Zenoh router after a change of credentials")
                continue
            log.warning(
                "robots' credentials changed (added: %s; revoked: %s; reissued or unchanged: the rest): the router "
                "re-opened in %.2f s with %d robots",
                ", ".join(added) or "none",
                ", ".join(gone) or "none",
                time.perf_counter() - t0,
                len(now),
            )

    # ------------------------------------------------------------------ policy versions
    def policy_dir(self, version: int) -> Path:
        return self.data_dir / "policies" / f"v{version}"

    def snapshot_dir(self, version: int) -> Path:
        return self.policy_dir(version) / "snapshot"

    def artifact(self, version: int) -> Path:
        return self.policy_dir(version) / ARTIFACT

    def current_version(self) -> int:
        v = self.store.get_setting("current_version")
        if v is None:
            raise RuntimeError("no policy version yet")
        return int(v)

    def set_current(self, version: int) -> None:
        """Make ``version`` current (an operator's choice): it ends a canary in progress, recorded as such."""
        if self.store.policy(version) is None:
            raise KeyError(version)
        with self.version_lock:
            canary = self.canary()
            if canary is not None:
                self._end_canary(canary, "ended by the operator", {"made_current": version})
            self.store.set_setting("current_version", str(version))

    # ------------------------------------------------------------------ canary (staged promotion)
    # A version that passed its run's gate does not become current at once: it flies every other
    # mission (the canary arm) beside the current version (the baseline arm) until ``pairs`` pairs
    # of missions are complete. The canary mission of a pair repeats its baseline mission's seed,
    # so in simulation both meet the same target path (with real robots the pair is two missions
    # in a row). Then the fleet's own capture times decide: the canary is made current if its mean
    # over the pairs is not higher than the baseline's (the paired difference's mean <= 0),
    # otherwise it is rolled back (never made current) with an alert. A mission counts as the
    # performance view counts it: captured, or run to its step limit (the limit counts); a pair
    # with an arm that does not count is skipped and another pair is flown.
    def canary(self) -> dict[str, Any] | None:
        raw = self.store.get_setting("canary")
        return json.loads(raw) if raw else None

    def start_canary(self, version: int, baseline: int, run_id: str | None, pairs: int) -> None:
        with self.version_lock:
            old = self.canary()
            if old is not None:
                self._end_canary(old, f"replaced by version {version}", {})
            canary: dict[str, Any] = {"version": version, "baseline": baseline, "run_id": run_id, "pairs": pairs}
            canary.update(started=time.time(), next_pair=0, pending_seed=None)
            self.store.set_setting("canary", json.dumps(canary))
        self.store.update_policy_meta(version, {"canary": {"state": "flying", "pairs": pairs, "baseline": baseline}})
        log.info("version %d flies as a canary beside version %d for %d pairs of missions", version, baseline, pairs)

    def mission_policy(self, seed: int) -> tuple[int, int, dict[str, Any] | None]:
        """(version, seed, canary arm or None) for the next mission asked for with ``seed``."""
        with self.version_lock:
            canary = self.canary()
            if canary is None:
                return self.current_version(), seed, None
            if canary["pending_seed"] is None:  # a pair begins: the baseline arm, this mission's seed
                canary["pending_seed"] = seed
                arm = {"arm": "baseline", "pair": canary["next_pair"], "canary_version": canary["version"]}
                version = canary["baseline"]
            else:  # the pair's canary arm repeats its baseline's seed
                seed = canary["pending_seed"]
                arm = {"arm": "canary", "pair": canary["next_pair"], "canary_version": canary["version"]}
                canary["pending_seed"] = None
                canary["next_pair"] += 1
                version = canary["version"]
            self.store.set_setting("canary", json.dumps(canary))
        return version, seed, arm

    def check_canary(self) -> dict[str, Any] | None:
        """Decide the canary once enough pairs are complete; returns the decision, if one was made."""
        from shared.engine.evaluate import mean_ci95

        canary = self.canary()
        if canary is None:
            return None
        arms: dict[int, dict[str, tuple[float, float | None]]] = {}  # pair -> arm -> (steps, seconds)
        for o in self.store.canary_outcomes(self.fleet, canary["version"]):
            ct = self.store.counted_capture_time(o)
            if ct is not None:  # (stopped or timed out early: no capture time)
                arms.setdefault(o["pair"], {})[o["arm"]] = (ct, self.store.counted_seconds(o))
        pairs = sorted(k for k, a in arms.items() if {"canary", "baseline"} <= set(a))
        if len(pairs) < canary["pairs"]:
            return None
        used = pairs[: canary["pairs"]]
        # seconds where every mission of the pairs flew on the mission clock, else steps
        on_clock = all(arms[k][arm][1] is not None for k in used for arm in ("canary", "baseline"))
        pick = 1 if on_clock else 0
        c = [float(arms[k]["canary"][pick]) for k in used]  # type: ignore[arg-type]
        b = [float(arms[k]["baseline"][pick]) for k in used]  # type: ignore[arg-type]
        diff, half = mean_ci95([x - y for x, y in zip(c, b, strict=True)])
        keep = diff <= 0
        evidence = {
            "pairs": len(used),
            "canary_mean": round(sum(c) / len(c), 3),
            "baseline_mean": round(sum(b) / len(b), 3),
            "mean_difference": round(diff, 3),
            "ci95": round(half, 3),
            "unit": "seconds" if on_clock else "steps",
        }
        with self.version_lock:
            if self.canary() != canary:
                return None  # decided or replaced meanwhile
            self._end_canary(canary, "kept" if keep else "rolled back", evidence)
            if keep:
                self.store.set_setting("current_version", str(canary["version"]))
        log.log(
            logging.INFO if keep else logging.WARNING,
            "canary version %d %s: %.2f vs %.2f %s over %d pairs (difference %+.2f ± %.2f)",
            canary["version"],
            "kept and made current" if keep else "rolled back: it flew worse than the current version",
            evidence["canary_mean"],
            evidence["baseline_mean"],
            evidence["unit"],
            len(used),
            diff,
            half,
        )
        return {"decision": "kept" if keep else "rolled back", **evidence}

    def _end_canary(self, canary: dict[str, Any], state: str, evidence: dict[str, Any]) -> None:
        """(under version_lock) The canary's end, recorded in its version's meta."""
        self.store.set_setting("canary", "")
        record = {"state": state, "decided": time.time(), "baseline": canary["baseline"], **evidence}
        record.setdefault("pairs_asked", canary["pairs"])
        self.store.update_policy_meta(canary["version"], {"canary": record})

    def publish_version(
        self, snapshot_dir: Path, parent: int | None, run_id: str | None, metrics: dict[str, Any], promote: bool
    ) -> int:
        """Turn a snapshot directory into the next immutable version (and make it current).

        The version holds the snapshot in the numpy-readable format (an older torch-format one is
        converted) and the tar agents download."""
        with self.version_lock:
            version = self.store.next_version()
            final = self.policy_dir(version)
            tmp = final.with_name(f".{final.name}.tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(snapshot_dir, tmp / "snapshot")
            snap = self._numpy_snapshot(tmp / "snapshot")  # checks graph, shapes, hash
            _write_artifact(tmp)
            shutil.rmtree(final, ignore_errors=True)
            os.replace(tmp, final)
            digest = sha256_file(final / ARTIFACT)
            meta = {
                "graph_id": self.graph.graph_id,
                "robots": snap.robots,
                "variant": snap.variant,
                "algorithm": snap.meta.get("algorithm", "cepg"),
                "beta": snap.meta.get("beta"),
                "sensor": snap.meta.get("sensor"),
                "weights_sha256": snap.meta["weights"]["sha256"],
                "training": {k: snap.meta.get("training", {}).get(k) for k in ("episodes", "seed", "belief")},
                "metrics": metrics,
            }
            self.store.add_policy(version, digest, (final / ARTIFACT).stat().st_size, parent, run_id, meta)
            if promote or self.store.get_setting("current_version") is None:
                self.store.set_setting("current_version", str(version))
        log.info("policy version %d published (sha256 %s...)%s", version, digest[:12], " and made current" * promote)
        return version

    def _numpy_snapshot(self, path: Path) -> SnapshotData:
        """Read (and check) a snapshot, converting an older torch-format one in place first."""
        if read_meta(path)["weights"].get("file") != WEIGHTS:
            from shared.learning.team_snapshot import convert_snapshot

            convert_snapshot(path)
        return read_snapshot(path, self.graph)

    def migrate_versions(self) -> list[int]:
        """Convert stored versions of the older torch format (weights.pt) so that torch-free agents
        can run them: the snapshot is rewritten with the same values, the tar rebuilt, and the
        version's sha256 updated (agents then download it again). Returns the versions converted."""
        done = []
        for p in self.store.policies():
            v = int(p["version"])
            snap_dir = self.snapshot_dir(v)
            if not snap_dir.is_dir() or read_meta(snap_dir)["weights"].get("file") == WEIGHTS:
                continue
            with self.version_lock:
                snap = self._numpy_snapshot(snap_dir)
                _write_artifact(self.policy_dir(v))
                art = self.artifact(v)
                digest = sha256_file(art)
                self.store.update_policy_artifact(v, digest, art.stat().st_size, snap.meta["weights"]["sha256"])
            done.append(v)
            log.info("policy version %d converted to %s (new sha256 %s...)", v, WEIGHTS, digest[:12])
        return done

    def ensure_initial_policy(self, robots: int, init_policy: str | None, sensor: Any, seed: int) -> None:
        """Version 1 when there is none: ``init_policy`` None or "general" (the shipped general policy,
        flown by ``robots`` robots on the uniform walk until EM has learned a model, with FHPE-SA as
        its team searcher: ``write_general_version``), "untrained" (a per-map team of random
        networks) or a snapshot directory."""
        if self.store.get_setting("current_version") is not None:
            return
        from shared.learning.team_snapshot import load_snapshot, save_snapshot

        staging = self.data_dir / "staging" / "initial"
        if init_policy in (None, "general"):
            from shared.core.snapshot_format import write_general_version
            from shared.learning.team_snapshot import provenance

            write_general_version(staging, self.graph, sensor, robots, seed, {"trained_with": provenance()})
            note = "the general policy"
        elif init_policy != "untrained":
            load_snapshot(init_policy, self.graph)  # clear error before anything is written (either format)
            shutil.rmtree(staging, ignore_errors=True)
            shutil.copytree(init_policy, staging)
            note = f"from {init_policy}"
        else:
            import torch

            from shared.core.models import identity_model
            from shared.learning.policy import TeamPolicy

            torch.manual_seed(seed)
            policy = TeamPolicy(self.graph.n, robots, torch.as_tensor(self.graph.adjacency()))
            save_snapshot(
                staging,
                policy,
                self.graph,
                identity_model(self.graph),
                sensor,
                "cepg",
                [0.5] * robots,
                {"episodes": 0, "seed": seed, "belief": "identity", "map": self.graph.name},
                {"episodes": 0, "note": "untrained initial policy"},
            )
            note = "untrained"
        self.publish_version(staging, None, None, {"note": f"initial policy ({note})"}, promote=True)
        shutil.rmtree(staging, ignore_errors=True)


def _lock_data_dir(data_dir: Path) -> Any:
    """Hold an exclusive lock on ``data_dir/server.lock`` for the process's life: a second server on
    the same data directory would interleave writes to its database and policy versions."""
    fh = open(data_dir / "server.lock", "a+", encoding="utf-8")  # noqa: SIM115 - held until close()
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.seek(0)
        holder = fh.read().strip() or "?"
        fh.close()
        raise ValueError(
            f"data directory {data_dir} is in use by another training-server (pid {holder}); "
            "stop it or use another --data-dir"
        ) from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    return fh


def _write_artifact(version_dir: Path) -> None:
    """(Re)build the tar agents download from ``version_dir/snapshot``, atomically."""
    tmp = version_dir / f".{ARTIFACT}"
    with tarfile.open(tmp, "w") as tar:
        for f in sorted((version_dir / "snapshot").iterdir()):
            tar.add(f, arcname=f.name)
    os.replace(tmp, version_dir / ARTIFACT)
