"""Estimating the target's motion model (Gamma_hat, b0) from the robots' own records.

Only robots' positions, observations and the mission outcome are used, never the target's
true positions (docs/SPEC.md section 2). The hidden state is the target's node e_t; at each t the
emission is the product of the Lambdas of every robot of the mission (Theorem 3, Eq. 7).

``em`` (default): Baum-Welch with the sensor known. Scaled forward-backward smoothing over all
missions at once (tensors (T, M, n), the M missions sorted by length so that step t works on
those still running only), expected transition counts,
transitions restricted to the closed neighbourhoods (the support of the initial guess, which
Baum-Welch never leaves), rows stochastic, iterated until the log-likelihood stops improving.
Above ``SPARSE_FROM_NODES`` nodes, or where the dense pass's buffers padded to the longest
mission would pass ``DENSE_EM_MAX_ELEMENTS``, Gamma_hat is kept on its n + 2m entries and each
step works on the missions still running alone (``_SparseForwardBackward``): O(n + m) a
mission-step and memory that grows with the steps the missions took, where the dense pass is
O(n^2) and (T, M, n). The missions' likelihoods are stored packed the same way (``MissionData``).

``eq8``: the paper's one-round least-squares estimate (Eq. 8) from collective beliefs filtered
with Gamma_hat_0 = I, projected onto the closed-neighbourhood support and made row-stochastic;
kept for comparison.

Capture-aware emissions. A mission stops at its capture, and a z = 1 that did not stop it was a
false alarm. The EM uses that: a z = 1 before the capture time says e_t is outside D(p), and the
capturing robot's last z = 1 says e_t is inside D(p). With eta_fp = 0 this changes nothing.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, NoReturn

import numpy as np
import torch

from shared.core.graph import Graph
from shared.core.models import TargetModel, from_matrix, uniform_walk
from shared.core.records import Episode, RecordError, emission_likelihoods, parse_record, spread
from shared.engine.batched_belief import SPARSE_FROM_NODES


@dataclass
class MissionData:
    """Emission likelihoods of M missions, packed: lik (sum of lengths, n), mission m's steps
    t = 0..length[m]-1 in rows start[m] + t (``mission``); length (M,) steps per mission. Packed,
    not padded to the longest mission, so that memory grows with the steps the missions took
    (one mission that ran to the step limit of 3 n does not make every mission that long)."""

    lik: np.ndarray
    length: np.ndarray
    used_records: int
    skipped: Counter[str] = field(default_factory=Counter)
    impossible: list[str] = field(default_factory=list)  # missions set aside: no target path explains them
    records: np.ndarray | None = None  # (M,) records per mission

    def __post_init__(self) -> None:
        self.length = np.asarray(self.length, dtype=np.int64)
        self.start = np.concatenate([[0], np.cumsum(self.length)[:-1]]).astype(np.int64)  # (M,)
        if self.lik.shape[0] != int(self.length.sum()):
            raise ValueError(f"lik has {self.lik.shape[0]} rows for missions of {int(self.length.sum())} steps")

    def mission(self, m: int) -> np.ndarray:
        """Mission m's likelihoods: (length[m], n), a view."""
        return self.lik[self.start[m] : self.start[m] + self.length[m]]

    def step(self, t: int, missions: np.ndarray) -> np.ndarray:
        """Step t of the missions ``missions`` (indices, each at least t + 1 steps long): (k, n)."""
        return self.lik[self.start[missions] + t]

    def subset(self, missions: np.ndarray) -> MissionData:
        """The missions ``missions`` (indices) alone."""
        idx = np.sort(np.asarray(missions))
        records = None if self.records is None else self.records[idx]
        used = int(records.sum()) if records is not None else self.used_records
        lik = np.concatenate([self.mission(m) for m in idx]) if len(idx) else self.lik[:0]
        return MissionData(lik=lik, length=self.length[idx], used_records=used, records=records)


