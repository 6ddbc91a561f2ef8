"""Policy snapshots on the torch side: what training writes and what evaluation runs.

The format, its checks and the numpy decision step that robot agents run are in
shared/core/snapshot_format.py (docs/SPEC.md section 8); here a snapshot's weights become a
``TeamPolicy`` (and back), and a team becomes a batched searcher for the evaluator. Snapshots of
the older torch format (``weights.pt``) are read here, and ``convert_snapshot`` rewrites them.
"""

from __future__ import annotations

import io
import json
import os
import platform
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from shared.core.files import atomic_write
from shared.core.graph import Graph
from shared.core.graph_policy import NODE_BIAS
from shared.core.models import Sensor, TargetModel
from shared.core.snapshot_format import (
    GENERAL,
    LEGACY_WEIGHTS,
    META,
    PARAMS,
    WEIGHTS,
    GeneralPolicy,
    SnapshotData,
    SnapshotError,
    TeamInfo,
    Weights,
    read_meta,
    read_snapshot,
    read_weights_blob,
    sha256_hex,
    write_snapshot,
)
from shared.engine.batched_belief import BatchedBelief, BeliefTracker
from shared.engine.sim import Obs
from shared.learning.policy import TeamPolicy, sample

__all__ = ["PolicySearcher", "Snapshot", "SnapshotError", "convert_snapshot", "load_snapshot", "save_snapshot"]


@dataclass
class Snapshot(TeamInfo):
    """A snapshot's team of networks as a torch module (the general policy bound to the map and
    its robots, shared/learning/general.py ``GraphTeam``, for a snapshot of architecture "general")."""

    policy: Any  # TeamPolicy | GraphTeam

    def to_data(self) -> SnapshotData:
        """The numpy view the robot agent runs (float32 weights, as a snapshot stores them)."""
        return SnapshotData(meta=self.meta, weights=policy_weights(self.policy), model=self.model, sensor=self.sensor)


def policy_weights(policy: Any) -> Weights:
    """A TeamPolicy's (or GraphTeam's) parameters as float32 numpy arrays, keyed as in a snapshot."""
    from shared.learning.general import GraphTeam

    if isinstance(policy, GraphTeam):
        bias = policy.node_bias()
        extra = {} if bias is None else {NODE_BIAS: bias.detach().cpu().to(torch.float32).numpy()}
        return {**policy.net.numpy_weights(), **extra}
    return {k: v.detach().cpu().to(torch.float32).numpy() for k, v in policy.named_parameters()}


def torch_weights(raw: bytes) -> Weights:
    """Read the older ``weights.pt`` (a plain dict of tensors) without executing code."""
    state = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        raise SnapshotError(f"{LEGACY_WEIGHTS} does not hold a dict of tensors")
    return {k: v.numpy() for k, v in state.items()}


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
    algorithm: str = "cepg",
    team_searcher: str | None = None,
) -> Path:
    """Write ``policy`` as a snapshot directory (shared/core/snapshot_format.py ``write_snapshot``); the
    summary gains ``trained_with`` (``provenance``) unless it has one."""
    summary = {**summary, "trained_with": summary.get("trained_with") or provenance()}
    weights = policy_weights(policy)
    return write_snapshot(
        path, graph, weights, model, sensor, variant, beta, config, summary, algorithm, team_searcher, robots=policy.N
    )


