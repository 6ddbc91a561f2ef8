"""Policy snapshots: what training writes and what evaluation and the robot agents run.

A snapshot is a directory:

    weights.pt     the N networks' parameters, a plain dict of tensors (w_pos, w_bel, b1, w2, b2;
                   shapes in shared/policy.py), loadable with torch.load(weights_only=True)
    policy.json    metadata (``format`` "mures.policy/1"): graph_id, node labels in row order,
                   n, robots, hidden, variant, beta, the belief model the robots use (Gamma_hat,
                   b0, as model.json), the sensor, the training config and seed, the sha256 of
                   weights.pt, and the training summary

Loading checks the format, the graph_id against the map in use, every tensor's shape and the
weights' sha256, and fails with a ``SnapshotError`` naming the mismatch. Snapshots are written
to a temporary directory next to the target and renamed into place, so a reader (or a crash
half-way) never sees a half-written one.

Running a team of k robots on a snapshot trained for N: robot i runs network i for k <= N (the
others dropped out); for k > N robot i runs network i mod N, and ``team_note`` says so.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shared.belief import BatchedBelief, BeliefFilter
from shared.cepg import sample
from shared.graph import Graph
from shared.models import ModelError, Sensor, TargetModel, from_matrix
from shared.policy import TeamPolicy
from shared.searchers import BeliefTracker
from shared.sim import Obs

FORMAT = "mures.policy/1"
WEIGHTS = "weights.pt"
META = "policy.json"
SUMMARY = "training_summary.json"
VARIANTS = ("cepg", "cepg+", "c-cepg")


class SnapshotError(ValueError):
    """A snapshot cannot be loaded or does not fit the map in use; the message says why."""


@dataclass
class Snapshot:
    meta: dict[str, Any]
    policy: TeamPolicy
    model: TargetModel  # the robots' belief model (Gamma_hat, b0)
    sensor: Sensor

    @property
    def variant(self) -> str:
        return str(self.meta["variant"])

    @property
    def robots(self) -> int:
        return int(self.meta["robots"])

    def network_for(self, robot: int) -> int:
        """The network robot ``robot`` runs (module docstring)."""
        return robot % self.robots

    def team_note(self, k: int) -> str | None:
        if k > self.robots:
            return (
                f"snapshot trained for {self.robots} robots, running {k}: robot i runs network i mod {self.robots}, "
                "so some robots share a policy"
            )
        return None


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def save_snapshot(
    path: str | Path,
    policy: TeamPolicy,
    graph: Graph,
    model: TargetModel,
    sensor: Sensor,
    variant: str,
    beta: list[float],
    config: dict[str, Any],
    summary: dict[str, Any],
) -> Path:
    """Write a snapshot directory atomically (an existing one at ``path`` is replaced)."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save({k: v.detach().cpu().contiguous() for k, v in policy.named_parameters()}, buf)
    weights = buf.getvalue()
    meta = {
        "format": FORMAT,
        "graph_id": graph.graph_id,
        "map": graph.name,
        "nodes": [int(x) for x in graph.labels],
        "n": graph.n,
        "robots": policy.N,
        "hidden": policy.H,
        "variant": variant,
        "beta": [float(b) for b in beta],
        "model": {**model.to_json(graph), "kind": model.kind},
        "sensor": sensor.to_json(),
        "training": config,
        "seed": config.get("seed"),
        "weights": {"file": WEIGHTS, "sha256": _sha256(weights), "bytes": len(weights)},
        "summary": summary,
    }
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        (tmp / WEIGHTS).write_bytes(weights)
        (tmp / META).write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
        (tmp / SUMMARY).write_text(json.dumps(summary, indent=1) + "\n", encoding="utf-8")
        for f in (tmp / WEIGHTS, tmp / META, tmp / SUMMARY):
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
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


def load_snapshot(path: str | Path, graph: Graph, device: torch.device | str = "cpu") -> Snapshot:
    """Load and check a snapshot for ``graph`` (module docstring)."""
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
    if meta["graph_id"] != graph.graph_id:
        raise SnapshotError(
            f"{where}: trained on map {meta.get('map')!r} ({meta['graph_id']}), "
            f"not on {graph.name!r} ({graph.graph_id})"
        )
    if meta["n"] != graph.n or meta.get("nodes") != [int(x) for x in graph.labels]:
        raise SnapshotError(f"{where}: node list does not match map {graph.name!r} in row order")
    if meta["variant"] not in VARIANTS:
        raise SnapshotError(f"{where}: unknown variant {meta['variant']!r}")
    try:
        raw = (path / WEIGHTS).read_bytes()
    except FileNotFoundError:
        raise SnapshotError(f"{where}: no {WEIGHTS}") from None
    if _sha256(raw) != meta["weights"].get("sha256"):
        raise SnapshotError(f"{where}/{WEIGHTS}: sha256 does not match policy.json (corrupt or replaced file)")
    try:
        state = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for a bad archive
        raise SnapshotError(f"{where}/{WEIGHTS}: cannot be read as weights ({exc})") from None
    N, n, H = int(meta["robots"]), graph.n, int(meta["hidden"])
    policy = TeamPolicy(n, N, torch.as_tensor(graph.adjacency()), hidden=H)
    expected = {k: tuple(v.shape) for k, v in policy.named_parameters()}
    if not isinstance(state, dict) or set(state) != set(expected):
        raise SnapshotError(f"{where}/{WEIGHTS}: expected tensors {sorted(expected)}")
    for k, shape in expected.items():
        if tuple(state[k].shape) != shape:
            raise SnapshotError(f"{where}/{WEIGHTS}: {k} has shape {tuple(state[k].shape)}, expected {shape}")
    with torch.no_grad():
        for k, p in policy.named_parameters():
            p.copy_(state[k])
    try:
        m = meta["model"]
        model = from_matrix(graph, np.asarray(m["gamma"], dtype=np.float64), m["b0"], kind=m.get("kind", "matrix"))
        s = meta["sensor"]
        sensor = Sensor(float(s["eta_fn"]), float(s["eta_fp"]), str(s["detection"]))
    except (ModelError, KeyError, TypeError, ValueError) as exc:
        raise SnapshotError(f"{where}/{META}: bad belief model or sensor ({exc})") from None
    return Snapshot(meta=meta, policy=policy.to(device), model=model, sensor=sensor)


