"""``--backend nav2``: a ROS 2 robot running Nav2, driven through zenoh-bridge-ros2dds on the fleet's
Zenoh network, without a ROS install on the agent's side (docs/connecting-a-robot.md).

The bridge maps the robot's ROS graph into Zenoh under its namespace (``--nav2-namespace``,
default the robot id). The backend reaches it on ``--nav2-connect`` (the bridge's own endpoint on
the robot, e.g. tcp/127.0.0.1:7447: the robot's ROS traffic stays on the robot) or, without it,
through the agent's fleet session. It uses, with CDR payloads (robot_agent/nav2_msgs.py):

    <ns>/navigate_to_pose/_action/send_goal    query: NavigateToPose_SendGoal_Request -> _Response
    <ns>/navigate_to_pose/_action/get_result   query: NavigateToPose_GetResult_Request -> _Response
    <ns>/navigate_to_pose/_action/cancel_goal  query: CancelGoal_Request -> _Response
    <ns>/<pose topic>                          subscribed: PoseWithCovarianceStamped (amcl_pose)
    <ns>/<detection topic>                     subscribed: std_msgs/Bool (the target detector)

A mission starts at the node whose region holds the robot's pose: looked up in the regions image
`mures map import --regions` wrote (``--nav2-regions REGIONS.png`` with ``--nav2-map MAP.yaml``,
the map it was imported from), or, without them, the node whose position is nearest. A move sends
a NavigateToPose goal to the node's position (the graph file's ``positions``, map frame) and waits
for its result: succeeded, the robot is at the goal node; aborted, canceled, or
no result within ``--nav2-goal-timeout`` (the goal is then cancelled), it stays where it was (a
legal move: staying), and the agent's log says why. A robot that does not answer a goal or a pose
within ``--nav2-answer-timeout`` is down: the mission ends for it with that reason (BackendError).
``detect`` is 1 when the detector published true since the last reading.

``clock`` (the agent's mission clock, docs/deploying.md "Clocks") reads the robot's own: the
header stamp of its latest pose, in seconds since the pose it began the mission on. So arrivals and
detections are timed by the robot, under ROS simulated time (``use_sim_time``) too, where the
robot's seconds are not the agent's; a robot whose poses carry no stamp (all zero) leaves the agent
its own clock (None).
"""

from __future__ import annotations

import logging
import math
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import zenoh

from robot_agent import nav2_msgs as msg
from robot_agent.backend import BackendError
from shared.core.graph import Graph
from shared.core.map_frame import MapFrame
from shared.core.wire import zenoh_config

log = logging.getLogger("mures.agent.nav2")

GOAL_TIMEOUT_S = 120.0  # the longest a navigation goal may take before it is cancelled
ANSWER_TIMEOUT_S = 10.0  # the longest the robot may leave a goal or its pose unanswered
OUTCOMES = {msg.STATUS_SUCCEEDED: "succeeded", msg.STATUS_CANCELED: "canceled", msg.STATUS_ABORTED: "aborted"}


def action_key(namespace: str, part: str) -> str:
    """The bridge's key of NavigateToPose's ``part`` (send_goal, get_result, cancel_goal, ...)."""
    return f"{namespace}/navigate_to_pose/_action/{part}"


