"""The robot backend: what the agent needs from a robot, and the simulated one.

A backend moves the robot between nodes of the map and runs its detector. The agent calls, per
mission::

    node = backend.begin(mission)   # the node the robot stands on at t = 0 (a label: an int)
    z = backend.detect()            # 0 or 1 (an int; True/False are taken): the detector's reading
                                    # at the current node, step t
    node = backend.move(goal)       # go to goal (a label in N[node]); returns where the robot is
                                    # after the move: goal on arrival, another node on failure
    backend.end()                   # the mission is over (stop, park, release resources)
    backend.clock()                 # optional: the mission clock (s) of the last reading, or None

A backend without ``clock`` leaves the time of a reading to the agent: the seconds since it began
the mission (robot-agent --team-clock seconds; the agents start within a network delay of each
other, when the server's start message reaches them).

``mission`` is the mission's start message, a dict (docs/SPEC.md section 6): "mission_id" (str),
"robots" (the mission's robot ids, in order), "start_node" (the label every robot starts on),
"seed", "max_steps", "capture" ("auto" or "confirm"), "policy_version". Labels are the map's node
labels (``graph.labels``; ``graph.index`` maps a label to its row).

Every return value is checked (``CheckedBackend``): a label not on the map, a z that is not 0 or
1 (the string "1" included), or any exception other than ``MissionOver`` ends this robot's part of
the mission with a one-line reason that the server records (the robot withdraws, docs/operating.md);
the agent stays up for the next mission. ``detect`` or ``move`` may raise ``MissionOver`` when the
robot's world says the mission has ended (the simulated world does; a real robot learns it from the
mission-control message), and ``BackendError("why")`` when the robot cannot go on: both are
importable from ``robot_agent.backend``.

``--backend MODULE:CLASS`` loads any class with this interface, MODULE found on Python's path with
the agent's working directory added (so a module in the folder the agent is started from loads);
``--backend path/to/file.py:CLASS`` loads it from that file. Its constructor is called as
``CLASS(graph=..., robot_id=..., session=..., fleet=..., args=...)`` (``args``: the agent's parsed
flags; keyword arguments it does not take are not passed). ``--backend nav2`` is a Nav2 robot
through zenoh-bridge-ros2dds (robot_agent/nav2.py); ``robot_agent/examples/nav_goal.py`` is a
documented adapter for a navigation stack that takes goal nodes, as the paper's robots did.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import json
import logging
import numbers
import os
import sys
import time
from pathlib import Path
from typing import Any, Protocol

import zenoh

from shared.core.graph import Graph
from shared.core.records import is_seconds
from shared.core.wire import WORLD_CLOCK_PROBE, sim_key

log = logging.getLogger("mures.agent")
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
    each other. It carries only this robot's own state, never the others'. ``wait_s``, when the
    agent sets it, goes with each report: how long this robot's decision waits for its teammates'
    observations (the continuous world answers together only the robots arriving within it).
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
        self.time_s: float | None = None
        self.wait_s: float | None = None  # this robot's wait for its teammates' observations (None: not said)

    def begin(self, mission: dict[str, Any]) -> int:
        self.mission = mission["mission_id"]
        self.node = int(mission.get("start_node", self.graph.labels[self.graph.start]))
        self.t = 0
        self.time_s = None
        return self.node

    def clock(self) -> float | None:
        """The continuous world's clock of the last reading (None from the step world)."""
        return self.time_s

    def move(self, goal: int) -> int:
        row = self.graph.index[self.node]
        if goal not in self.graph.index or self.graph.index[goal] not in self.graph.closed(row):
            raise BackendError(f"goal {goal} is not in N[{self.node}]")
        self.node = goal
        self.t += 1
        return self.node

    def detect(self) -> int:
        report = {"t": self.t, "node": self.node, **({} if self.wait_s is None else {"wait_s": self.wait_s})}
        payload = json.dumps(report).encode()
        key = sim_key(self.fleet, self.mission, self.robot_id)
        start = time.monotonic()
        while (left := self.timeout - (time.monotonic() - start)) > 0:
            for reply in self.session.get(
                key, payload=payload, timeout=left, consolidation=zenoh.ConsolidationMode.NONE
            ):
                if reply.ok is None:
                    err = reply.err.payload.to_bytes().decode(errors="replace") if reply.err else "?"
                    raise BackendError(f"the simulated world refused step t={self.t}: {err}")
                msg = json.loads(reply.ok.payload.to_bytes())
                if msg.get("ended"):
                    raise MissionOver
                self.time_s = float(msg["time_s"]) if "time_s" in msg else None
                return int(msg["z"])
            # no reply: either no world is there yet (a get with no queryable to match ends at once,
            # so ask again until the timeout) or it did not answer in time
            time.sleep(min(0.5, max(0.0, self.timeout - (time.monotonic() - start))))
        waited = time.monotonic() - start
        if self.t == 0:
            raise BackendError(
                f"no simulated world answers on {key} (waited {round(waited, 1):g} s): the sim backend needs one; "
                "start it with `mures world` (with the kit's --zenoh-* flags on a secured fleet), or run the "
                "whole fleet with `mures fleet-sim`"
            )
        raise BackendError(f"the simulated world did not answer step t={self.t} within {round(waited, 1):g} s")

    def end(self) -> None:
        self.mission = ""

    def world_clock(self, timeout: float = 1.0) -> str | None:
        """The clock the simulated world keeps: "seconds" (the continuous world, `mures world
        --world`), "steps" (every robot's step together), or None when no world answers within
        ``timeout`` seconds (a world older than the question never does)."""
        key = sim_key(self.fleet, WORLD_CLOCK_PROBE, self.robot_id)
        try:
            for reply in self.session.get(key, timeout=timeout):
                if reply.ok is not None:
                    clock = json.loads(reply.ok.payload.to_bytes()).get("clock")
                    if clock in ("steps", "seconds"):
                        return str(clock)
        except Exception as exc:  # a closed session, an answer that is not JSON: no answer
            log.debug("asking the simulated world its clock: %s", exc)
        return None


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
    mod_name, sep, cls_name = spec.rpartition(":")
    if not sep or not mod_name or not cls_name:
        raise ValueError(f"--backend must be 'sim', 'nav2', MODULE:CLASS or FILE.py:CLASS, got {spec!r}")
    try:
        cls = getattr(_import_backend_module(mod_name), cls_name)
    except (ImportError, AttributeError, FileNotFoundError) as exc:
        raise ValueError(f"--backend {spec}: cannot load ({exc}){_path_hint(mod_name)}") from None
    except Exception as exc:  # the module itself failed while importing
        raise ValueError(f"--backend {spec}: importing {mod_name} failed ({type(exc).__name__}: {exc})") from None
    if not isinstance(cls, type):
        raise ValueError(f"--backend {spec}: {cls_name} is not a class")
    missing = [m for m in ("begin", "detect", "move", "end") if not callable(getattr(cls, m, None))]
    if missing:
        raise ValueError(f"--backend {spec}: the class has no {', '.join(f'{m}()' for m in missing)} method")
    return cls


