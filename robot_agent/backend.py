"""The robot backend: what the agent needs from a robot, and the simulated one.

A backend moves the robot between nodes of the map and runs its detector. The agent calls, per
mission::

    node = backend.begin(mission)   # the node the robot stands on at t = 0 (a label)
    z = backend.detect()            # 0/1: the detector's reading at the current node, step t
    node = backend.move(goal)       # go to goal (a label in N[node]); returns where the robot is
                                    # after the move: goal on arrival, another node on failure
    backend.end()                   # the mission is over (stop, park, release resources)

``detect`` or ``move`` may raise ``MissionOver`` when the robot's world says the mission has
ended (the simulated world does; a real robot learns it from the mission-control message).

``--backend MODULE:CLASS`` loads any class with this interface; its constructor is called as
``CLASS(graph=..., robot_id=..., session=..., fleet=..., args=...)`` (``args``: the agent's parsed
flags; keyword arguments it does not take are not passed). ``--backend nav2`` is a Nav2 robot
through zenoh-bridge-ros2dds (robot_agent/nav2.py); ``robot_agent/examples/nav_goal.py`` is a
documented adapter for a navigation stack that takes goal nodes, as the paper's robots did.
"""

from __future__ import annotations

import importlib
import inspect
import json
from typing import Any, Protocol

import zenoh

from shared.core.graph import Graph
from shared.core.wire import sim_key

NAV2_BACKEND = "robot_agent.nav2:Nav2Backend"  # `--backend nav2` (it imports this module: loaded by name)


class MissionOver(Exception):
    """The robot's world ended the mission (capture announced, stop, or step limit)."""


class BackendError(RuntimeError):
    """The robot cannot go on with the mission (e.g. the world does not answer)."""


class RobotBackend(Protocol):
    def begin(self, mission: dict[str, Any]) -> int: ...
    def detect(self) -> int: ...
    def move(self, goal: int) -> int: ...
    def end(self) -> None: ...


class SimBackend:
    """A simulated robot in the fleet simulator's world (shared/tools/world.py), over Zenoh.

    Moves always arrive. ``detect`` sends this robot's (t, node) to the world's queryable
    ``mures/<fleet>/sim/<mission>/<robot>`` and returns the world's z; the world answers once
    every robot of the mission has reported step t (lockstep), so this is where robots wait for
    each other. It carries only this robot's own state, never the others'.
    """

    def __init__(self, graph: Graph, robot_id: str, session: zenoh.Session, fleet: str, timeout: float = 30.0) -> None:
        self.graph = graph
        self.robot_id = robot_id
        self.session = session
        self.fleet = fleet
        self.timeout = timeout
        self.mission = ""
        self.node = -1
        self.t = 0

    def begin(self, mission: dict[str, Any]) -> int:
        self.mission = mission["mission_id"]
        self.node = int(mission.get("start_node", self.graph.labels[self.graph.start]))
        self.t = 0
        return self.node

    def move(self, goal: int) -> int:
        row = self.graph.index[self.node]
        if goal not in self.graph.index or self.graph.index[goal] not in self.graph.closed(row):
            raise BackendError(f"goal {goal} is not in N[{self.node}]")
        self.node = goal
        self.t += 1
        return self.node

    def detect(self) -> int:
        payload = json.dumps({"t": self.t, "node": self.node}).encode()
        key = sim_key(self.fleet, self.mission, self.robot_id)
        for reply in self.session.get(
            key, payload=payload, timeout=self.timeout, consolidation=zenoh.ConsolidationMode.NONE
        ):
            if reply.ok is None:
                err = reply.err.payload.to_bytes().decode(errors="replace") if reply.err else "?"
                raise BackendError(f"the simulated world refused step t={self.t}: {err}")
            msg = json.loads(reply.ok.payload.to_bytes())
            if msg.get("ended"):
                raise MissionOver
            return int(msg["z"])
        if self.t == 0:
            raise BackendError(
                f"no simulated world answers on {key} (waited {self.timeout:.0f} s): the sim backend needs one; "
                "start it with `mures world` (or run the whole fleet with `mures fleet-sim`)"
            )
        raise BackendError(f"the simulated world did not answer step t={self.t} within {self.timeout:.0f} s")

    def end(self) -> None:
        self.mission = ""


def resolve_backend(spec: str) -> type:
    """``sim`` or ``MODULE:CLASS`` -> the backend's class, or ValueError saying why not (checked at
    the agent's start, before it connects anywhere)."""
    if spec == "sim":
        return SimBackend
    if spec == "nav2":
        try:
            return resolve_backend(NAV2_BACKEND)
        except ValueError as exc:  # pycdr2 missing: the nav2 extra
            raise ValueError(f"--backend nav2 needs the nav2 extra (pip install 'mures-fleet[nav2]'): {exc}") from None
    mod_name, sep, cls_name = spec.partition(":")
    if not sep or not mod_name or not cls_name:
        raise ValueError(f"--backend must be 'sim', 'nav2' or MODULE:CLASS, got {spec!r}")
    try:
        cls = getattr(importlib.import_module(mod_name), cls_name)
    except (ImportError, AttributeError) as exc:
        raise ValueError(f"--backend {spec}: cannot load ({exc})") from None
    except Exception as exc:  # the module itself failed while importing
        raise ValueError(f"--backend {spec}: importing {mod_name} failed ({type(exc).__name__}: {exc})") from None
    if not isinstance(cls, type):
        raise ValueError(f"--backend {spec}: {cls_name} is not a class")
    missing = [m for m in ("begin", "detect", "move", "end") if not callable(getattr(cls, m, None))]
    if missing:
        raise ValueError(f"--backend {spec}: the class has no {', '.join(f'{m}()' for m in missing)} method")
    return cls


def load_backend(spec: str, **kwargs: Any) -> RobotBackend:
    """``sim`` or ``MODULE:CLASS`` -> a backend instance; ValueError with the reason when the class
    cannot be loaded or constructed. Its constructor gets the keyword arguments it takes."""
    cls = resolve_backend(spec)
    params = inspect.signature(cls).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    try:
        backend = cls(**{k: v for k, v in kwargs.items() if takes_any or k in params})
    except Exception as exc:  # a constructor that needs more, or a robot that is not there
        raise ValueError(f"--backend {spec}: cannot construct it ({type(exc).__name__}: {exc})") from None
    return backend
