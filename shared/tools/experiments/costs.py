"""What the experiments' jobs are expected to cost, in seconds on one core: a team's training
(``train_cost``) and a cell's evaluation (``cell_cost``), for the runner's ETA and `--plan`'s
estimate, never for results."""

from __future__ import annotations

from typing import Any

from shared.tools.experiments.budget import FULL, PLANNERS

# Training: ms per episode on one core, OFFICE at N = 4; MUSEUM's cost is TRAIN_MAP_COST times
# OFFICE's, and N robots cost sqrt(4 / N) times N = 4's (fewer robots, longer episodes: CE-PG at
# N = 1 and 2 cost 1.9 and 1.2 times N = 4; the baselines' N = 1 teams 1.7 to 3.6 times). The rates
# are calibrated against the committed cache's 159 teams, trained on a 2-core x86 VM (wall_seconds
# in training_summary.json, mostly run beside one other job, so a job's share of a busy machine):
# each rate is the geometric mean of its teams' measured / estimated time on each map
# (`python benchmarks/protocol_remaining.py --calibrate`, which should print about 1 for every
# row; single teams lie within 0.25 to 2.7 times their estimate, CE-PG's short runs the most).
# Planners, seconds per team step: MILP at its 1 s limit (every solve at N >= 2 reaches it;
# 0.6 s at N = 1), D-MILP one such solve per robot (0.6 s a step at N = 1, 3.0-3.8 s at N = 4),
# FHPE-SA about 5 ms per robot on OFFICE (7.5 / 9 / 12 / 14 / 24 ms a step at N = 1..5) and FHPE,
# which searches the joint paths, 0.5 / 1.0 / 11 ms a step at N = 1 / 2 / 3 (fig8 OFFICE and the
# cache's wall_seconds / team_steps; FHPE runs at N <= 3 only); MUSEUM's planner steps cost
# MAP_COST times OFFICE's (FHPE-SA at N = 4: 36 against 14 ms; FHPE not measured there); episodes
# of about 8 steps on OFFICE and 17 on MUSEUM at N = 4, 4 / N times that for N robots.
# Both cost as many steps as the episodes take, and a sensor that misses the target with
# probability eta_fn stretches them by about 1 / (1 - eta_fn) (each detection chance succeeds with
# 1 - eta_fn): the cache's OFFICE teams trained under eta_fn 0.1 / 0.3 / 0.5 took 1.08-1.10 /
# 1.34-1.38 / 1.76-1.98 times eta_fn 0's steps per episode (CE-PG, MASAC, MAPPO), against 1.11 /
# 1.43 / 2; D-MILP's 30 episodes there averaged 8.9 / 11.2 / 14.0 steps.
TRAIN_MS_PER_EPISODE = {"cepg": 0.19, "mappo": 1.24, "maddpg": 5.3, "masac": 6.0, "facmac": 5.35, "mambpo": 8.2}
TRAIN_MAP_COST = {"museum": {"cepg": 2.4, "mappo": 3.0, "maddpg": 2.5, "masac": 3.6, "facmac": 2.6, "mambpo": 3.0}}
MAP_COST = {"office": 1.0, "museum": 2.5}  # a planner's (below), and a method's without its own above
STEPS_AT_N4 = {"office": 8.0, "museum": 17.0}
FHPE_SECONDS_PER_STEP = {1: 0.001, 2: 0.002, 3: 0.015}  # by N; beyond N = 3 (not run) the joint search explodes


def miss_stretch(eta_fn: float) -> float:
    """How much longer episodes get when the sensor misses with probability ``eta_fn``
    (see TRAIN_MS_PER_EPISODE); at most 10x: a sensor that never detects runs every episode to
    T_max, a bounded length, where 1 / (1 - eta_fn) would be infinite."""
    return 1.0 / (1.0 - min(float(eta_fn), 0.9))


def train_cost(method: str, env: str, robots: int, episodes: int, eta_fn: float = 0.0) -> float:
    """A team's expected training time in seconds on one core (see TRAIN_MS_PER_EPISODE)."""
    per = TRAIN_MS_PER_EPISODE.get(method, TRAIN_MS_PER_EPISODE["cepg"]) / 1000
    per_map = TRAIN_MAP_COST.get(env, {}).get(method, MAP_COST.get(env, 1.0))
    return episodes * per * per_map * (4 / robots) ** 0.5 * miss_stretch(eta_fn)


def cell_cost(method: str, args: dict[str, Any], make: Any = None) -> float:
    """A cell's expected time in seconds on one core (see TRAIN_MS_PER_EPISODE): a planner's
    decisions (at the MILP time limit ``make``, a ``Reference``, passes it; else the protocol's),
    or a learned team's batched episodes (and its decision timing with ``latency``)."""
    steps = args["episodes"] * STEPS_AT_N4.get(args["env"], 10.0) * 4 / args["robots"]
    steps *= miss_stretch(args["sensor"]["eta_fn"])
    if method in PLANNERS:
        limit = dict(getattr(make, "kw", ())).get("time_limit", FULL.milp_limit)
        return steps * planner_step_cost(method, args["env"], args["robots"], limit)
    return steps * 2e-4 + (20.0 if args.get("latency") else 0.0)


def planner_step_cost(method: str, env: str, robots: int, time_limit: float = FULL.milp_limit) -> float:
    """A planner's seconds per team step on one core (see TRAIN_MS_PER_EPISODE); ``time_limit``
    the MILP planners' seconds per solve."""
    if method == "milp":
        return time_limit  # every solve reaches it at N >= 2
    if method == "d-milp":
        return time_limit * robots  # one solve per robot
    per_map = MAP_COST.get(env, 1.0)
    if method == "fhpe-sa":
        return 0.005 * robots * per_map
    return FHPE_SECONDS_PER_STEP.get(robots, 1.0) * per_map


def duration(seconds: float) -> str:
    """A duration as a reader takes it in: seconds, minutes or hours."""
    if seconds >= 360:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 60:.0f} min" if seconds >= 60 else f"{seconds:.0f} s"