class Nav2Backend:
    """One Nav2 robot, over the bridge's keys (module docstring)."""

    def __init__(self, graph: Graph, robot_id: str, session: zenoh.Session, args: Any = None) -> None:
        missing = [int(v) for i, v in enumerate(graph.labels) if i not in graph.positions]
        if missing:
            raise ValueError(f"the graph has no position for nodes {missing[:10]}: a goal needs one per node")
        self.graph, self.robot_id = graph, robot_id
        bridge = getattr(args, "nav2_connect", None)
        self.own_session = zenoh.open(zenoh_config("client", connect=[bridge])) if bridge else None
        self.session = self.own_session or session
        self.ns = (getattr(args, "nav2_namespace", None) or robot_id).strip("/")
        self.goal_timeout = float(getattr(args, "nav2_goal_timeout", None) or GOAL_TIMEOUT_S)
        self.answer_timeout = float(getattr(args, "nav2_answer_timeout", None) or ANSWER_TIMEOUT_S)
        pose_topic = getattr(args, "nav2_pose_topic", None) or "amcl_pose"
        detection_topic = getattr(args, "nav2_detection_topic", None) or "detection"
        self.lock = threading.Lock()
        self.pose: tuple[float, float] | None = None
        self.stamp_s = 0.0  # the latest pose's header stamp, the robot's clock (0: none)
        self.zero_s: float | None = None  # the stamp the mission began on
        self.detected = False
        self.node = -1
        self.regions = load_regions(getattr(args, "nav2_regions", None), getattr(args, "nav2_map", None))
        self.pose_sub = self.session.declare_subscriber(f"{self.ns}/{pose_topic}", self._on_pose)
        self.detection_sub = self.session.declare_subscriber(f"{self.ns}/{detection_topic}", self._on_detection)

    # callbacks: decode and keep, no Zenoh call (docs/zenoh.md)
    def _on_pose(self, sample: Any) -> None:
        try:
            m = msg.PoseWithCovarianceStamped.deserialize(bytes(sample.payload.to_bytes()))
        except Exception as exc:
            log.warning("nav2: a pose that is no PoseWithCovarianceStamped: %s", exc)
            return
        p, stamp = m.pose.pose.position, m.header.stamp
        with self.lock:
            self.pose = (p.x, p.y)
            self.stamp_s = max(self.stamp_s, stamp.sec + stamp.nanosec * 1e-9)  # a late pose never turns it back

    def _on_detection(self, sample: Any) -> None:
        try:
            seen = msg.Bool.deserialize(bytes(sample.payload.to_bytes())).data
        except Exception as exc:
            log.warning("nav2: a detection that is no std_msgs/Bool: %s", exc)
            return
        if seen:
            with self.lock:
                self.detected = True

    def node_at(self, x: float, y: float) -> int:
        """The label of the node whose region holds map-frame point (x, y) (``regions``), else of
        the node whose position is nearest."""
        if self.regions is not None:
            labels, frame = self.regions
            row, col = frame.to_pixel(x, y)
            if 0 <= row < labels.shape[0] and 0 <= col < labels.shape[1] and labels[row, col] > 0:
                label = int(labels[row, col]) - 1  # region k + 1 is node k (mures map import)
                if label in self.graph.index:
                    return label
            log.warning("nav2: pose (%.2f, %.2f) is in no region of the regions image: the nearest node", x, y)
        best = min(self.graph.positions, key=lambda i: math.dist(self.graph.positions[i], (x, y)))
        return int(self.graph.labels[best])

    def begin(self, mission: dict[str, Any]) -> int:
        """The node nearest to the robot's pose (waiting for its first pose at most the answer
        timeout); the detector's earlier readings are forgotten."""
        deadline = time.monotonic() + self.answer_timeout
        while True:
            with self.lock:
                pose, self.detected = self.pose, False
                self.zero_s = self.stamp_s if self.stamp_s > 0 else None
            if pose is not None:
                break
            if time.monotonic() > deadline:
                raise BackendError(
                    f"nav2: no pose from robot {self.robot_id} on {self.ns}/… within {self.answer_timeout:g} s "
                    "(is zenoh-bridge-ros2dds running on it, with its pose topic allowed?)"
                )
            time.sleep(0.05)
        self.node = self.node_at(*pose)
        return self.node

    def detect(self) -> int:
        with self.lock:
            seen, self.detected = self.detected, False
        return int(seen)

    def clock(self) -> float | None:
        """Seconds on the robot's clock since the mission began (module docstring), or None."""
        with self.lock:
            stamp, zero = self.stamp_s, self.zero_s
        return None if zero is None else max(0.0, stamp - zero)

    def move(self, goal: int) -> int:
        """Navigate to ``goal``'s position: ``goal`` once there, the node it was on otherwise."""
        if goal not in self.graph.index:
            raise BackendError(f"nav2: goal {goal} is not on the map")
        if goal == self.node:
            return self.node  # staying: no goal to send
        goal_id = msg.UUID(uuid.uuid4().bytes)  # type: ignore[arg-type]  # pycdr2 takes bytes for uint8[16]
        x, y = self.graph.positions[self.graph.index[goal]]
        pose = msg.PoseStamped(msg.Header(_now(), "map"), msg.Pose(msg.Point(float(x), float(y), 0.0)))
        request = msg.NavigateToPose_SendGoal_Request(goal_id, msg.NavigateToPose_Goal(pose, ""))
        reply = self._ask("send_goal", request.serialize(), self.answer_timeout)
        if reply is None:
            raise BackendError(
                f"nav2: robot {self.robot_id} did not answer a goal on {action_key(self.ns, 'send_goal')} "
                f"within {self.answer_timeout:g} s"
            )
        if not msg.NavigateToPose_SendGoal_Response.deserialize(reply).accepted:
            log.warning("nav2: goal to node %s rejected by Nav2; robot %s stays at %s", goal, self.robot_id, self.node)
            return self.node
        raw = self._ask("get_result", msg.NavigateToPose_GetResult_Request(goal_id).serialize(), self.goal_timeout)
        if raw is None:
            log.warning(
                "nav2: goal to node %s timed out after %g s; cancelled, robot %s stays at %s",
                goal, self.goal_timeout, self.robot_id, self.node,
            )  # fmt: skip
            self._ask("cancel_goal", msg.CancelGoal_Request(msg.GoalInfo(goal_id, msg.Time())).serialize(), 2.0)
            return self.node
        result = msg.NavigateToPose_GetResult_Response.deserialize(raw)
        if result.status == msg.STATUS_SUCCEEDED:
            self.node = goal
        else:
            log.warning(
                "nav2: goal to node %s %s (error %s: %s); robot %s stays at %s",
                goal, OUTCOMES.get(result.status, f"ended with status {result.status}"),
                result.result.error_code, result.result.error_msg or "-", self.robot_id, self.node,
            )  # fmt: skip
        return self.node

    def _ask(self, part: str, payload: bytes, timeout: float) -> bytes | None:
        """The first reply's payload to a query on the action's ``part``, or None by ``timeout``."""
        replies = self.session.get(action_key(self.ns, part), payload=payload, timeout=timeout)
        for reply in replies:
            if reply.ok is not None:
                return bytes(reply.ok.payload.to_bytes())
            err = reply.err.payload.to_string() if reply.err is not None else "?"
            log.warning("nav2: %s answered with an error: %s", part, err)
        return None

    def end(self) -> None:
        pass

    def close(self) -> None:
        self.pose_sub.undeclare()
        self.detection_sub.undeclare()
        if self.own_session is not None:
            self.own_session.close()