def provenance() -> dict[str, Any]:
    """The software and machine a team is trained with: the same seeds give the same weights only
    with the same versions and the same processor kernels (torch picks its vector instructions,
    ``cpu_capability``, by processor), so a summary says which."""
    return {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "platform": platform.platform(),
        "processor": _processor_name(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
    }


def _processor_name() -> str:
    """The processor's model name (Linux's /proc/cpuinfo), else what ``platform`` knows."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


def load_snapshot(path: str | Path, graph: Graph, device: torch.device | str = "cpu") -> Snapshot:
    """Load and check a snapshot for ``graph`` (either weights format) as a TeamPolicy."""
    data = read_snapshot(path, graph, legacy=torch_weights)
    if data.general:
        from shared.learning.general import GeneralNet, GraphTeam

        team = GraphTeam(
            GeneralNet.from_weights(data.weights), graph, data.robots, node_bias=data.weights.get(NODE_BIAS)
        )
        return Snapshot(meta=data.meta, policy=team.to(device), model=data.model, sensor=data.sensor)
    policy = TeamPolicy(graph.n, data.robots, torch.as_tensor(graph.adjacency()), hidden=int(data.meta["hidden"]))
    with torch.no_grad():
        for k, p in policy.named_parameters():
            p.copy_(torch.from_numpy(np.ascontiguousarray(data.weights[k])))
    return Snapshot(meta=data.meta, policy=policy.to(device), model=data.model, sensor=data.sensor)


def convert_snapshot(path: str | Path) -> bool:
    """Rewrite an older snapshot's ``weights.pt`` as ``weights.safetensors`` in place (the same
    values); True when something was converted, False when it already was in the new format.

    Crash-safe: the new weights file is written first, then policy.json is switched to it, then
    the old file is removed; at every point the directory is a valid snapshot.
    """
    from safetensors.numpy import save as save_safetensors

    path = Path(path)
    meta = read_meta(path)
    name, raw = read_weights_blob(path, meta)
    if name == WEIGHTS:
        return False
    try:
        weights = torch_weights(raw)
    except SnapshotError:
        raise
    except Exception as exc:
        raise SnapshotError(f"{path}/{name}: cannot be read as weights ({exc})") from None
    if set(weights) != set(PARAMS):
        raise SnapshotError(f"{path}/{name}: expected tensors {sorted(PARAMS)}, got {sorted(weights)}")
    blob = save_safetensors({k: np.ascontiguousarray(weights[k], dtype=np.float32) for k in PARAMS})
    atomic_write(path / WEIGHTS, blob)
    meta["weights"] = {"file": WEIGHTS, "sha256": sha256_hex(blob), "bytes": len(blob)}
    atomic_write(path / META, json.dumps(meta, indent=1) + "\n")
    (path / LEGACY_WEIGHTS).unlink(missing_ok=True)
    return True


class PolicySearcher:
    """A snapshot's team as a batched searcher for the evaluator (shared/engine/evaluate.py).

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
        """Lambda's diagonal per robot (B, N, n), 1 for a robot without a reading this tick."""
        if self.collective:
            lik = self.belief.collective_likelihood(obs.pos, obs.z, obs.observed())
            return lik.unsqueeze(1).expand(-1, obs.pos.shape[1], -1)
        return self.belief.likelihood(obs.pos, obs.z, obs.ready)

    @torch.no_grad()
    def act(self, obs: Obs) -> torch.Tensor:
        b, _pred = self.beliefs.update(self._lik(obs), obs.new)  # Eq. 1 / Eq. 6, (B, N, n)
        logits = self.policy.logits_for(self.nets, obs.pos, b)
        if self.greedy_actions:
            return logits.argmax(-1)
        return sample(torch.softmax(logits, dim=-1), self.gen)


def general_snapshot(
    policy: GeneralPolicy,
    graph: Graph,
    robots: int,
    model: TargetModel,
    sensor: Sensor,
    device: torch.device | str = "cpu",
) -> Snapshot:
    """The general policy as a snapshot of this map for ``robots`` robots flying on ``model``:
    what `mures train --init general` fine-tunes and what a training server flies first."""
    from shared.learning.general import GeneralNet, GraphTeam

    team = GraphTeam(GeneralNet.from_weights(policy.weights), graph, robots).to(device)
    meta = {"architecture": GENERAL, "variant": "cepg", "robots": robots, "hidden": team.H, "general": policy.meta}
    return Snapshot(meta=meta, policy=team, model=model, sensor=sensor)
