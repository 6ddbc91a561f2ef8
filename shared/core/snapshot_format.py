"""Policy snapshots in numpy (docs/SPEC.md section 8): the format, reading and writing, and one
robot's decision step. No torch here: this is what a robot agent loads and runs.

A snapshot is a directory:

    weights.safetensors    the N networks' parameters as float32 tensors (w_pos, w_bel, b1, w2, b2;
                           shapes in ``param_shapes``), safetensors format
    policy.json            metadata (``format`` "mures.policy/1"): graph_id, node labels in row
                           order, n, robots, hidden, variant, algorithm (the training method;
                           absent in older snapshots: cepg), beta, the belief model the robots use
                           (Gamma_hat, b0, as model.json), the sensor, the training config and seed,
                           the weights file with its sha256, and the training summary
    training_summary.json  the training summary alone

Reading checks the format, the graph_id against the map in use, the node order, every tensor's
shape and the weights' sha256, and fails with a ``SnapshotError`` naming the mismatch. Writing
goes to a temporary directory beside the target, renamed into place, so a reader (or a crash
half-way) never sees a half-written snapshot.

Snapshots written before this format hold ``weights.pt`` (torch's format). ``read_snapshot``
takes a ``legacy`` reader for those (shared/learning/team_snapshot.py passes torch's); without one it
says how to convert the snapshot.

A snapshot may also hold teams trained for other team sizes k (``teams`` in policy.json, each
its own weights file ``team-<k>.safetensors`` with the same tensors for k networks, checked as
the main one is): a mission of k robots flies the team built for k where there is one
(``team_for``), and its robots switch to the team for the robots left when a teammate drops out.

Running a team of k robots on a snapshot with no team for k: robot i runs network i of the main
team (N networks) for k <= N; for k > N robot i runs network i mod N, and ``team_note`` says so.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from safetensors.numpy import load as load_safetensors
from safetensors.numpy import save as save_safetensors

from shared.core.belief_filter import BeliefFilter
from shared.core.choices import ALGORITHMS, TEAM_SEARCHERS, VARIANTS
from shared.core.files import atomic_write
from shared.core.graph import Graph
from shared.core.graph_policy import FEATURE_COUNTS, FEATURES, NODE_BIAS, SCALES, GeneralAgent, draw, feature_count
from shared.core.graph_policy import PARAMS as GENERAL_PARAMS
from shared.core.graph_policy import param_shapes as general_shapes
from shared.core.models import ModelError, Sensor, TargetModel, from_matrix, uniform_walk

FORMAT = "mures.policy/1"
WEIGHTS = "weights.safetensors"
LEGACY_WEIGHTS = "weights.pt"
META = "policy.json"
SUMMARY = "training_summary.json"
PARAMS = ("w_pos", "w_bel", "b1", "w2", "b2")
MAX_TEAM = 64  # the largest team size a snapshot may hold a team for


GENERAL = "general"  # policy.json "architecture" of a snapshot that holds the general policy
GENERAL_FORMAT = "mures.general/1"  # a general policy on its own, for any building: general.json
GENERAL_META = "general.json"
GENERAL_WEIGHTS = "general.safetensors"


def team_file(k: int) -> str:
    """The weights file of a snapshot's team for ``k`` robots (beside the main team's)."""
    return f"team-{k}.safetensors"


Weights = dict[str, np.ndarray]


class SnapshotError(ValueError):
    """A snapshot cannot be loaded or does not fit the map in use; the message says why."""


def param_shapes(n: int, robots: int, hidden: int) -> dict[str, tuple[int, ...]]:
    """The parameter shapes of N = ``robots`` networks 2n -> H -> n (docs/SPEC.md section 8)."""
    N, H = robots, hidden
    return {"w_pos": (N, n, H), "w_bel": (N, n, H), "b1": (N, H), "w2": (N, H, n), "b2": (N, n)}


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass
class TeamInfo:
    """What every view of a snapshot holds (numpy here, torch in shared/learning/team_snapshot.py): its
    metadata, the robots' belief model (Gamma_hat, b0) and their sensor."""

    meta: dict[str, Any]
    model: TargetModel
    sensor: Sensor

    @property
    def variant(self) -> str:
        return str(self.meta["variant"])

    @property
    def robots(self) -> int:
        return int(self.meta["robots"])

    @property
    def general(self) -> bool:
        """The general policy (one network for any building and team size, shared/core/graph_policy.py)
        rather than N networks shaped by this map."""
        return self.meta.get("architecture") == GENERAL

    @property
    def clock(self) -> tuple[float, float] | None:
        """(speed m/s, tick s) of a team trained on the mission clock (`mures train --speed`), whose
        belief model is per tick; None for a team trained in steps, whose model is per step."""
        training = self.meta.get("training") or {}
        speed = training.get("speed")
        if not isinstance(speed, (int, float)) or isinstance(speed, bool):
            return None
        return float(speed), float(training.get("tick", 1.0))

    def network_for(self, robot: int) -> int:
        """The network robot ``robot`` runs (module docstring)."""
        return robot % self.robots

    def team_note(self, k: int) -> str | None:
        if k > self.robots and not self.general:
            return (
                f"snapshot trained for {self.robots} robots, running {k}: robot i runs network i mod {self.robots}, "
                "so some robots share a policy"
            )
        return None