def load_regions(regions: str | None, map_yaml: str | None) -> tuple[Any, MapFrame] | None:
    """(labels (H, W), the map frame) from a regions image and the map it was made from; None
    without them. ValueError names what is wrong."""
    if regions is None and map_yaml is None:
        return None
    if regions is None or map_yaml is None:
        raise ValueError("--nav2-regions and --nav2-map go together: the regions image and the map it was made from")
    import numpy as np
    import yaml
    from PIL import Image

    try:
        with Image.open(regions) as im:
            labels = np.asarray(im, dtype=np.int64)
        raw = yaml.safe_load(Path(map_yaml).read_text(encoding="utf-8"))
        frame = MapFrame(float(raw["resolution"]), tuple(float(v) for v in raw["origin"]), labels.shape[0])  # type: ignore[arg-type]
    except (OSError, ValueError, KeyError, TypeError, yaml.YAMLError) as exc:
        raise ValueError(f"cannot read --nav2-regions {regions} with --nav2-map {map_yaml}: {exc}") from None
    if labels.ndim != 2:
        raise ValueError(f"--nav2-regions {regions} is not a one-channel (16-bit) regions image")
    return labels, frame


def _now() -> msg.Time:
    t = time.time()
    return msg.Time(int(t), int((t % 1) * 1e9))