class PolicySearcher:
    """A snapshot's team as a batched searcher for the evaluator (shared/evaluate.py).

    Each robot keeps its own belief (Eq. 1, with the snapshot's Gamma_hat and b0) and samples
    its action from its network (Algorithm 1); C-CE-PG robots share the collective belief
    (Eq. 6) instead. ``greedy_actions`` takes the most likely action instead of sampling.
    """

    def __init__(
        self,
        snap: Snapshot,
        graph: Graph,
        sensor: Sensor,
        n_robots: int,
        seed: int = 0,
        device: torch.device | str = "cpu",
        greedy_actions: bool = False,
    ) -> None:
        self.name = f"policy:{snap.variant}"
        self.device = torch.device(device)
        self.policy = snap.policy.to(self.device)
        self.collective = snap.variant == "c-cepg"
        self.belief = BatchedBelief(graph, snap.model, sensor, self.device)
        self.beliefs = BeliefTracker(self.belief)
        self.nets = torch.tensor([snap.network_for(i) for i in range(n_robots)], device=self.device)
        self.greedy_actions = greedy_actions
        self.gen = torch.Generator(device=self.device)
        self.gen.manual_seed(seed)

    def _lik(self, obs: Obs) -> torch.Tensor:
        if self.collective:
            lik = self.belief.collective_likelihood(obs.pos, obs.z, obs.active)
            return lik.unsqueeze(1).expand(-1, obs.pos.shape[1], -1)
        return self.belief.likelihood(obs.pos, obs.z)

    @torch.no_grad()
    def act(self, obs: Obs) -> torch.Tensor:
        b, _pred = self.beliefs.update(self._lik(obs), obs.new)  # Eq. 1 / Eq. 6, (B, N, n)
        logits = self.policy.logits_for(self.nets, obs.pos, b)
        if self.greedy_actions:
            return logits.argmax(-1)
        return sample(torch.softmax(logits, dim=-1), self.gen)


class PolicyAgent:
    """One robot's decision loop in numpy (for the robot agent): its own belief filter (Eq. 1)
    and its own network, nothing from other robots. ``reset(p0, z0)`` at a mission's start, then
    ``decide(p, z)`` -> next node label-row for each step's observation.

    C-CE-PG needs the other robots' observations, so it is refused here.
    """

    def __init__(self, snap: Snapshot, graph: Graph, robot: int, seed: int = 0, greedy_actions: bool = False) -> None:
        if snap.variant == "c-cepg":
            raise SnapshotError("a c-cepg policy needs every robot's observations; a lone agent cannot run it")
        k = snap.network_for(robot)
        P = {name: p.detach().cpu().numpy().astype(np.float64) for name, p in snap.policy.named_parameters()}
        self.w_pos, self.w_bel, self.b1 = P["w_pos"][k], P["w_bel"][k], P["b1"][k]
        self.w2, self.b2 = P["w2"][k], P["b2"][k]
        self.graph = graph
        self.filter = BeliefFilter(graph, snap.model, snap.sensor)
        self.rng = np.random.default_rng(seed)
        self.greedy_actions = greedy_actions
        self.belief: np.ndarray | None = None

    def reset(self, p0: int, z0: int) -> None:
        self.belief = self.filter.reset(p0, z0)

    def observe(self, p: int, z: int) -> None:
        self.belief = self.filter.update(p, z)

    def act(self, p: int) -> int:
        """Next node row from N[p] for the current belief (Algorithm 1, line 3)."""
        assert self.belief is not None, "reset() first"
        nbrs = self.graph.closed(p)
        h = np.maximum(self.w_pos[p] + self.belief @ self.w_bel + self.b1, 0.0)
        logits = h @ self.w2[:, nbrs] + self.b2[nbrs]
        if self.greedy_actions:
            return int(nbrs[int(np.argmax(logits))])
        w = np.exp(logits - logits.max())
        c = np.cumsum(w)
        return int(nbrs[min(int(np.searchsorted(c, self.rng.random() * c[-1], side="right")), len(nbrs) - 1)])
