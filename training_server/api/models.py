"""The REST API's models (docs/SPEC.md section 9): requests, responses and the one error schema.

Requests are strict (no "5000" or 5.5 for an integer, no true for a number, no NaN or infinity;
5.0 is the integer 5, as in JSON Schema) and refuse unknown fields. Responses are the models
below, so the OpenAPI document describes exactly what the server sends.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from shared.core.records import ID_RE, MAX_MISSION_ROBOTS
from training_server.jobs import INTEGRAL, TrainingParams

RobotId = Annotated[str, Field(pattern=ID_RE.pattern, description="1-128 characters of A-Z a-z 0-9 _ . -")]
# the largest integer a request may carry (ids, seeds, versions): 2^53 - 1, the largest that JSON
# clients holding numbers as doubles (JavaScript, schema validators) hold exactly, so that a client
# and the server agree on which values are in range; the database's own limit (2^63 - 1) is above
MAX_ID = 2**53 - 1
MAX_MISSION_STEPS = 100_000  # a mission's step limit at most (the default guard under a time limit)
# a mission's durations (its time limit, its wall-clock timeout): finite seconds, more than 0, a week at most
MissionSeconds = Annotated[float, Field(gt=0, le=7 * 24 * 3600, allow_inf_nan=False)]


class Error(BaseModel):
    """Every 4xx and 5xx body."""

    error: str = Field(description="what is wrong, in one line")


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)


# ---------------------------------------------------------------------- health, map, fleet
class Health(BaseModel):
    status: Literal["ok"]
    version: str
    fleet: str
    graph_id: str
    current_policy: int
    uptime_s: float


class MapOut(BaseModel):
    """The map in the graph-file format (docs/SPEC.md section 7) with its graph_id."""

    name: str
    start_node: int
    nodes: list[int]
    edges: list[list[int]]
    positions: dict[str, list[float]] | None = None
    sensing: dict[str, list[int]] | None = None
    edge_lengths_m: list[float] | None = Field(
        None, description="each edge's length along free space in metres, in the order of edges (imported maps)"
    )
    graph_id: str


class MapImage(BaseModel):
    url: str = Field(description="the PNG (GET, with a fleet token)")
    x: float = Field(description="its left edge, in the layout's coordinates")
    y: float = Field(description="its top edge, in the layout's coordinates (y down)")
    width: float
    height: float


class MapLayout(BaseModel):
    positions: dict[str, list[float]] = Field(description="node label -> [x, y] in [0, 1], y down (screen)")
    source: Literal["file", "automatic"] = Field(description="the graph file's positions, or a force-directed layout")
    image: MapImage | None = Field(
        None, description="where to draw the building's map under the nodes (training-server --map-image); null: none"
    )


class Agent(BaseModel):
    robot_id: str
    online: bool = Field(description="its liveliness token is declared now; false: it dropped off")
    since: float | None = Field(description="when its liveliness token appeared (Unix time); null when offline")
    last_seen: float = Field(description="when it was last heard of (token or telemetry, Unix time)")
    state: Literal["flying", "idle", "offline", "revoked"] = Field(
        description="flying: a running mission awaits its record; idle: online and free; revoked: its credentials "
        "were taken away (training-server robots revoke)"
    )
    mission_id: str | None = Field(None, description="the running mission it is flying")
    step: int | None = Field(None, description="its last reported step t in that mission (telemetry)")
    node: int | None = Field(None, description="its last reported node (telemetry)")
    policy_version: int | None = Field(None, description="the policy version it last reported running (telemetry)")
    revoked: float | None = Field(None, description="when its credentials were revoked (Unix time)")
    z: int | None = Field(None, description="its last observation z_t in that mission (1: it detected the target)")
    mode: Literal["team", "partial", "own"] | None = Field(
        None,
        description="how it decided its last step (telemetry): on the team's plan with every teammate's step in, "
        "on it with one missing, or on its own policy (docs/coordination.md)",
    )
    backend: str | None = Field(None, description="its robot backend (sim, or MODULE:CLASS), from its telemetry")
    speed: float | None = Field(
        None,
        description="its speed in m/s when it flies on the mission clock (telemetry; docs/continuous-world.md); "
        "null: on the step index, or not said",
    )
    down_reason: str | None = Field(
        None, description="why its agent stopped, when it stopped on an error it cannot retry (e.g. its backend)"
    )
    last_failure: dict[str, str] | None = Field(
        None,
        description="the last mission it withdrew from and why ({mission_id, reason}: its backend failed), "
        "while it is idle; null when its last missions went well",
    )


class FleetOut(BaseModel):
    fleet: str
    online: int
    agents: list[Agent] = Field(description="every robot heard of since the server started, online or not")


class WhoAmI(BaseModel):
    role: Literal["operator", "agent"] = Field(description="operator: may act; agent: reads only")
    who: str = Field(description='"operator", "agent" or "robot:<id>" (a robot\'s own token)')


class Alert(BaseModel):
    kind: Literal["robot-lost", "run-failed", "run-gated-out", "ingest-rejections", "detection", "canary-rolled-back"]
    level: Literal["warning", "error"]
    subject: str = Field(description="the robot, the training run, 'ingest', or the detection's id")
    since: float | None = Field(description="Unix time it began")
    text: str


class AlertList(BaseModel):
    items: list[Alert]


# ---------------------------------------------------------------------- missions
class MissionRequest(_Request):
    robots: list[RobotId] | None = Field(
        default=None,
        description="robot ids to fly, each once (default: every agent online)",
        min_length=1,
        max_length=MAX_MISSION_ROBOTS,
        json_schema_extra={"uniqueItems": True},
    )
    seed: Annotated[int, Field(ge=0, le=MAX_ID), INTEGRAL] | None = Field(
        default=None, description="mission seed (agents' and simulated world's randomness)"
    )
    max_steps: Annotated[int, Field(ge=1, le=MAX_MISSION_STEPS), INTEGRAL] | None = Field(
        default=None, description="step limit (default 3n; with max_seconds, 100000: a guard only)"
    )
    max_seconds: MissionSeconds | None = Field(
        default=None,
        description="time limit on the mission clock, seconds: each robot stops at its first reading at or past it "
        "(robots on the mission clock; docs/continuous-world.md). Default, when max_steps is not given either and "
        "a robot's telemetry says it flies on the clock: 3 n moves of the map's median edge at the slowest such "
        "robot's speed; otherwise none (the step limit alone)",
    )
    timeout_s: MissionSeconds | None = Field(
        default=None,
        description="end the mission if it still runs after this long (default and upper bound: the server's "
        "--mission-timeout)",
    )
    mission_id: str | None = Field(default=None, pattern=ID_RE.pattern, description="default: generated")
    capture: Literal["auto", "confirm"] | None = Field(
        default=None,
        description="what a robot's detection does: auto ends the mission as captured, confirm waits for an "
        "operator to confirm or dismiss it (default: the server's --capture)",
    )


class MissionParams(BaseModel):
    seed: int
    max_steps: int
    max_seconds: float | None = Field(default=None, description="the time limit on the mission clock, if any")
    start_node: int
    capture: Literal["auto", "confirm"] | None = Field(
        default=None, description="how detections end this mission (None: a mission from before capture modes)"
    )
    canary: dict[str, Any] | None = Field(
        default=None,
        description="flown while a new version was on trial: {arm: baseline|canary, pair, canary_version}; "
        "the canary arm of a pair repeats its baseline mission's seed",
    )


class Detection(BaseModel):
    """A robot's z = 1 during a mission, and what became of it."""

    id: int
    mission_id: str
    robot_id: str
    t: int = Field(description="the step of the reading")
    node: int = Field(description="the node the robot read it on")
    received: float = Field(description="when the server received it (Unix time)")
    status: Literal["pending", "confirmed", "dismissed", "closed"] = Field(
        description="pending: awaits an operator; confirmed: it ended the mission as captured; dismissed: a false "
        "alarm, the search went on; closed: the mission ended otherwise first (under capture auto: another "
        "detection, earlier or of a robot listed first, ended it)"
    )
    decided: float | None
    decided_by: str | None = Field(description="auto (the server's --capture auto) or who decided")