@dataclass
class SnapshotData(TeamInfo):
    """A checked snapshot with its float32 weights (``param_shapes``) and those of its teams for
    other team sizes (``teams``: k -> weights of k networks)."""

    weights: Weights
    teams: dict[int, Weights] = field(default_factory=dict)

    @property
    def team_sizes(self) -> list[int]:
        """The team sizes this snapshot holds a team built for: its own N and its ``teams``."""
        return sorted({self.robots, *self.teams})

    def switches_to(self, k: int) -> bool:
        """Whether robots left k switch to the team built for k when teammates drop out
        mid-mission: the version holds one, and its ``switch_to`` (decided when it was trained)
        names k, or it has none (every team)."""
        if self.general:  # the same network, with the robots left as its team
            return k != self.robots
        listed = self.meta.get("switch_to")
        return k in self.teams and k != self.robots and (listed is None or k in listed)

    def team_for(self, k: int) -> SnapshotData:
        """The snapshot as flown by a mission of ``k`` robots: its team built for k where it holds
        one (meta's robots and hidden then k's), else itself (robot i on network i, or i mod N)."""
        if self.general and k != self.robots:  # every team size flies the one network, each robot with its role
            network = {name: w for name, w in self.weights.items() if name != NODE_BIAS}  # learned for N's roles
            return SnapshotData(meta={**self.meta, "robots": k, "flown_for": k}, model=self.model, sensor=self.sensor,
                                weights=network)  # fmt: skip
        weights = self.teams.get(k)
        if weights is None or k == self.robots:
            return self
        meta = {**self.meta, "robots": k, "hidden": int(weights["w_pos"].shape[2]), "flown_for": k}
        return SnapshotData(meta=meta, model=self.model, sensor=self.sensor, weights=weights)


