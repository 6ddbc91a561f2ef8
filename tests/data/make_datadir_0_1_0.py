"""Write a data directory with the release at 729df11 (schema before SQLAlchemy/Alembic)."""

import json
import sys
import time
from pathlib import Path

from shared.core.graph import builtin_graph
from shared.core.models import Sensor
from shared.core.records import canonical_record, make_record, parse_record
from training_server.security import rotate
from training_server.server import Server

d = Path(sys.argv[1])
d.mkdir(parents=True, exist_ok=True)
g = builtin_graph("office")
rotate(d / "operator.token")
rotate(d / "agent.token")
srv = Server(d, g, "default", d / "operator.token", d / "agent.token")
srv.ensure_initial_policy(2, None, Sensor(), 0)
rows = []
for m in range(3):
    for r in ("r0", "r1"):
        nodes = [0, 0, 55] if r == "r0" else [2, 2, 2]
        rec = make_record(
            g,
            fleet="default",
            mission_id=f"m{m}",
            robot_id=r,
            nodes=nodes,
            z=[0, 0, int(m == 1 and r == "r0")],
            sensor=Sensor(),
            captured=(m == 1),
            capture_time=(2 if m == 1 else None),
            captured_by=("r0" if m == 1 else None),
            policy_version=1,
        )
        ep = parse_record(rec, g, "default")
        rows.append(("default", r, f"m{m}", 1, 2, m == 1, 2 if m == 1 else None, json.dumps(canonical_record(ep, g))))
print(srv.store.add_episodes(rows))
srv.store.reject(["bad-json", "bad-json", "bad-move"])
srv.store.add_mission("m0", "default", ["r0", "r1"], {"max_steps": 30}, 1)
srv.store.add_mission("m1", "default", ["r0", "r1"], {"max_steps": 30}, 1)
srv.store.mission_event("m1", {"type": "captured", "mission_id": "m1", "captured_by": "r0", "t": 2}, "captured")
srv.store.add_run("run-a", {"episodes": 256})
srv.store.update_run("run-a", status="failed", finished=time.time(), error="evaluation gate: kept")
srv.store.add_run("run-b", {"episodes": 512})
srv.store.update_run("run-b", status="cancelled", finished=time.time())
srv.close()
