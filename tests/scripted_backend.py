"""A robot backend that is not the fleet simulator, for tests: it stands still (a legal move) and
its detector reads z = 1 on the steps listed in MURES_TEST_DETECT ("ROBOT:T,ROBOT:T,..."), 0 on
the others; each step takes MURES_TEST_STEP_S seconds. MURES_TEST_FAULT ("ROBOT:KIND,...") makes a
robot's backend break the contract: begin-none (begin() returns None), detect-string (detect()
returns "1"), move-raises (move() raises OSError at its third move). Nothing in it talks to a simulated world,
so a mission flown with it ends only as a real robot's does: through the server."""

from __future__ import annotations

import os
import time
from typing import Any

from shared.core.graph import Graph


class ScriptedBackend:
    def __init__(self, graph: Graph, robot_id: str) -> None:
        self.graph, self.robot_id = graph, robot_id
        self.detect_at = {
            int(t)
            for r, t in (x.split(":") for x in os.environ.get("MURES_TEST_DETECT", "").split(",") if x)
            if r == robot_id
        }
        self.step_s = float(os.environ.get("MURES_TEST_STEP_S", "0.02"))
        faults = (x.split(":") for x in os.environ.get("MURES_TEST_FAULT", "").split(",") if x)
        self.fault = next((kind for r, kind in faults if r == robot_id), "")
        self.node, self.t = -1, 0

    def begin(self, mission: dict[str, Any]) -> Any:
        self.node, self.t = int(mission["start_node"]), 0
        return None if self.fault == "begin-none" else self.node

    def detect(self) -> Any:
        z = int(self.t in self.detect_at)
        return "1" if self.fault == "detect-string" and self.t >= 2 else z

    def move(self, goal: int) -> int:
        time.sleep(self.step_s)
        self.t += 1
        if self.fault == "move-raises" and self.t == 3:
            raise OSError("the base controller is not answering")
        return self.node  # stays: the record shows it, a legal move

    def end(self) -> None:
        pass
