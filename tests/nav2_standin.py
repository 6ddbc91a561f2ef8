"""A stand-in for Nav2 robots behind zenoh-bridge-ros2dds: what `robot-agent --backend nav2` talks
to, without ROS. For each robot it answers NavigateToPose's send_goal, get_result and cancel_goal
queries on the bridge's keys with CDR payloads, drives the robot to the goal's node after
``--move-delay`` seconds, publishes its pose (amcl_pose, stamped with a robot clock at ``--clock-rate``
times the wall's) and its detector (std_msgs/Bool: true when
it stands on the target's node; the target walks one step, uniformly over its closed
neighbourhood, whenever a goal ends). Faults on purpose: ``--abort r1:3`` aborts robot r1's third
goal, ``--hang r2:5`` never ends robot r2's fifth (the agent's goal timeout cancels it).

    python tests/nav2_standin.py --graph G.json --robots r1,r2 --listen tcp/127.0.0.1:7447 [--move-delay 0.05]

Prints "ready" once its queryables are declared; logs every goal's outcome on stderr.
"""

from __future__ import annotations

import argparse
import math
import queue
import random
import sys
import threading
import time
from pathlib import Path

import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from robot_agent import nav2_msgs as msg
from robot_agent.nav2 import action_key
from shared.core.graph import load_graph_file
from shared.core.wire import zenoh_config


def faults(specs: list[str]) -> set[tuple[str, int]]:
    out = set()
    for spec in specs:
        robot, _, k = spec.partition(":")
        out.add((robot, int(k)))
    return out


class Robot:
    def __init__(self, rid: str, start: int) -> None:
        self.rid, self.node, self.goals = rid, start, 0
        self.results: dict[bytes, tuple[int, int]] = {}  # goal id -> (status, error code), once ended
        self.waiting: dict[bytes, list] = {}  # goal id -> get_result queries waiting for it


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--graph", required=True)
    ap.add_argument("--robots", required=True)
    ap.add_argument("--listen", required=True, help="the endpoint the agents' --nav2-connect names, as a bridge's")
    ap.add_argument("--move-delay", type=float, default=0.05)
    ap.add_argument("--abort", nargs="*", default=[])
    ap.add_argument("--hang", nargs="*", default=[])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--clock-rate", type=float, default=0.0,
        help="stamp poses with a robot clock running at this rate of the wall's (ROS simulated time); 0: no stamps",
    )  # fmt: skip
    args = ap.parse_args()
    began = time.monotonic()
    graph = load_graph_file(args.graph)
    rng = random.Random(args.seed)
    aborts, hangs = faults(args.abort), faults(args.hang)
    robots = {rid: Robot(rid, graph.start) for rid in args.robots.split(",")}
    target = [rng.randrange(graph.n)]
    session = zenoh.open(zenoh_config("peer", listen=[args.listen]))
    queries: queue.Queue = queue.Queue()  # (robot, part, query): answered by the main loop, not in callbacks
    handles = []
    for rid in robots:
        for part in ("send_goal", "get_result", "cancel_goal"):
            handles.append(
                session.declare_queryable(
                    action_key(rid, part), lambda q, rid=rid, part=part: queries.put((rid, part, q)), complete=True
                )
            )
    pubs = {
        rid: (session.declare_publisher(f"{rid}/amcl_pose"), session.declare_publisher(f"{rid}/detection"))
        for rid in robots
    }
    lock = threading.Lock()

    def publish(robot: Robot) -> None:
        x, y = graph.positions[robot.node]
        robot_s = 1000.0 + (time.monotonic() - began) * args.clock_rate if args.clock_rate else 0.0
        stamp = msg.Time(int(robot_s), int((robot_s % 1) * 1e9))
        pose = msg.PoseWithCovarianceStamped(msg.Header(stamp, "map"))
        pose.pose.pose.position = msg.Point(float(x), float(y), 0.0)
        pubs[robot.rid][0].put(pose.serialize())
        pubs[robot.rid][1].put(msg.Bool(robot.node == target[0]).serialize())

    def drive(robot: Robot, goal_id: bytes, goal: int, k: int) -> None:
        time.sleep(args.move_delay)
        with lock:
            if (robot.rid, k) in aborts:
                status, code = msg.STATUS_ABORTED, 9000
            else:
                status, code, robot.node = msg.STATUS_SUCCEEDED, 0, goal
            nbrs = list(graph.closed(target[0]))
            target[0] = nbrs[rng.randrange(len(nbrs))]
            robot.results[goal_id] = (status, code)
            waiting = robot.waiting.pop(goal_id, [])
        print(
            f"{robot.rid} goal {k} to node {graph.labels[goal]}: {'aborted' if code else 'succeeded'}", file=sys.stderr
        )
        for q in waiting:
            queries.put((robot.rid, "result_ready", q))

    def answer_result(robot: Robot, q, goal_id: bytes) -> None:
        status, code = robot.results[goal_id]
        reply = msg.NavigateToPose_GetResult_Response(
            status, msg.NavigateToPose_Result(code, "stand-in" if code else "")
        )
        q.reply(q.key_expr, reply.serialize())
        q.drop()

    print("ready", flush=True)
    last_pose = 0.0
    try:
        while True:
            try:
                rid, part, q = queries.get(timeout=0.1)
            except queue.Empty:
                rid = part = q = None
            if time.monotonic() - last_pose > 0.2:  # poses and detections at 5 Hz
                last_pose = time.monotonic()
                with lock:
                    for robot in robots.values():
                        publish(robot)
            if q is None:
                continue
            robot = robots[rid]
            if part == "send_goal":
                req = msg.NavigateToPose_SendGoal_Request.deserialize(bytes(q.payload.to_bytes()))
                p = req.goal.pose.pose.position
                goal = min(graph.positions, key=lambda i: math.dist(graph.positions[i], (p.x, p.y)))
                robot.goals += 1
                q.reply(q.key_expr, msg.NavigateToPose_SendGoal_Response(True, msg.Time()).serialize())
                q.drop()
                if (rid, robot.goals) in hangs:
                    print(f"{rid} goal {robot.goals}: never ends (a timeout)", file=sys.stderr)
                    continue
                threading.Thread(target=drive, args=(robot, bytes(req.goal_id.uuid), goal, robot.goals)).start()
            elif part == "get_result":
                goal_id = bytes(
                    msg.NavigateToPose_GetResult_Request.deserialize(bytes(q.payload.to_bytes())).goal_id.uuid
                )
                with lock:
                    ready = goal_id in robot.results
                    if not ready:
                        robot.waiting.setdefault(goal_id, []).append(q)
                if ready:
                    answer_result(robot, q, goal_id)
            elif part == "result_ready":
                raw = msg.NavigateToPose_GetResult_Request.deserialize(bytes(q.payload.to_bytes()))
                answer_result(robot, q, bytes(raw.goal_id.uuid))
            elif part == "cancel_goal":
                q.reply(q.key_expr, msg.CancelGoal_Response(0, []).serialize())
                q.drop()
    except KeyboardInterrupt:
        pass
    finally:
        for h in handles:
            h.undeclare()
        session.close()


if __name__ == "__main__":
    main()