def write_snapshot(
    path: str | Path,
    graph: Graph,
    weights: Weights,
    model: TargetModel,
    sensor: Sensor,
    variant: str,
    beta: list[float],
    config: dict[str, Any],
    summary: dict[str, Any],
    algorithm: str = "cepg",
    team_searcher: str | None = None,
    teams: dict[int, Weights] | None = None,
    switch_to: list[int] | None = None,
    robots: int | None = None,
) -> Path:
    """Write a snapshot directory atomically (an existing one at ``path`` is replaced).
    ``algorithm`` names the method that trained the team (ALGORITHMS); every one runs the same way.
    ``team_searcher`` ("fhpe-sa", "c-cepg" or "none"; shared/core/team.py) is what its robots fly
    together when their links allow; without one, a c-cepg team flies c-cepg and the others none.
    ``teams``: the weights of teams built for other team sizes k (k networks each), flown by
    missions of k robots (``SnapshotData.team_for``); ``switch_to``: the sizes among them that
    robots left switch to when teammates drop out mid-mission (None: every one). ``weights`` of the
    general policy (``GENERAL_PARAMS``) make a snapshot of architecture "general" flown by ``robots``
    robots (any team size flies it; it holds no teams)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}")
    if algorithm not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algorithm!r}")
    names: tuple[str, ...]
    general = set(GENERAL_PARAMS) <= set(weights) <= {*GENERAL_PARAMS, NODE_BIAS}
    if general:
        if teams or robots is None:
            raise ValueError("a general policy's snapshot names its robots and holds no teams (it flies every size)")
        hidden = int(weights["b1"].shape[0])
        names = _check_general(weights, hidden, robots, graph.n, str(path))
    else:
        robots, n, hidden = weights["w_pos"].shape
        names = PARAMS
        _check_shapes(weights, param_shapes(n, robots, hidden), str(path))
    blobs = {}
    for k, team in sorted((teams or {}).items()):
        if not 1 <= k <= MAX_TEAM or k == robots:
            raise ValueError(f"team size {k}: expected 1..{MAX_TEAM}, other than the main team's {robots}")
        _check_shapes(team, param_shapes(n, k, team["w_pos"].shape[2]), f"{path} team {k}")
        blobs[k] = save_safetensors({name: np.ascontiguousarray(team[name], dtype=np.float32) for name in PARAMS})
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = save_safetensors({k: np.ascontiguousarray(weights[k], dtype=np.float32) for k in names})
    meta: dict[str, Any] = {
        "format": FORMAT,
        "graph_id": graph.graph_id,
        "map": graph.name,
        "nodes": [int(x) for x in graph.labels],
        "n": graph.n,
        "robots": int(robots),
        "hidden": int(hidden),
        "variant": variant,
        "algorithm": algorithm,
        "beta": [float(b) for b in beta],
        "model": {**model.to_json(graph), "kind": model.kind},
        "sensor": sensor.to_json(),
        "training": config,
        "seed": config.get("seed"),
        "weights": {"file": WEIGHTS, "sha256": sha256_hex(blob), "bytes": len(blob)},
        "summary": summary,
    }
    if general:
        meta["architecture"] = GENERAL
    if blobs:
        meta["teams"] = {
            str(k): {
                "file": team_file(k),
                "sha256": sha256_hex(b),
                "bytes": len(b),
                "hidden": int((teams or {})[k]["w_pos"].shape[2]),
            }
            for k, b in blobs.items()
        }
    if switch_to is not None:
        if not set(switch_to) <= set(blobs):
            raise ValueError(f"switch_to {sorted(switch_to)}: a team size the snapshot holds no team for")
        meta["switch_to"] = sorted(int(k) for k in switch_to)
    if team_searcher is not None:
        if team_searcher not in (*TEAM_SEARCHERS, "none"):
            raise ValueError(f"unknown team searcher {team_searcher!r}")
        meta["team_searcher"] = team_searcher
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        atomic_write(tmp / WEIGHTS, blob)
        for k, b in blobs.items():
            atomic_write(tmp / team_file(k), b)
        atomic_write(tmp / META, json.dumps(meta, indent=1) + "\n")
        atomic_write(tmp / SUMMARY, json.dumps(summary, indent=1) + "\n")
        if path.exists():
            old = path.with_name(f".{path.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return path


def read_meta(path: str | Path) -> dict[str, Any]:
    """policy.json of a snapshot directory, with its format and required fields checked."""
    path = Path(path)
    where = str(path)
    if not path.is_dir():
        raise SnapshotError(f"{where}: not a snapshot directory")
    try:
        meta = json.loads((path / META).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SnapshotError(f"{where}: no {META}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SnapshotError(f"{where}/{META}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise SnapshotError(f"{where}/{META}: format is {got!r}, expected {FORMAT!r}")
    for key in ("graph_id", "n", "robots", "hidden", "variant", "model", "sensor", "weights"):
        if key not in meta:
            raise SnapshotError(f"{where}/{META}: missing field {key!r}")
    if meta["variant"] not in VARIANTS:
        raise SnapshotError(f"{where}: unknown variant {meta['variant']!r}")
    if meta.get("architecture", GENERAL) != GENERAL:
        got = meta["architecture"]
        raise SnapshotError(f"{where}/{META}: unknown architecture {got!r} (expected {GENERAL!r} or none)")
    w = meta["weights"]
    if not isinstance(w, dict) or w.get("file", LEGACY_WEIGHTS) not in (WEIGHTS, LEGACY_WEIGHTS):
        raise SnapshotError(f"{where}/{META}: weights must name {WEIGHTS} (or the older {LEGACY_WEIGHTS})")
    return meta


def read_weights_blob(path: str | Path, meta: dict[str, Any]) -> tuple[str, bytes]:
    """(file name, bytes) of the weights file, its sha256 checked against the metadata."""
    name = meta["weights"].get("file", LEGACY_WEIGHTS)
    return name, _checked_file(Path(path), name, meta["weights"].get("sha256"))


def _checked_file(path: Path, name: str, sha256: Any) -> bytes:
    """The bytes of ``path``/``name``, their sha256 checked against the one policy.json gives."""
    try:
        raw = (path / name).read_bytes()
    except FileNotFoundError:
        raise SnapshotError(f"{path}: no {name}") from None
    if sha256_hex(raw) != sha256:
        raise SnapshotError(f"{path}/{name}: sha256 does not match {META} (corrupt or replaced file)")
    return raw


def read_snapshot(path: str | Path, graph: Graph, legacy: Callable[[bytes], Weights] | None = None) -> SnapshotData:
    """Load and check a snapshot for ``graph`` (module docstring)."""
    path = Path(path)
    where = str(path)
    meta = read_meta(path)
    if meta["graph_id"] != graph.graph_id:
        raise SnapshotError(
            f"{where}: trained on map {meta.get('map')!r} ({meta['graph_id']}), "
            f"not on {graph.name!r} ({graph.graph_id})"
        )
    if meta["n"] != graph.n or meta.get("nodes") != [int(x) for x in graph.labels]:
        raise SnapshotError(f"{where}: node list does not match map {graph.name!r} in row order")
    name, raw = read_weights_blob(path, meta)
    try:
        if name == WEIGHTS:
            weights = dict(load_safetensors(raw))
        elif legacy is not None:
            weights = legacy(raw)
        else:
            raise SnapshotError(
                f"{where}: weights are in the older torch format ({LEGACY_WEIGHTS}); "
                f"convert it with `mures snapshot convert {where}` (the training server converts its own)"
            )
    except SnapshotError:
        raise
    except Exception as exc:  # safetensors and torch raise several types for a bad file
        raise SnapshotError(f"{where}/{name}: cannot be read as weights ({exc})") from None
    general = meta.get("architecture") == GENERAL
    if general:
        names: tuple[str, ...] = _check_general(weights, int(meta["hidden"]), int(meta["robots"]), graph.n,
                                                f"{where}/{name}")  # fmt: skip
        if meta.get("teams"):
            raise SnapshotError(f"{where}/{META}: a general policy flies every team size itself and holds no teams")
    else:
        names = PARAMS
        _check_shapes(weights, param_shapes(graph.n, int(meta["robots"]), int(meta["hidden"])), f"{where}/{name}")
    try:
        m = meta["model"]
        model = from_matrix(graph, np.asarray(m["gamma"], dtype=np.float64), m["b0"], kind=m.get("kind", "matrix"))
        s = meta["sensor"]
        sensor = Sensor(float(s["eta_fn"]), float(s["eta_fp"]), str(s["detection"]))
    except (ModelError, KeyError, TypeError, ValueError) as exc:
        raise SnapshotError(f"{where}/{META}: bad belief model or sensor ({exc})") from None
    teams = _read_teams(path, meta, graph.n)
    listed = meta.get("switch_to")
    if listed is not None and (not isinstance(listed, list) or not set(listed) <= set(teams)):
        raise SnapshotError(f"{where}/{META}: switch_to must list team sizes the snapshot holds a team for")
    return SnapshotData(meta=meta, weights={k: weights[k] for k in names}, model=model, sensor=sensor, teams=teams)


def _read_teams(path: Path, meta: dict[str, Any], n: int) -> dict[int, Weights]:
    """The teams for other team sizes that policy.json lists, each file's sha256 and shapes checked."""
    listed = meta.get("teams", {})
    if not isinstance(listed, dict):
        raise SnapshotError(f"{path}/{META}: teams must be an object of team size -> weights file")
    teams: dict[int, Weights] = {}
    for key, entry in listed.items():
        k = int(key) if isinstance(key, str) and key.isdigit() else 0
        ok = isinstance(entry, dict) and entry.get("file") == team_file(k) and isinstance(entry.get("hidden"), int)
        if not 1 <= k <= MAX_TEAM or k == int(meta["robots"]) or not ok:
            raise SnapshotError(f"{path}/{META}: teams entry {key!r} is not a team size with its {team_file(k)}")
        where = f"{path}/{entry['file']}"
        raw = _checked_file(path, entry["file"], entry.get("sha256"))
        try:
            weights = dict(load_safetensors(raw))
        except Exception as exc:
            raise SnapshotError(f"{where}: cannot be read as weights ({exc})") from None
        _check_shapes(weights, param_shapes(n, k, entry["hidden"]), where)
        teams[k] = {name: weights[name] for name in PARAMS}
    return teams