class DetectionList(BaseModel):
    items: list[Detection]


class Withdrawal(BaseModel):
    steps: int = Field(description="steps the robot flew before it left (0: it failed before its first reading)")
    reason: str = Field(description="why, as the robot's agent reported it")
    at: float = Field(description="when the server heard of it (Unix time)")


class Mission(BaseModel):
    id: str
    status: Literal["running", "captured", "stopped", "timed-out", "completed"]
    robots: list[str]
    params: MissionParams
    policy_version: int | None
    created: float
    ended: float | None
    deadline: float | None = Field(description="when it times out if still running (Unix time; None: never)")
    event: dict[str, Any] | None = Field(description="the captured, stop or timeout message that ended it")
    episodes_received: list[str]
    withdrawn: dict[str, Withdrawal] = Field(
        default_factory=dict,
        description="robots that left it because they could not go on (their backend failed), by robot id",
    )
    outcome: dict[str, Any] | None = Field(
        description="from the records received: captured, capture_time, steps, policy_versions, captured_by, and "
        "capture_time_s (seconds on the mission clock) where the capturing robot flew on it"
    )


class MissionList(BaseModel):
    items: list[Mission]
    total: int = Field(description="missions in all (page with ?offset=)")


class RobotReplay(BaseModel):
    policy_version: int | None
    steps: list[Step] = Field(description="as recorded")
    belief: list[list[float]] | None = Field(
        description="b_t after each step, n floats in the map's node order; null when its policy version is gone"
    )


class MissionReplay(BaseModel):  # (RobotReplay is rebuilt below, after Step)
    mission: Mission
    nodes: list[int] = Field(description="the map's node labels, the order of every belief")
    robots: dict[str, RobotReplay]
    team_belief: list[list[float]] | None = Field(
        None,
        description="the team's collective belief b^c_t after each step, from every robot's record (Eq. 6-7: what a "
        "robot whose links delivered every teammate's observation held), n floats in the map's node order; null for "
        "a robot alone or when the version flown is gone",
    )