def collect_missions(
    records: Iterable[tuple[int, Any]],
    graph: Graph,
    capture_aware: bool = True,
    fleet: str | None = None,
    tick_s: float | None = None,
) -> MissionData:
    """Validate records, group them by (fleet, mission_id) and build emission likelihoods.

    ``records`` yields (line number, parsed JSON or RecordError). Bad records are skipped and
    counted by reason; a second record of the same robot in a mission counts as "duplicate".

    ``tick_s``: the mission clock cut into ticks of that many seconds, so that the model fitted is
    Gamma_hat per tick: each reading is an emission at the tick it was made (floor(time_s /
    tick_s); readings in one tick multiply), and a tick without one has none (likelihood 1).
    Records without times (``steps[k].time_s``) are skipped as "no-times".
    """
    skipped: Counter[str] = Counter()
    missions: dict[tuple[str, str], dict[str, Episode]] = defaultdict(dict)
    for _lineno, rec in records:
        if isinstance(rec, RecordError):
            skipped[rec.reason] += 1
            continue
        try:
            ep = parse_record(rec, graph, fleet=fleet)
        except RecordError as exc:
            skipped[exc.reason] += 1
            continue
        if tick_s is not None and ep.times is None:
            skipped["no-times"] += 1
            continue
        robots = missions[(ep.fleet, ep.mission_id)]
        if ep.robot_id in robots:
            skipped["duplicate"] += 1
            continue
        robots[ep.robot_id] = ep
    n = graph.n

    def at(ep: Episode) -> np.ndarray:
        """(T_r + 1,) the index along the mission's axis of each of the robot's readings."""
        if tick_s is None:
            return np.arange(len(ep.nodes))
        assert ep.times is not None
        return np.floor(ep.times / tick_s + 1e-9).astype(np.int64)

    length = np.array(
        [max(int(at(ep)[-1]) + 1 for ep in robots.values()) for robots in missions.values()], dtype=np.int64
    )
    data = MissionData(lik=np.ones((int(length.sum()), n), dtype=np.float64), length=length, used_records=0)
    detect_cache: dict[str, np.ndarray] = {}
    used = 0
    for m, robots in enumerate(missions.values()):
        for ep in robots.values():
            det = detect_cache.get(ep.sensor.detection)
            if det is None:
                det = detect_cache[ep.sensor.detection] = graph.detection_matrix(ep.sensor.detection)
            l_in, l_out = emission_likelihoods(ep, capture_aware)
            np.multiply.at(data.mission(m), at(ep), np.where(det[ep.nodes], l_in[:, None], l_out[:, None]))
            used += 1
    per_mission = np.array([len(robots) for robots in missions.values()], dtype=np.int64)
    keep = explained(graph, data)
    impossible = [mid for (_fleet, mid), ok in zip(missions, keep, strict=True) if not ok]
    if impossible:  # probability zero under every model: EM's posterior would be 0/0
        skipped["impossible"] += sum(len(missions[k]) for k, ok in zip(missions, keep, strict=True) if not ok)
        used -= skipped["impossible"]
        data = data.subset(np.flatnonzero(keep))
        per_mission = per_mission[keep]
    data.used_records, data.skipped, data.impossible, data.records = used, skipped, impossible, per_mission
    return data


def explained(graph: Graph, data: MissionData) -> np.ndarray:
    """(M,) bool: whether some path of the target (any start, steps within closed neighbourhoods)
    has non-zero likelihood for each mission's joint observations: the support of the forward
    filter (Eq. 6) under any model with full support on the map, which is where EM starts (the
    uniform walk). O(sum of lengths (n + m))."""
    M = len(data.length)
    possible = data.step(0, np.arange(M)) > 0 if M else np.zeros((0, data.lik.shape[1]), dtype=bool)
    for t in range(1, int(data.length.max(initial=0))):
        running = np.flatnonzero(data.length > t)
        possible[running] = spread(graph, possible[running]) & (data.step(t, running) > 0)
    return np.asarray(possible.any(1), dtype=bool)