def combine_teams(
    main: str | Path, others: list[str | Path], out: str | Path, graph: Graph, switch_to: list[int] | None = None
) -> tuple[SnapshotData, dict[str, float]]:
    """Write at ``out`` the snapshot ``main`` holding, besides its own team, the team of each of
    ``others`` (snapshots for other team sizes on the same map and sensor; `mures snapshot
    combine`); a SnapshotError names a snapshot that does not fit. The robots keep ``main``'s
    belief model whatever team they fly (a team trained with its own EM estimate flies on it).
    ``switch_to``: the team sizes robots left switch to mid-mission (None: every one held).
    Returns the snapshot written, and for each of ``others`` the largest gap between its belief
    model's Gamma_hat and ``main``'s."""
    base = read_snapshot(main, graph)
    teams = dict(base.teams)
    gaps = {}
    for where in others:
        other = read_snapshot(where, graph)
        k = other.robots
        if k == base.robots or k in teams:
            raise SnapshotError(f"{where}: a team for {k} robots is there already")
        if other.sensor != base.sensor:
            raise SnapshotError(f"{where}: its sensor differs from {main}'s")
        teams[k] = other.weights
        gaps[str(where)] = float(np.abs(other.model.dense() - base.model.dense()).max())
    m = base.meta
    write_snapshot(
        out,
        graph,
        base.weights,
        base.model,
        base.sensor,
        m["variant"],
        list(m.get("beta") or []),
        {**m.get("training", {}), "teams_from": [str(w) for w in others]},
        m.get("summary") or {},
        algorithm=m.get("algorithm", "cepg"),
        team_searcher=m.get("team_searcher"),
        teams=teams,
        switch_to=switch_to,
    )
    return read_snapshot(out, graph), gaps


