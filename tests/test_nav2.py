"""`robot-agent --backend nav2`: the CDR codec agrees with rosbags (an independent implementation,
built from Nav2's own NavigateToPose.action) both ways, and robot-agent processes fly missions
against a stand-in for Nav2 robots behind zenoh-bridge-ros2dds (tests/nav2_standin.py), an aborted
goal and a timed-out one leaving the robot where it was."""

from __future__ import annotations

import dataclasses
import itertools
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from robot_agent import nav2_msgs as msg
from robot_agent.nav2 import Nav2Backend, load_regions
from shared.core.graph import load_graph_file
from shared.core.models import Sensor, uniform_walk
from shared.tools.cli import main as mures
from shared.tools.fleetsim import free_port, launch, wait_until

ROOT = Path(__file__).resolve().parents[1]
ACTION = ROOT / "tests" / "data" / "nav2_msgs" / "NavigateToPose.action"


@pytest.fixture(scope="module")
def typestore():
    """rosbags' ROS 2 Jazzy types, with NavigateToPose's parts and the action's generated types."""
    store = get_typestore(Stores.ROS2_JAZZY)
    goal, result, feedback = ACTION.read_text().split("---")
    name = "nav2_msgs/action/NavigateToPose"
    defs = {
        f"{name}_Goal": goal,
        f"{name}_Result": result,
        f"{name}_Feedback": feedback,
        f"{name}_SendGoal_Request": f"unique_identifier_msgs/UUID goal_id\n{name}_Goal goal",
        f"{name}_SendGoal_Response": "bool accepted\nbuiltin_interfaces/Time stamp",
        f"{name}_GetResult_Request": "unique_identifier_msgs/UUID goal_id",
        f"{name}_GetResult_Response": f"int8 status\n{name}_Result result",
        f"{name}_FeedbackMessage": f"unique_identifier_msgs/UUID goal_id\n{name}_Feedback feedback",
        "action_msgs/srv/CancelGoal_Request": "action_msgs/GoalInfo goal_info",
        "action_msgs/srv/CancelGoal_Response": "int8 return_code\naction_msgs/GoalInfo[] goals_canceling",
    }
    names = {}  # our typename -> rosbags' (it files a service's types under .../srv/msg/...)
    for typename, text in defs.items():
        types = get_types_from_msg(text, typename)
        store.register(types)
        names[typename] = next(iter(types))
    return store, names


def _ours():
    """One of each message, every field away from its default."""
    stamp = msg.Time(1_733_000_000, 123_456_789)
    pose = msg.PoseStamped(
        msg.Header(stamp, "map"), msg.Pose(msg.Point(1.5, -2.25, 0.0), msg.Quaternion(0, 0, 0.6, 0.8))
    )
    goal_id = msg.UUID(bytes(range(16)))
    feedback = msg.NavigateToPose_Feedback(pose, msg.Duration(3, 5), msg.Duration(7, 9), 2, 4.5)
    with_cov = msg.PoseWithCovarianceStamped(msg.Header(stamp, "map"), msg.PoseWithCovariance(pose.pose, [0.1] * 36))
    return [
        msg.Bool(True),
        with_cov,
        msg.NavigateToPose_SendGoal_Request(goal_id, msg.NavigateToPose_Goal(pose, "bt.xml")),
        msg.NavigateToPose_SendGoal_Response(True, stamp),
        msg.NavigateToPose_GetResult_Request(goal_id),
        msg.NavigateToPose_GetResult_Response(msg.STATUS_ABORTED, msg.NavigateToPose_Result(9003, "timeout")),
        msg.NavigateToPose_FeedbackMessage(goal_id, feedback),
        msg.CancelGoal_Request(msg.GoalInfo(goal_id, stamp)),
        msg.CancelGoal_Response(1, [msg.GoalInfo(goal_id, stamp)]),
    ]


def _plain(x):
    """A message as nested plain values, ours or rosbags' alike."""
    if dataclasses.is_dataclass(x):  # fields only: a message's constants (UPPER_CASE in ROS) are not sent
        names = [f.name for f in dataclasses.fields(x) if f.name != "__msgtype__" and not f.name.isupper()]
        return {k: _plain(getattr(x, k)) for k in names}
    if isinstance(x, (bytes, bytearray)) or (hasattr(x, "tolist") and not isinstance(x, (int, float))):
        return [_plain(v) for v in (list(x) if isinstance(x, (bytes, bytearray)) else x.tolist())]
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, float):
        return round(x, 5)
    return x


@pytest.mark.parametrize("index", range(9))
def test_the_codec_agrees_with_rosbags_both_ways(typestore, index):
    store, names = typestore
    ours = _ours()[index]
    typename = type(ours).__idl_typename__.replace(".", "/")
    typename = names.get(typename, typename)
    decoded = store.deserialize_cdr(ours.serialize(), typename)  # ours -> rosbags
    assert _plain(decoded) == _plain(ours)
    again = type(ours).deserialize(bytes(store.serialize_cdr(decoded, typename)))  # rosbags -> ours
    assert _plain(again) == _plain(ours)
    assert bytes(store.serialize_cdr(decoded, typename)) == ours.serialize()