# ---------------------------------------------------------------------- episodes
class EpisodeSummary(BaseModel):
    id: int
    robot_id: str
    mission_id: str
    policy_version: int | None
    steps: int
    captured: bool
    capture_time: int | None
    received: float
    set_aside: str | None = Field(
        default=None,
        description="why no path of the target explains this record under its sensor model: kept, but never "
        "used to estimate the model (None: usable)",
    )


class EpisodePage(BaseModel):
    items: list[EpisodeSummary]
    next_after: int | None = Field(description="pass as ?after= for the next page; null on the last page")


class EpisodeStats(BaseModel):
    stored: int
    rejected: dict[str, int] = Field(description="rejected records by reason")
    set_aside: dict[str, int] = Field(
        default_factory=dict, description="records stored but set aside from estimation, by reason"
    )
    missions: int
    usable_missions: int = Field(default=0, description="missions with at least one record that is not set aside")
    by_policy_version: dict[str, int]


class Step(BaseModel):
    t: int
    node: int
    z: int
    time_s: float | None = Field(
        None, description="the reading's time on the mission clock, seconds (records of robots on the clock)"
    )


class Outcome(BaseModel):
    captured: bool
    capture_time: int | None = None
    captured_by: str | None = None


class Coordination(BaseModel):
    team_searcher: str | None = Field(description="the version's team searcher (null: none, the robot searched alone)")
    team_steps: int = Field(description="decisions on the team's plan, every live teammate's step in")
    partial_steps: int = Field(0, description="decisions on the team's plan with a teammate's step missing")
    own_steps: int = Field(description="decisions on the robot's own policy (no teammate heard, or no team searcher)")
    observations_heard: int | None = Field(
        None, description="teammates' observations its links delivered in time for its decision at their step"
    )
    observations_sent: int | None = Field(
        None, description="teammates' observations sent to it (each teammate's up to its latest step heard)"
    )
    teammates_dropped: int | None = Field(
        None, description="teammates whose liveliness went during the mission (withdrawn from its team)"
    )
    flown_for: int | None = Field(
        None, description="the team size its own policy was built for at the mission's end (the robots left)"
    )


class EpisodeRecord(BaseModel):
    """The episode record as stored (docs/SPEC.md section 5)."""

    schema_: str = Field(alias="schema", serialization_alias="schema")
    fleet: str
    mission_id: str
    robot_id: str
    graph_id: str
    policy_version: int | None
    sensor: dict[str, Any]
    steps: list[Step]
    outcome: Outcome
    coordination: Coordination | None = Field(
        None, description="how the robot searched: steps on its team's plan and on its own policy (agents that team)"
    )


# ---------------------------------------------------------------------- policies
class PromoteRequest(_Request):
    version: Annotated[int, Field(ge=1, le=MAX_ID), INTEGRAL]


class PolicyVersion(BaseModel):
    version: int
    created: float
    sha256: str = Field(description="of the artifact (the tar agents download); also its ETag")
    bytes: int
    parent: int | None
    run_id: str | None
    meta: dict[str, Any] = Field(description="graph_id, robots, variant, algorithm, beta, sensor, training, metrics")
    current: bool
    artifact: str


class TargetModelOut(BaseModel):
    """A version's estimated target model (Gamma_hat, b0), learned by EM from the fleet's records."""

    version: int
    nodes: list[int]
    b0: list[float] = Field(description="initial target distribution, in the order of nodes")
    moves: dict[str, dict[str, float]] = Field(description="Gamma_hat: node -> {next node: probability}")
    stationary: list[float] = Field(
        description="where the target tends to be in the long run (Gamma_hat's fixed point)"
    )


class VersionPerformance(BaseModel):
    version: int
    missions: int = Field(description="missions counted: captured, or ended at their step limit")
    captured: int
    mean_capture_time: float | None = Field(description="mean over the missions counted (a miss counts its step limit)")
    ci95: float | None = Field(description="half-width of the 95 % CI of that mean (normal approximation)")
    missions_on_clock: int = Field(0, description="of the missions counted, those flown on the mission clock")
    mean_capture_time_s: float | None = Field(
        None,
        description="mean capture time in seconds over the missions on the clock (a miss counts its last reading's "
        "time); null when none was",
    )
    ci95_s: float | None = Field(None, description="half-width of the 95 % CI of that mean, seconds")


class PerformanceOut(BaseModel):
    items: list[VersionPerformance]
    excluded: int = Field(description="missions not counted: stopped, timed out, or flown with mixed versions")


class PolicyList(BaseModel):
    current: int
    items: list[PolicyVersion]


# ---------------------------------------------------------------------- training runs
class TrainingRun(BaseModel):
    id: str
    created: float
    started: float | None
    finished: float | None
    status: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    params: TrainingParams
    progress: dict[str, Any] | None
    metrics: dict[str, Any] | None
    version: int | None = Field(description="the policy version it published")
    error: str | None = Field(description="why it failed or was gated out")
    cancel_requested: float | None = Field(None, description="when an operator asked to cancel it")


class TrainingRunList(BaseModel):
    items: list[TrainingRun]


RobotReplay.model_rebuild()
MissionReplay.model_rebuild()