def _check_general(weights: Any, hidden: int, robots: int, n: int, where: str) -> tuple[str, ...]:
    """A general snapshot's tensors: the network's (``general_shapes``) and, from a fine-tune on
    this map, ``NODE_BIAS`` of shape (robots, n). Returns their names; a SnapshotError names a bad one."""
    expected = general_shapes(hidden, feature_count(weights))
    if isinstance(weights, dict) and NODE_BIAS in weights:
        expected[NODE_BIAS] = (robots, n)
    _check_shapes(weights, expected, where)
    return tuple(expected)


def _check_shapes(weights: Any, expected: dict[str, tuple[int, ...]], where: str) -> None:
    if not isinstance(weights, dict) or set(weights) != set(expected):
        got = sorted(weights) if isinstance(weights, dict) else type(weights).__name__
        raise SnapshotError(f"{where}: expected tensors {sorted(expected)}, got {got}")
    for k, shape in expected.items():
        if tuple(weights[k].shape) != shape:
            raise SnapshotError(f"{where}: {k} has shape {tuple(weights[k].shape)}, expected {shape}")


class PolicyAgent:
    """One robot's decision loop in numpy (Algorithm 1), what the robot agent runs: its own belief
    filter (Eq. 1) and its own network, nothing from other robots. ``reset(p0, z0)`` at a mission's
    start, ``observe(p, z)`` for each later observation, then ``act(p)`` -> next node row.

    C-CE-PG needs the other robots' observations: it is refused here unless ``team`` (a
    ``TeamAgent`` gives it the collective belief, shared/core/team.py).
    """

    def __init__(
        self,
        snap: SnapshotData,
        graph: Graph,
        robot: int,
        seed: int = 0,
        greedy_actions: bool = False,
        team: bool = False,
    ) -> None:
        if snap.variant == "c-cepg" and not team:
            raise SnapshotError(
                "a c-cepg policy needs every robot's observations: fly it in a team (shared.core.team.TeamAgent)"
            )
        self.graph = graph
        self.filter = BeliefFilter(graph, snap.model, snap.sensor)
        self.rng = np.random.default_rng(seed)
        self.greedy_actions = greedy_actions
        self.belief: np.ndarray | None = None
        self.fly(snap, robot)

    def fly(self, snap: SnapshotData, robot: int) -> None:
        """Decide from now on with network ``snap.network_for(robot)`` of ``snap`` (a team of the
        same version for another team size: the belief, its model and the generator are kept)."""
        self.general: GeneralAgent | None = None
        if snap.general:  # one network: robot i of the snapshot's robots, with its role
            self.general = GeneralAgent(snap.weights, self.graph, robot % snap.robots, snap.robots, self.rng,
                                        self.greedy_actions)  # fmt: skip
            return
        k = snap.network_for(robot)
        W = {name: np.asarray(w[k], dtype=np.float64) for name, w in snap.weights.items()}
        self.w_pos, self.w_bel, self.b1 = W["w_pos"], W["w_bel"], W["b1"]  # (n, H), (n, H), (H,)
        self.w2, self.b2 = W["w2"], W["b2"]  # (H, n), (n,)

    def reset(self, p0: int, z0: int) -> None:
        """b_0 ∝ Lambda(p_0, z_0) b0 (Theorem 1 at t = 0)."""
        self.belief = self.filter.reset(p0, z0)

    def observe(self, p: int, z: int, ticks: int = 1) -> None:
        """Eq. 1: b_t ∝ Lambda(p_t, z_t) Gamma_hat^T b_{t-1}; a team trained on the clock (model per
        tick) predicts the ``ticks`` since the last reading."""
        self.belief = self.filter.update(p, z, ticks)

    def act(self, p: int, belief: np.ndarray | None = None, mates: np.ndarray | None = None) -> int:
        """Next node row from N[p] for the robot's own belief (or ``belief``, a team's collective
        one): a ~ pi_i(. | onehot(p), b) (Algorithm 1, line 3). The general policy also reads
        ``mates``, the teammates' latest known node rows (the per-map networks read no teammate)."""
        b = self.belief if belief is None else belief
        assert b is not None, "reset() first"
        if self.general is not None:
            return self.general.act(p, b, mates)
        nbrs = self.graph.closed(p)
        h = np.maximum(self.w_pos[p] + b @ self.w_bel + self.b1, 0.0)
        return draw(nbrs, h @ self.w2[:, nbrs] + self.b2[nbrs], self.rng, self.greedy_actions)