def test_a_pose_is_snapped_to_the_node_of_its_region(tmp_path):
    """With the regions image, a pose's node is its region's, even where another node's position
    is nearer; outside every region, the nearest node."""
    depot = ROOT / "examples" / "maps" / "nav2" / "depot.yaml"
    graph_file, regions = tmp_path / "depot.json", tmp_path / "regions.png"
    assert mures(["map", "import", str(depot), "--out", str(graph_file), "--regions", str(regions), "--quiet"]) == 0
    graph = load_graph_file(graph_file)
    with_regions = SimpleNamespace(graph=graph, regions=load_regions(str(regions), str(depot)))
    nearest_only = SimpleNamespace(graph=graph, regions=None)
    labels, frame = with_regions.regions
    disagree = 0
    for row, col in zip(*np.nonzero(labels[::7, ::7]), strict=True):  # a grid of the building's pixels
        x, y = frame.to_map(7 * row, 7 * col)
        node = Nav2Backend.node_at(with_regions, x, y)
        assert node == labels[7 * row, 7 * col] - 1
        disagree += node != Nav2Backend.node_at(nearest_only, x, y)
    assert disagree > 0  # the nearest node is not always the region's
    x, y = frame.to_map(-50, -50)  # off the map: the nearest node
    assert Nav2Backend.node_at(with_regions, x, y) == Nav2Backend.node_at(nearest_only, x, y)
    with pytest.raises(ValueError, match="go together"):
        load_regions(str(regions), None)
    with pytest.raises(ValueError, match="cannot read"):
        load_regions(str(tmp_path / "absent.png"), str(depot))


@pytest.mark.slow
def test_agents_fly_nav2_robots_through_the_bridge_with_an_abort_and_a_timeout(tmp_path):
    depot = ROOT / "examples" / "maps" / "nav2" / "depot.yaml"
    graph_file, regions = tmp_path / "depot.json", tmp_path / "regions.png"
    assert mures(["map", "import", str(depot), "--out", str(graph_file), "--regions", str(regions), "--quiet"]) == 0
    graph = load_graph_file(graph_file)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    standin_log = tmp_path / "standin.log"
    standin = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "nav2_standin.py"), "--graph", str(graph_file), "--robots", "r1,r2",
         "--listen", endpoint, "--abort", "r1:3", "--hang", "r2:5"],
        stdout=subprocess.PIPE, stderr=standin_log.open("w"), text=True,
    )  # fmt: skip
    fleet = None
    try:
        assert standin.stdout is not None and standin.stdout.readline().strip() == "ready"
        agent_extra = ["--backend", "nav2", "--nav2-connect", endpoint, "--nav2-goal-timeout", "1.0"]
        agent_extra += ["--nav2-regions", str(regions), "--nav2-map", str(depot)]  # poses looked up by region
        fleet = launch(graph, ["--graph", str(graph_file)], uniform_walk(graph), Sensor(), 2, tmp_path / "fleet",
                       agent_extra=agent_extra)  # fmt: skip
        for seed in range(20):
            m = fleet.fly(["r1", "r2"], seed=seed, max_steps=5, timeout=60)
            assert sorted(m["episodes_received"]) == ["r1", "r2"]
        stats = fleet.api.get("/api/v1/episodes/stats")
        assert stats["stored"] >= 40, stats
        logs = {r: (tmp_path / "fleet" / "logs" / f"agent-{r}.log").read_text() for r in ("r1", "r2")}
        assert "aborted" in logs["r1"] and "stays at" in logs["r1"]  # the stand-in aborted r1's third goal
        assert "timed out after 1 s; cancelled" in logs["r2"]  # and never ended r2's fifth
        moves = wait_until(lambda: standin_log.read_text().count("succeeded") >= 20 and standin_log.read_text(), 10, "")
        assert "r1 goal 3" in moves and "aborted" in moves and "r2 goal 5: never ends" in moves
    finally:
        if fleet is not None:
            fleet.close()
        standin.terminate()
        standin.wait(10)


def test_a_nav2_robots_readings_are_timed_by_its_own_clock(tmp_path):
    """Under ROS simulated time the robot's seconds are not the agent's: with the stand-in's clock at a
    quarter of the wall's, the agents' records on the mission clock advance at the robot's rate. Nav2
    robots on a map with edge lengths fly on the mission clock without being told (--team-clock auto)."""
    depot = ROOT / "examples" / "maps" / "nav2" / "depot.yaml"
    graph_file = tmp_path / "depot.json"
    assert mures(["map", "import", str(depot), "--out", str(graph_file), "--quiet"]) == 0
    graph = load_graph_file(graph_file)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    standin = subprocess.Popen(
        [sys.executable, str(ROOT / "tests" / "nav2_standin.py"), "--graph", str(graph_file), "--robots", "r1,r2",
         "--listen", endpoint, "--move-delay", "0.4", "--clock-rate", "0.25"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )  # fmt: skip
    fleet = None
    try:
        assert standin.stdout is not None and standin.stdout.readline().strip() == "ready"
        agent_extra = ["--backend", "nav2", "--nav2-connect", endpoint]
        fleet = launch(graph, ["--graph", str(graph_file)], uniform_walk(graph), Sensor(), 2, tmp_path / "fleet",
                       agent_extra=agent_extra)  # fmt: skip
        gaps = []
        for seed in range(3):
            m = fleet.fly(["r1", "r2"], seed=seed, max_steps=6, timeout=60)
            for robot in ("r1", "r2"):
                steps = fleet.api.get(f"/api/v1/episodes/{robot}/{m['id']}")["steps"]
                times = [s["time_s"] for s in steps]
                assert times[0] == 0.0 and times == sorted(times)
                gaps += [b["time_s"] - a["time_s"] for a, b in itertools.pairwise(steps) if a["node"] != b["node"]]
        # a move takes 0.4 s of wall time, so 0.1 s of the robot's: its poses' stamps, not the agent's clock
        assert gaps and 0.0 < float(np.median(gaps)) < 0.25, gaps
    finally:
        if fleet is not None:
            fleet.close()
        standin.terminate()
        standin.wait(10)
