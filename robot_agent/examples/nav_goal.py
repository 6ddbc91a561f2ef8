"""An example backend for a robot whose navigation stack takes goal nodes (as the paper's robots did).

Adapt it to your robot: implement a ``Navigator`` (three methods) on top of your stack, e.g. a
ROS 2 Nav2 action client that sends the goal pose of a node and waits for the result, and a
``Detector`` on top of your person/asset detector. Then launch::

    robot-agent --robot-id r1 --server http://server:8000 --zenoh-connect tcp/server:7447 \
        --token-file /etc/mures/agent.token --backend mypackage.mybackend:MyBackend

where ``MyBackend`` subclasses ``NavGoalBackend`` and builds your navigator and detector in
``__init__``. Node positions come from the map's "positions" table ({label: [x, y]},
docs/SPEC.md section 7) unless your navigator resolves node labels itself.

The agent needs nothing else from the robot: it never sees other robots' state, and a failed
move simply leaves the robot where it is (the record then shows it stayed, a legal move).
"""

from __future__ import annotations

from typing import Any, Protocol

from robot_agent.backend import BackendError
from shared.core.graph import Graph


class Navigator(Protocol):
    def current_node(self) -> int:
        """The label of the node the robot is at (localisation snapped to the map's nodes)."""

    def go_to(self, node: int, position: tuple[float, float] | None, timeout_s: float) -> bool:
        """Drive to ``node``; True on arrival, False on failure (blocked, timeout, aborted)."""


class Detector(Protocol):
    def detect(self) -> bool:
        """Whether the target is seen from the current node (the sensor of docs/SPEC.md section 1)."""


class NavGoalBackend:
    """A RobotBackend over a goal-taking navigator and a detector."""

    def __init__(
        self,
        graph: Graph,
        navigator: Navigator | None = None,
        detector: Detector | None = None,
        move_timeout_s: float = 120.0,
    ) -> None:
        if navigator is None or detector is None:  # launched as it is, not subclassed
            raise BackendError(
                "NavGoalBackend is an adapter to subclass: build your robot's Navigator and Detector in your "
                "subclass's __init__ and pass it as --backend MODULE:YOURCLASS (robot_agent/examples/nav_goal.py)"
            )
        self.graph = graph
        self.nav = navigator
        self.detector = detector
        self.move_timeout_s = move_timeout_s
        self.node = -1

    def begin(self, mission: dict[str, Any]) -> int:
        self.node = int(self.nav.current_node())
        if self.node not in self.graph.index:
            raise BackendError(f"the robot is at {self.node}, which is not a node of the map")
        return self.node

    def move(self, goal: int) -> int:
        if goal == self.node:
            return self.node  # "stay" is a legal action
        pos = self.graph.positions.get(self.graph.index[goal])
        arrived = self.nav.go_to(goal, pos, self.move_timeout_s)
        here = int(self.nav.current_node())
        if not arrived and here not in (self.node, goal):
            raise BackendError(f"move {self.node} -> {goal} failed and left the robot at {here}")
        self.node = here
        return self.node

    def detect(self) -> int:
        return int(bool(self.detector.detect()))

    def end(self) -> None:
        pass