def _import_backend_module(name: str) -> Any:
    """MODULE (on sys.path, with the working directory added as ``python -m`` would) or a
    FILE.py path."""
    if name.endswith(".py"):
        path = Path(name)
        if not path.is_file():
            raise FileNotFoundError(f"no file {name}")
        mod_spec = importlib.util.spec_from_file_location(path.stem, path)
        if mod_spec is None or mod_spec.loader is None:
            raise ImportError(f"{name} is not a Python module")
        module = importlib.util.module_from_spec(mod_spec)
        sys.modules[path.stem] = module
        mod_spec.loader.exec_module(module)
        return module
    if os.getcwd() not in sys.path and "" not in sys.path:
        sys.path.append(os.getcwd())  # after the installed packages: a local file shadows none of them
    return importlib.import_module(name)


def _path_hint(name: str) -> str:
    if name.endswith(".py"):
        return ""
    return (
        f"; the agent looks for {name} on Python's path and in its working directory {os.getcwd()}: "
        "start it from the module's folder, set PYTHONPATH, or give --backend "
        f"path/to/{name.replace('.', '/')}.py:CLASS"
    )


def _label(value: Any, graph: Graph, method: str) -> int:
    """A node label a backend returned, checked: an integer (not a bool) that is on the map."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise BackendError(f"backend {method} returned {value!r} ({type(value).__name__}); expected a node label (int)")
    if int(value) not in graph.index:
        raise BackendError(f"backend {method} returned node {int(value)}, which is not on the map")
    return int(value)


class CheckedBackend:
    """Any backend, with what it returns checked (module docstring): a label not on the map, a z
    that is not 0 or 1, or an exception other than MissionOver becomes a BackendError whose text
    says which call and what it returned."""

    def __init__(self, backend: RobotBackend, graph: Graph) -> None:
        self.backend, self.graph = backend, graph

    def _call(self, method: str, *args: Any) -> Any:
        try:
            return getattr(self.backend, method)(*args)
        except (MissionOver, BackendError):
            raise
        except Exception as exc:
            raise BackendError(f"backend {method}() raised {type(exc).__name__}: {exc}") from exc

    def begin(self, mission: dict[str, Any]) -> int:
        return _label(self._call("begin", mission), self.graph, "begin()")

    def detect(self) -> int:
        z = self._call("detect")
        if isinstance(z, bool):
            return int(z)
        if not isinstance(z, numbers.Integral) or int(z) not in (0, 1):
            raise BackendError(f"backend detect() returned {z!r} ({type(z).__name__}); expected 0 or 1")
        return int(z)

    def move(self, goal: int) -> int:
        return _label(self._call("move", goal), self.graph, f"move({goal})")

    def end(self) -> None:
        self._call("end")

    def tell_team_wait(self, seconds: float) -> None:
        """How long this robot's decisions wait for its teammates' observations, for a backend
        whose world answers together only the robots that wait for each other (``sim``'s
        ``wait_s``); others are not told."""
        if isinstance(self.backend, SimBackend):
            self.backend.wait_s = seconds

    def world_clock(self, timeout: float) -> str | None:
        """The clock a simulated world keeps (``SimBackend.world_clock``); None for any other
        backend, or when no world answers."""
        return self.backend.world_clock(timeout) if isinstance(self.backend, SimBackend) else None

    def clock(self) -> float | None:
        """The backend's mission clock of its last reading (seconds, finite, >= 0), or None where
        it keeps none."""
        if not callable(getattr(self.backend, "clock", None)):
            return None
        value = self._call("clock")
        if value is None:
            return None
        if not is_seconds(value):
            raise BackendError(f"backend clock() returned {value!r}; expected seconds (a finite number >= 0) or None")
        return float(value)


def load_backend(spec: str, **kwargs: Any) -> RobotBackend:
    """``sim``, ``nav2``, ``MODULE:CLASS`` or ``FILE.py:CLASS`` -> a backend instance (a
    CheckedBackend when ``graph`` is given, as the agent gives it); ValueError with the reason when
    the class cannot be loaded or constructed. Its constructor gets the keyword arguments it takes."""
    cls = resolve_backend(spec)
    params = inspect.signature(cls).parameters
    takes_any = any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())
    try:
        backend = cls(**{k: v for k, v in kwargs.items() if takes_any or k in params})
    except Exception as exc:  # a constructor that needs more, or a robot that is not there
        raise ValueError(f"--backend {spec}: cannot construct it ({type(exc).__name__}: {exc})") from None
    graph = kwargs.get("graph")
    return CheckedBackend(backend, graph) if graph is not None else backend
