"""The ROS 2 messages the Nav2 backend exchanges through zenoh-bridge-ros2dds, as CDR (the
encoding DDS and the bridge carry: a 4-byte encapsulation header, then the fields aligned), with
pycdr2. Field layouts follow the ROS 2 Jazzy definitions (builtin_interfaces, std_msgs,
geometry_msgs, unique_identifier_msgs, and nav2_msgs/action/NavigateToPose, whose result is
``uint16 error_code, string error_msg``); an action's goal, result and feedback travel inside the
request and response types rosidl generates for it (``NavigateToPose_SendGoal_Request`` ...).
tests/test_nav2.py checks each against rosbags decoding with the official definitions, both ways.
"""

# no `from __future__ import annotations`: pycdr2 reads the field types at class creation
from dataclasses import dataclass, field

from pycdr2 import IdlStruct
from pycdr2.types import array, float32, float64, int8, int16, int32, sequence, uint8, uint16, uint32

# action_msgs/msg/GoalStatus
STATUS_UNKNOWN, STATUS_ACCEPTED, STATUS_EXECUTING, STATUS_CANCELING = 0, 1, 2, 3
STATUS_SUCCEEDED, STATUS_CANCELED, STATUS_ABORTED = 4, 5, 6


@dataclass
class Time(IdlStruct, typename="builtin_interfaces/msg/Time"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Duration(IdlStruct, typename="builtin_interfaces/msg/Duration"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs/msg/Header"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Bool(IdlStruct, typename="std_msgs/msg/Bool"):
    data: bool = False


@dataclass
class Point(IdlStruct, typename="geometry_msgs/msg/Point"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs/msg/Quaternion"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs/msg/Pose"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs/msg/PoseStamped"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class PoseWithCovariance(IdlStruct, typename="geometry_msgs/msg/PoseWithCovariance"):
    pose: Pose = field(default_factory=Pose)
    covariance: array[float64, 36] = field(default_factory=lambda: [0.0] * 36)


@dataclass
class PoseWithCovarianceStamped(IdlStruct, typename="geometry_msgs/msg/PoseWithCovarianceStamped"):
    header: Header = field(default_factory=Header)
    pose: PoseWithCovariance = field(default_factory=PoseWithCovariance)


@dataclass
class UUID(IdlStruct, typename="unique_identifier_msgs/msg/UUID"):
    uuid: array[uint8, 16] = field(default_factory=lambda: bytes(16))


@dataclass
class NavigateToPose_Goal(IdlStruct, typename="nav2_msgs/action/NavigateToPose_Goal"):
    pose: PoseStamped = field(default_factory=PoseStamped)
    behavior_tree: str = ""


@dataclass
class NavigateToPose_Result(IdlStruct, typename="nav2_msgs/action/NavigateToPose_Result"):
    error_code: uint16 = 0
    error_msg: str = ""


@dataclass
class NavigateToPose_Feedback(IdlStruct, typename="nav2_msgs/action/NavigateToPose_Feedback"):
    current_pose: PoseStamped = field(default_factory=PoseStamped)
    navigation_time: Duration = field(default_factory=Duration)
    estimated_time_remaining: Duration = field(default_factory=Duration)
    number_of_recoveries: int16 = 0
    distance_remaining: float32 = 0.0


@dataclass
class NavigateToPose_SendGoal_Request(IdlStruct, typename="nav2_msgs/action/NavigateToPose_SendGoal_Request"):
    goal_id: UUID = field(default_factory=UUID)
    goal: NavigateToPose_Goal = field(default_factory=NavigateToPose_Goal)


@dataclass
class NavigateToPose_SendGoal_Response(IdlStruct, typename="nav2_msgs/action/NavigateToPose_SendGoal_Response"):
    accepted: bool = False
    stamp: Time = field(default_factory=Time)


@dataclass
class NavigateToPose_GetResult_Request(IdlStruct, typename="nav2_msgs/action/NavigateToPose_GetResult_Request"):
    goal_id: UUID = field(default_factory=UUID)


@dataclass
class NavigateToPose_GetResult_Response(IdlStruct, typename="nav2_msgs/action/NavigateToPose_GetResult_Response"):
    status: int8 = STATUS_UNKNOWN
    result: NavigateToPose_Result = field(default_factory=NavigateToPose_Result)


@dataclass
class NavigateToPose_FeedbackMessage(IdlStruct, typename="nav2_msgs/action/NavigateToPose_FeedbackMessage"):
    goal_id: UUID = field(default_factory=UUID)
    feedback: NavigateToPose_Feedback = field(default_factory=NavigateToPose_Feedback)


@dataclass
class GoalInfo(IdlStruct, typename="action_msgs/msg/GoalInfo"):
    goal_id: UUID = field(default_factory=UUID)
    stamp: Time = field(default_factory=Time)


@dataclass
class CancelGoal_Request(IdlStruct, typename="action_msgs/srv/CancelGoal_Request"):
    goal_info: GoalInfo = field(default_factory=GoalInfo)


@dataclass
class CancelGoal_Response(IdlStruct, typename="action_msgs/srv/CancelGoal_Response"):
    return_code: int8 = 0
    goals_canceling: sequence[GoalInfo] = field(default_factory=list)