@dataclass
class Estimate:
    model: TargetModel
    method: str
    iterations: int
    log_likelihood: list[float]
    converged: bool
    wall_seconds: float

    def to_json(self, graph: Graph, data: MissionData) -> dict[str, Any]:
        out = self.model.to_json(graph)
        out.update(
            method=self.method,
            iterations=self.iterations,
            converged=self.converged,
            log_likelihood=self.log_likelihood,
            missions=len(data.length),
            records_used=data.used_records,
            records_skipped=dict(data.skipped),
            wall_seconds=round(self.wall_seconds, 3),
            graph_id=graph.graph_id,
        )
        return out


def _by_length(data: MissionData, missions: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The missions a forward-backward works on, longest first (``missions``, or all of them
    sorted), their lengths and, per step t, how many are still running (the first k_t):
    (order (M,), length (M,), active (T,) non-increasing)."""
    order = np.argsort(-data.length, kind="stable") if missions is None else np.asarray(missions)
    length = data.length[order]
    active = (length[None, :] > np.arange(int(length.max(initial=1)))[:, None]).sum(1)
    return order, length, active


class _ForwardBackward:
    """Scaled forward-backward over M missions at once, time-major and packed by length: the
    missions sorted longest first, so that step t works on the missions [0, active[t]) that have
    a step t instead of on every mission padded to T. Buffers, and the views of them that each
    step reads and writes, are made once per data set and reused by every pass (an EM run makes
    hundreds; at these sizes a slice costs about as much as the arithmetic on it).

    ``missions`` picks the missions (indices into ``data``, longest first; default: all of them,
    sorted). ``__call__(G, b0)`` with G (n, n), b0 (n,) returns views of the buffers, valid until
    the next call: alpha (T, M, n) (filtered, normalised; 0 after a mission's end), beta (T, M, n)
    (scaled; 1 after it), c (T, M) scales (1 after it; log P(observations) = sum log c), and
    xi (n, n) = sum over missions and t of alpha_t^T w_{t+1}, w_{t+1} = L_{t+1} beta_{t+1} / c_{t+1},
    so that G * xi are the expected transition counts (Baum-Welch's E-step).
    """

    def __init__(self, data: MissionData, missions: np.ndarray | None = None) -> None:
        order, length, self.active = _by_length(data, missions)
        T = len(self.active)
        padded = np.ones((T, len(order), data.lik.shape[1]), dtype=np.float64)  # 1 after a mission's end
        for j, m in enumerate(order):
            padded[: length[j], j] = data.mission(m)
        self.L = torch.from_numpy(padded)  # (T, M, n)
        _T, M, n = self.L.shape
        self.alpha = torch.zeros_like(self.L)
        self.beta = torch.ones_like(self.L)
        self.c = torch.ones(T, M, dtype=self.L.dtype)
        self.w = torch.empty(M, n, dtype=self.L.dtype)
        self.xi = torch.empty(n, n, dtype=self.L.dtype)
        L, alpha, beta, c = self.L, self.alpha, self.beta, self.c
        steps = [int(k) for k in self.active if k > 0]
        # forward, t = 1..: (alpha_{t-1}, alpha_t, L_t, c_t) on the k missions running at t
        self._forward = [(alpha[t - 1, :k], alpha[t, :k], L[t, :k], c[t, :k]) for t, k in enumerate(steps) if t]
        # backward, t = T-2..0: (L_{t+1}, beta_{t+1}, c_{t+1}, w, beta_t, alpha_t) on the k running at t+1
        self._backward = [
            (L[t + 1, :k], beta[t + 1, :k], c[t + 1, :k].unsqueeze(1), self.w[:k], beta[t, :k], alpha[t, :k].T)
            for t, k in reversed(list(enumerate(steps[1:])))
        ]
        k0 = steps[0] if steps else 0  # missions with a step t = 0 (all, for records that parse)
        self._first = (alpha[0], L[0], alpha[0, :k0], c[0, :k0])

    def __call__(
        self, G: torch.Tensor, b0: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        alpha, beta, c, xi = self.alpha, self.beta, self.c, self.xi
        # every step writes into views of the buffers, in place: at these sizes the number of
        # operations, not their arithmetic, sets the time
        a0, L0, a, s = self._first
        torch.mul(b0.unsqueeze(0), L0, out=a0)
        self._normalise(a, s)
        for prev, a, Lt, s in self._forward:
            torch.mm(prev, G, out=a)  # Eq. 6: Lambda_c Gamma^T b, as row vectors
            a.mul_(Lt)
            self._normalise(a, s)
        xi.zero_()
        Gt = G.T.contiguous()
        for L1, beta1, c1, w, beta0, alpha0_T in self._backward:
            torch.mul(L1, beta1, out=w)
            w.div_(c1)
            torch.mm(w, Gt, out=beta0)
            xi.addmm_(alpha0_T, w)
        return alpha, beta, c, xi

    def posterior(self, G: torch.Tensor, b0: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
        """One pass: the log-likelihood, xi (n, n) and the posterior of e_0 per mission (M, n)."""
        alpha, beta, c, xi = self(G, b0)
        post0 = alpha[0] * beta[0]
        return float(c.log().sum()), xi, post0 / post0.sum(1, keepdim=True)

    @staticmethod
    def _normalise(a: torch.Tensor, s: torch.Tensor) -> None:
        torch.sum(a, 1, out=s)
        s.clamp_min_(1e-300)
        a.div_(s.unsqueeze(1))


class _SparseForwardBackward:
    """``_ForwardBackward`` on Gamma_hat's support alone, for maps above ``SPARSE_FROM_NODES``
    nodes or data sets whose padded buffers would be large (``em``'s ``sparse``): G is the (E,)
    vector of Gamma_hat on the E = n + 2m entries (src, dst) of the closed neighbourhoods, each
    step's propagation a sparse product (O(k (n + m)) for the k missions running, not O(k n^2)), xi
    the (E,) vector of expected transition counts' factors, and the buffers one (n, k_t) block per
    step t for the k_t missions running (memory grows with the steps the missions took, not with M
    times the longest; the likelihoods are read from the packed ``MissionData`` step by step, not
    copied). The same recursion and numbers up to rounding (tests/test_estimate.py)."""

    def __init__(self, data: MissionData, missions: np.ndarray | None, src: np.ndarray, dst: np.ndarray) -> None:
        order, _length, active = _by_length(data, missions)
        self.n, self.lik = data.lik.shape[1], data.lik  # read step by step, not copied
        # the rows of step t in the packed likelihoods: the missions running at t are the first k_t
        self.rows = [data.start[order[:k]] + t for t, k in enumerate(active)]
        self.src, self.dst = torch.as_tensor(src), torch.as_tensor(dst)

    def L(self, t: int) -> torch.Tensor:
        """Step t's likelihoods, (n, k_t), gathered from the packed ones."""
        return torch.from_numpy(self.lik[self.rows[t]]).T

    def posterior(self, G: torch.Tensor, b0: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
        """One pass: G (E,), b0 (n,) -> the log-likelihood, xi (E,) and the posterior of e_0 per
        mission (M, n)."""
        src, dst, g = self.src, self.dst, G.unsqueeze(1)
        alpha: list[torch.Tensor] = []  # (n, k_t) per step: filtered, normalised
        scale: list[torch.Tensor] = []  # (k_t,) per step: c_t
        for t in range(len(self.rows)):
            Lt = self.L(t)
            # Eq. 6: (Gamma^T alpha_{t-1})(v) = sum over the entries (u, v) of Gamma(u, v) alpha_{t-1}(u)
            prior = (
                b0.unsqueeze(1)
                if t == 0
                else torch.zeros_like(Lt).index_add_(0, dst, alpha[-1][src, : Lt.shape[1]] * g)
            )
            a = prior * Lt
            c = a.sum(0).clamp_min(1e-300)
            alpha.append(a / c)
            scale.append(c)
        xi = torch.zeros_like(G)
        beta = torch.ones_like(alpha[-1])
        for t in range(len(self.rows) - 2, -1, -1):
            L1 = self.L(t + 1)
            k = L1.shape[1]
            w_dst = (L1 * beta / scale[t + 1])[dst]  # (E, k): w_{t+1}(v), w = L_{t+1} beta_{t+1} / c_{t+1}
            xi += (alpha[t][src, :k] * w_dst).sum(1)  # alpha_t(u) w_{t+1}(v) on the support
            beta = torch.ones_like(alpha[t])  # the missions that end at t keep beta_t = 1
            beta[:, :k] = torch.zeros(self.n, k, dtype=L1.dtype).index_add_(0, src, w_dst * g)  # (Gamma w)(u)
        post0 = alpha[0] * beta
        ll = float(sum(c.log().sum() for c in scale))
        return ll, xi, (post0 / post0.sum(0, keepdim=True)).T


def _forward_backward(
    data: MissionData, missions: np.ndarray | None, support: tuple[np.ndarray, np.ndarray] | None
) -> _ForwardBackward | _SparseForwardBackward:
    """The dense forward-backward, or the sparse one on ``support`` (src, dst) where one is given."""
    return _ForwardBackward(data, missions) if support is None else _SparseForwardBackward(data, missions, *support)


def _serve(
    conn: Connection,
    data: MissionData,
    missions: np.ndarray,
    support: tuple[np.ndarray, np.ndarray] | None,
    inherited: list[Connection],
) -> None:
    """A worker process of ``_EStep``: the forward-backward of its group of missions, one pass per
    (G, b0) received, until None or until the caller's end is closed (its process ended: a kill -9
    included). ``inherited``: the caller's ends of the pipes, which the fork copied here and which
    are closed first, or the pipe would never report the caller's end."""
    for other in inherited:
        other.close()
    torch.set_num_threads(1)
    fb = _forward_backward(data, missions, support)
    try:
        while (msg := conn.recv()) is not None:
            ll, xi, post0 = fb.posterior(torch.from_numpy(msg[0]), torch.from_numpy(msg[1]))
            conn.send((ll, xi.numpy(), post0.numpy()))
    except (EOFError, OSError, KeyboardInterrupt):  # the caller went away or was interrupted: it says why
        pass


class EMWorkerError(RuntimeError):
    """A worker process of ``em`` ended before its pass was done (killed, out of memory)."""


def _can_fork() -> bool:
    """Worker processes can be forked here: the platform has fork, and this process is no daemon
    (multiprocessing forbids a daemon children; the training server's runs are daemons)."""
    return "fork" in multiprocessing.get_all_start_methods() and not multiprocessing.current_process().daemon


class _EStep:
    """Baum-Welch's E-step over every mission, the missions dealt into ``parts`` groups (every
    ``parts``-th of them by length, so that the groups' work is even): the first group in this
    process, each other one in a worker process of its own, forked once per EM run, which keeps
    its group's buffers and gets (G, b0) each pass. Not torch's threads: the passes' operations
    are too small for them (each would wait for the others' at its end), and Python threads
    contend for the interpreter lock at every one of a pass's thousand operations; groups of
    missions are independent. Where processes cannot be forked (``_can_fork``), the groups run
    here in turn: the same numbers, no faster. The estimate depends on ``parts`` (the order of
    the counts' sums), not on where the groups run.

    ``__call__(G, b0)`` returns the log-likelihood of the observations under (G, b0), xi (n, n)
    summed over the groups (``_ForwardBackward``) and the posterior of e_0 averaged over the
    missions (n,): the M-step's b0.
    """

    def __init__(self, data: MissionData, parts: int, support: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        order = np.argsort(-data.length, kind="stable")
        parts = max(1, min(parts, len(order)))
        groups = [order[i::parts] for i in range(parts)]
        self.local = _forward_backward(data, groups[0], support)
        self.here: list[_ForwardBackward | _SparseForwardBackward] = []  # groups run here after the first
        self.workers: list[tuple[Any, Connection]] = []  # (process, its end of the pipe)
        if parts > 1 and _can_fork():
            ctx = multiprocessing.get_context("fork")  # the data and the code are inherited, not sent
            for grp in groups[1:]:
                mine, theirs = ctx.Pipe()
                ours = [mine, *(c for _p, c in self.workers)]
                proc = ctx.Process(target=_serve, args=(theirs, data, grp, support, ours), daemon=True, name="mures-em")
                proc.start()
                theirs.close()
                self.workers.append((proc, mine))
        else:
            self.here = [_forward_backward(data, grp, support) for grp in groups[1:]]

    def __call__(self, G: torch.Tensor, b0: torch.Tensor) -> tuple[float, torch.Tensor, torch.Tensor]:
        if not self.workers and not self.here:
            ll, xi, post0 = self.local.posterior(G, b0)
            return ll, xi, post0.mean(0)
        for proc, conn in self.workers:
            try:
                conn.send((G.numpy(), b0.numpy()))
            except OSError:
                self._lost(proc)
        parts = [fb.posterior(G, b0) for fb in (self.local, *self.here)]  # each group its own buffers
        for proc, conn in self.workers:
            try:
                ll, xi, post0 = conn.recv()
            except (EOFError, OSError):
                self._lost(proc)
            parts.append((ll, torch.from_numpy(xi), torch.from_numpy(post0)))
        return (  # summed in the groups' order, wherever each ran
            sum(p[0] for p in parts),
            torch.stack([p[1] for p in parts]).sum(0),
            torch.cat([p[2] for p in parts]).mean(0),
        )

    @staticmethod
    def _lost(proc: Any) -> NoReturn:
        proc.join(1)  # its exit code
        raise EMWorkerError(f"EM's worker process {proc.pid} ended (exit code {proc.exitcode}); nothing was estimated")

    def close(self) -> None:
        for proc, conn in self.workers:
            with contextlib.suppress(OSError):
                conn.send(None)
            conn.close()
            proc.join(5)
            if proc.is_alive():
                proc.kill()
                proc.join()
        self.workers = []


ROW_MASS_MIN = 1e-200  # expected transitions out of a node below this are treated as none
DENSE_EM_MAX_ELEMENTS = 1 << 24  # above this many entries of (T, M, n) (128 MB of float64 a buffer) EM runs sparse


def em(
    graph: Graph,
    data: MissionData,
    init: TargetModel | None = None,
    max_iter: int = 1000,
    tol: float = 1e-6,
    pseudo_count: float = 0.0,
    accelerate: bool = True,
    progress: Callable[[int, float], None] | None = None,
    workers: int = 1,
    b0_pseudo_count: float = 0.0,
    sparse: bool | None = None,
) -> Estimate:
    """Baum-Welch for Gamma_hat and b0 with the sensor known (module docstring).

    ``init`` gives the support and starting point (default: the uniform walk on N[u]); a
    ``pseudo_count`` adds that many expected transitions to each supported entry, and
    ``b0_pseudo_count`` that many expected starts to every node (Dirichlet priors, so the result is
    the posterior mode; 0 and 0 are maximum likelihood). With few missions a prior keeps the model
    near the uniform walk and every node possible at the start, instead of ruling out what the
    data happened not to show. ``accelerate`` uses SQUAREM (Varadhan and Roland, 2008):
    from two EM steps it extrapolates along the EM path, keeps the result only if it raises the
    likelihood, and otherwise falls back to the plain steps, so the likelihood never decreases.
    Converged when the relative log-likelihood gain of an iteration falls below ``tol``;
    ``iterations`` counts forward-backward passes. ``workers`` processes share the missions'
    forward-backward (``_EStep``; 1: this process alone, with torch's threads as they are; more:
    each on one torch thread, this one's restored at the end). The estimate depends on it only by
    rounding: in the order of the expected counts' sums (1000 WARD missions: 2e-9 in an entry).
    ``sparse`` keeps Gamma_hat on its support's entries (``_SparseForwardBackward``; default: above
    ``SPARSE_FROM_NODES`` nodes, or where the dense pass's padded buffers would pass
    ``DENSE_EM_MAX_ELEMENTS``), the same estimate up to rounding at O(n + m) a step.
    """
    t0 = time.perf_counter()
    init = init or uniform_walk(graph)
    if len(data.length) == 0:
        raise ValueError("no usable missions in the records")
    if workers < 1:
        raise ValueError(f"EM needs at least one worker, not {workers}")
    torch_threads = torch.get_num_threads()
    if workers > 1:
        torch.set_num_threads(1)  # before forking: the workers take the other cores
    e_step = None
    if sparse is None:  # the dense pass's buffers are (T, M, n), padded to the longest mission
        padded = len(data.length) * int(data.length.max(initial=1)) * graph.n
        sparse = graph.n > SPARSE_FROM_NODES or padded > DENSE_EM_MAX_ELEMENTS
    support = (init.src, init.dst) if sparse else None  # Gamma_hat kept on its entries
    try:
        e_step = _EStep(data, workers, support)
        prior = (pseudo_count, b0_pseudo_count)
        return _em(graph, data, init, e_step, max_iter, tol, prior, accelerate, progress, t0, sparse=sparse)
    finally:
        if e_step is not None:
            e_step.close()
        torch.set_num_threads(torch_threads)


def _em(
    graph: Graph,
    data: MissionData,
    init: TargetModel,
    e_step: _EStep,
    max_iter: int,
    tol: float,
    prior: tuple[float, float],
    accelerate: bool,
    progress: Callable[[int, float], None] | None,
    t0: float,
    sparse: bool = False,
) -> Estimate:
    """``em``'s iterations, with its E-step made. G is Gamma_hat as an (n, n) matrix, or with
    ``sparse`` the (E,) vector of its entries on init's support (``_SparseForwardBackward``)."""
    if sparse:
        G = torch.as_tensor(init.prob, dtype=torch.float64).clone()
        src = torch.as_tensor(init.src)

        def row_sums(x: torch.Tensor) -> torch.Tensor:  # each entry's row total, (E,)
            return torch.zeros(graph.n, dtype=x.dtype).index_add_(0, src, x)[src]
    else:
        G = torch.as_tensor(init.dense())

        def row_sums(x: torch.Tensor) -> torch.Tensor:  # (n, 1)
            return x.sum(1, keepdim=True)

    support = G > 0
    b0 = torch.as_tensor(init.b0)
    passes = 0
    pseudo_count, b0_pseudo_count = prior
    missions = len(data.length)

    def step(G: torch.Tensor, b0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
        """One EM update; also returns the log-likelihood of its input."""
        nonlocal passes
        passes += 1
        ll, xi, b0_new = e_step(G, b0)
        # E-step: xi_t(u, v) = alpha_t(u) G(u, v) L_{t+1}(v) beta_{t+1}(v) / c_{t+1}, summed over t, missions
        counts = G * xi + pseudo_count * support
        rows = row_sums(counts)
        # M-step: rows stochastic on the support; a row with no expected transition keeps its value
        # (also one whose expected count is so small that dividing by it would not give a sum of 1:
        # seen with one short mission, where a start node's count came out near 1e-306)
        seen = rows > ROW_MASS_MIN
        G_new = torch.where(seen, counts / torch.where(seen, rows, torch.ones_like(rows)), G)
        if b0_pseudo_count:  # the expected starts plus the prior's, normalised
            b0_new = (missions * b0_new + b0_pseudo_count) / (missions + b0_pseudo_count * len(b0_new))
        return G_new, b0_new, ll  # b0_new: the posterior of e_0, averaged over the missions

    def project(G: torch.Tensor, b0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        G = torch.where(support, G.clamp_min(1e-10), torch.zeros_like(G))
        b0 = b0.clamp_min(1e-12)
        return G / row_sums(G), b0 / b0.sum()

    history: list[float] = []
    converged = False
    while passes < max_iter:
        G1, b1, ll = step(G, b0)
        history.append(ll)
        if progress:
            progress(passes, ll)
        if len(history) > 1 and abs(history[-1] - history[-2]) <= tol * abs(history[-2]):
            converged = True
            break
        if not accelerate:
            G, b0 = G1, b1
            continue
        G2, b2, ll1 = step(G1, b1)
        rG, rb = G1 - G, b1 - b0
        vG, vb = G2 - 2 * G1 + G, b2 - 2 * b1 + b0
        vnorm = float((vG**2).sum() + (vb**2).sum())
        if vnorm <= 0:
            G, b0 = G2, b2
            continue
        a = min(-1.0, -((float((rG**2).sum() + (rb**2).sum()) / vnorm) ** 0.5))
        Gx, bx = project(G - 2 * a * rG + a * a * vG, b0 - 2 * a * rb + a * a * vb)
        G3, b3, llx = step(Gx, bx)
        G, b0 = (G3, b3) if llx >= ll1 else (G2, b2)
    b0_out = b0.numpy() / b0.sum().item()
    if sparse:
        model = TargetModel(n=graph.n, src=init.src, dst=init.dst, prob=G.numpy(), b0=b0_out, kind="em")
    else:
        model = from_matrix(graph, G.numpy(), b0_out, kind="em")
    return Estimate(model, "em", passes, history, converged, time.perf_counter() - t0)


def eq8(graph: Graph, data: MissionData, rounds: int = 1, b0: np.ndarray | None = None) -> Estimate:
    """The paper's Eq. 8: Gamma_hat^T = B_{1:T} B_{0:T-1}^T (B_{0:T-1} B_{0:T-1}^T)^-1.

    Collective beliefs (Eq. 6) are filtered with the current Gamma_hat (Gamma_hat_0 = I, as in
    Algorithm 2), stacked over all missions' valid steps, and the least-squares solution is
    projected: entries off the closed neighbourhoods and negative entries set to 0, rows
    renormalised (a row left empty becomes the uniform walk's row).
    """
    t0 = time.perf_counter()
    forward_backward = _ForwardBackward(data)
    _T, M, n = forward_backward.L.shape
    valid = torch.arange(M).unsqueeze(0) < torch.as_tensor(forward_backward.active).unsqueeze(1)  # (T, M)
    G = torch.eye(n, dtype=torch.float64)
    prior = torch.as_tensor(np.full(n, 1.0 / n) if b0 is None else b0)
    support = torch.as_tensor(graph.closed_adjacency)
    fallback = torch.as_tensor(uniform_walk(graph).dense())
    for _ in range(max(1, rounds)):
        alpha, _beta, _c, _xi = forward_backward(G, prior)
        pair = valid[1:]  # transitions t -> t+1 inside a mission
        B0 = alpha[:-1][pair]  # (K, n) rows b_t
        B1 = alpha[1:][pair]  # (K, n) rows b_{t+1}
        gt = (B1.T @ B0) @ torch.linalg.pinv(B0.T @ B0)  # Gamma^T
        g = gt.T.clamp_min(0) * support
        s = g.sum(1, keepdim=True)
        G = torch.where(s > 0, g / s.clamp_min(1e-300), fallback)
    model = from_matrix(graph, G.numpy(), prior.numpy(), kind="eq8")
    return Estimate(model, "eq8", max(1, rounds), [], True, time.perf_counter() - t0)


def mean_row_tv(a: TargetModel | np.ndarray, b: TargetModel | np.ndarray) -> float:
    """Mean over rows of the total-variation distance 0.5 * sum_v |a(u, v) - b(u, v)|."""
    A = a.dense() if isinstance(a, TargetModel) else a
    Bm = b.dense() if isinstance(b, TargetModel) else b
    return float(0.5 * np.abs(A - Bm).sum(1).mean())