@dataclass
class GeneralPolicy:
    """The general policy on its own (no map, no model; docs/SPEC.md section 8): its float32 weights
    (shared/core/graph_policy.py ``param_shapes``) and general.json's metadata (training command,
    configuration, pool, learning curve)."""

    weights: Weights
    meta: dict[str, Any]

    @property
    def hidden(self) -> int:
        return int(self.weights["b1"].shape[0])


def save_general(path: str | Path, weights: Weights, meta: dict[str, Any]) -> Path:
    """Write a general policy directory (``GENERAL_META`` beside ``GENERAL_WEIGHTS``), each file atomically."""
    out = Path(path)
    out.mkdir(parents=True, exist_ok=True)
    blob = save_safetensors({k: np.ascontiguousarray(weights[k], dtype=np.float32) for k in GENERAL_PARAMS})
    full = {
        **meta,
        "format": GENERAL_FORMAT,
        "features": list(FEATURES[: feature_count(weights)]),
        "scales": list(SCALES),
        "hidden": int(weights["b1"].shape[0]),
        "weights": {"file": GENERAL_WEIGHTS, "sha256": sha256_hex(blob), "bytes": len(blob)},
    }
    atomic_write(out / GENERAL_WEIGHTS, blob)
    atomic_write(out / GENERAL_META, json.dumps(full, indent=1) + "\n")
    return out


def load_general(path: str | Path) -> GeneralPolicy:
    """Read and check a general policy directory; a ``SnapshotError`` names what is wrong."""
    where = Path(path)
    try:
        meta = json.loads((where / GENERAL_META).read_text(encoding="utf-8"))
    except OSError as exc:
        raise SnapshotError(f"{where}: no general policy here ({GENERAL_META}: {exc.strerror or exc})") from None
    except ValueError as exc:
        raise SnapshotError(f"{where / GENERAL_META}: not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or meta.get("format") != GENERAL_FORMAT:
        got = meta.get("format") if isinstance(meta, dict) else type(meta).__name__
        raise SnapshotError(f"{where / GENERAL_META}: expected format {GENERAL_FORMAT!r}, got {got!r}")
    features = meta.get("features")
    known = [list(FEATURES[:k]) for k in FEATURE_COUNTS]
    if features not in known or meta.get("scales") != list(SCALES):
        raise SnapshotError(
            f"{where / GENERAL_META}: its features are not this version's ({', '.join(FEATURES)}, "
            f"or all but the last {FEATURE_COUNTS[1] - FEATURE_COUNTS[0]})"
        )
    hidden = meta.get("hidden")
    if not isinstance(hidden, int) or isinstance(hidden, bool) or hidden < 1:
        raise SnapshotError(f"{where / GENERAL_META}: hidden must be a positive integer, got {hidden!r}")
    raw = _checked_file(where, GENERAL_WEIGHTS, (meta.get("weights") or {}).get("sha256"))
    try:
        weights = dict(load_safetensors(raw))
    except Exception as exc:  # safetensors raises several types for a bad file
        raise SnapshotError(f"{where / GENERAL_WEIGHTS}: cannot be read as weights ({exc})") from None
    _check_shapes(weights, general_shapes(hidden, len(features)), str(where / GENERAL_WEIGHTS))
    return GeneralPolicy(weights, meta)


def shipped_general_path() -> Path:
    """The general policy shipped with the project (trained by `mures train-general`)."""
    return Path(__file__).resolve().parent / "policies" / "general"


GENERAL_TEAM_SEARCHER = "fhpe-sa"  # a fleet's first version plans together (docs/general-policy.md)


def write_general_version(
    path: str | Path, graph: Graph, sensor: Sensor, robots: int, seed: int, summary: dict[str, Any]
) -> Path:
    """The shipped general policy bound to ``graph`` as a snapshot at ``path``, as a training
    server's first version: beliefs on the uniform walk until EM has learned a model, FHPE-SA as its
    team searcher (the team's plan on every observation heard; the network where links fail), flown
    by ``robots`` robots (any team size flies it). ``summary`` is added to the snapshot's summary."""
    general = load_general(shipped_general_path())
    return write_snapshot(  # its weights as they are: nothing of the map (distances, masks) is built here
        path,
        graph,
        general.weights,
        uniform_walk(graph),
        sensor,
        "cepg",
        [1.0] * robots,
        {"episodes": 0, "seed": seed, "belief": "uniform walk", "map": graph.name, "general": True},
        {"episodes": 0, "note": "the general policy, not trained on this map",
         "general_training": general.meta.get("training", {}).get("command"), **summary},
        team_searcher=GENERAL_TEAM_SEARCHER,
        robots=robots,
    )  # fmt: skip
