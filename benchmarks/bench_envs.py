"""Step rate of the TorchRL environment against the raw simulator it wraps (the target set for it:
at least half as fast as the raw simulator).

Run: python benchmarks/bench_envs.py [--batch B ...] [--seconds S] [--rounds R] [--threads T] [--default-malloc] [--forms]

Four loops with uniformly random actions on OFFICE, N = 4, finished episodes restarted:
  sim          the engine's SearchSim alone (auto-reset), no beliefs
  sim+belief   SearchSim plus every robot's own belief update (Eq. 1): the work the environment's
               observation needs, done with the engine's batched belief algebra
  torchrl      mures_v0.torchrl_env: a random valid index per robot, then step_and_maybe_reset (what
               TorchRL's rollouts and collectors call), observations, masks and the global state built
  cached       the same call on a second environment whose _step hands back a copy of one step's
               result with no episode ending: TorchRL's own cost of a step, with nothing simulated
The loops take turns for --rounds rounds of --seconds each (a shared machine's load then falls on
all of them alike); in a round each loop's rate is that of its fastest chunk of about 0.1 s.
Prints the median over the rounds of each loop's team steps per second and of the per-round
ratios torchrl / sim, torchrl / sim+belief and sim+belief / sim, then each loop's median time per
step. sim+belief / sim is the most torchrl / sim that any environment can reach whose
observations need the engine's belief update every step, before it builds any observation.

--forms: the belief prediction Gamma_hat^T b alone for the B N beliefs of each --batch, in the
forms torch offers: dense (B N, n) @ (n, n) as the engine computes it, the sparse Gamma_hat (COO
and CSR) on beliefs kept node-major, (n, B N), and the transposition between the two layouts that
the node-major forms need for observations laid out per robot. In ms: each form's fastest chunk
of about 0.1 s within --seconds, as the loops are timed, under the same malloc setting as the
loops (--default-malloc leaves it).
"""

import argparse
import statistics
import time
import warnings

import torch

from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.engine.batched_belief import BatchedBelief, BeliefTracker
from shared.engine.memory import keep_freed_memory
from shared.engine.searchers import RandomSearcher
from shared.engine.sim import SearchSim
from shared.envs import mures_v0


def _rate(step, batch: int, seconds: float) -> float:
    """Team steps per second of ``step``: the best of the chunks of about 0.1 s that fit in
    ``seconds`` (as ``timeit`` takes the best of its repeats: on a shared machine other work only
    ever slows a chunk down; a chunk spans enough steps for the episodes' restarts to average out)."""
    for _ in range(20):  # warm-up
        step()
    t0 = time.perf_counter()
    k = 0
    while time.perf_counter() - t0 < 0.1:
        step()
        k += 1
    best, t_end = float("inf"), time.perf_counter() + seconds
    while time.perf_counter() < t_end:
        t = time.perf_counter()
        for _ in range(k):
            step()
        best = min(best, (time.perf_counter() - t) / k)
    return batch / best


def run(batch: int, seconds: float, rounds: int, tune_malloc: bool = True) -> dict[str, float]:
    g = builtin_graph("office")
    model, sensor = uniform_walk(g), Sensor()
    sim = SearchSim(g, model, sensor, n_robots=4, batch=batch, seed=0)
    searcher = RandomSearcher(g, seed=1)
    state = {"obs": sim.reset()}

    def sim_step() -> None:
        state["obs"], _ = sim.step(searcher.act(state["obs"]))

    tracker = BeliefTracker(BatchedBelief(g, model, sensor))

    def belief_step() -> None:
        obs, _ = sim.step(searcher.act(state["obs"]))
        tracker.update(tracker.belief.likelihood(obs.pos, obs.z), obs.new)
        state["obs"] = obs

    # the environment sets the process's malloc (tune_malloc) before any loop runs: all three
    # loops run under the same allocator settings
    env = mures_v0.torchrl_env(map="office", robots=4, batch_size=[batch], seed=0, tune_malloc=tune_malloc)
    tds = {"td": env.reset()}
    gen = torch.Generator().manual_seed(1)

    def env_step() -> None:  # a uniformly random valid index, drawn as RandomSearcher draws
        td = tds["td"]
        deg = td["agents", "action_mask"].sum(-1)
        td["agents", "action"] = (torch.rand(deg.shape, generator=gen) * deg).long()
        _, tds["td"] = env.step_and_maybe_reset(td)

    cached_env = mures_v0.torchrl_env(map="office", robots=4, batch_size=[batch], seed=0, tune_malloc=tune_malloc)
    cached_td = cached_env.reset()
    cached_td["agents", "action"] = torch.zeros(batch, 4, dtype=torch.long)
    result = cached_env._step(cached_td)
    for flag in ("done", "terminated", "truncated"):
        result[flag].zero_()
    cached_env._step = lambda _: result.clone(recurse=False)

    def cached_step() -> None:
        cached_env.step_and_maybe_reset(cached_td.clone(recurse=False))

    loops = {"sim": sim_step, "sim+belief": belief_step, "torchrl": env_step, "cached": cached_step}
    ratios = {
        "torchrl/sim": ("torchrl", "sim"),
        "torchrl/(sim+belief)": ("torchrl", "sim+belief"),
        "(sim+belief)/sim": ("sim+belief", "sim"),
    }
    per_round: dict[str, list[float]] = {k: [] for k in (*loops, *ratios)}
    with torch.no_grad():
        for _ in range(rounds):
            r = {name: _rate(step, batch, seconds) for name, step in loops.items()}
            r.update({name: r[num] / r[den] for name, (num, den) in ratios.items()})
            for k, v in r.items():
                per_round[k].append(v)
    return {k: statistics.median(v) for k, v in per_round.items()}


def prediction_forms(batch: int, seconds: float) -> dict[str, float]:
    """ms per belief prediction for the B N = 4 batch beliefs of OFFICE (module docstring)."""
    g = builtin_graph("office")
    gamma = BatchedBelief(g, uniform_walk(g), Sensor()).gamma  # (n, n), rows sum to 1
    b = torch.rand(4 * batch, g.n, generator=torch.Generator().manual_seed(0))
    b /= b.sum(1, keepdim=True)  # (B N, n) row-major, as the engine keeps them
    b_t = b.t().contiguous()  # (n, B N) node-major
    gamma_t = gamma.t().contiguous()
    with warnings.catch_warnings():  # torch's notice that sparse CSR support is in beta
        warnings.simplefilter("ignore", UserWarning)
        coo, csr = gamma_t.to_sparse(), gamma_t.to_sparse_csr()
    if not torch.allclose(torch.sparse.mm(coo, b_t).t(), b @ gamma, atol=1e-6):
        raise AssertionError("the sparse prediction differs from the dense one")
    forms = {
        "dense b @ Gamma": lambda: b @ gamma,
        "node-major COO Gamma^T b": lambda: torch.sparse.mm(coo, b_t),
        "node-major CSR Gamma^T b": lambda: csr @ b_t,
        "transpose (n, B N) -> (B N, n)": lambda: b_t.t().contiguous(),
    }
    return {name: 1e3 / _rate(f, 1, seconds) for name, f in forms.items()}  # ms per call


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, nargs="+", default=[256, 4096])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--default-malloc", action="store_true", help="leave glibc's malloc as it is (torchrl_env(tune_malloc=False))"
    )
    ap.add_argument("--forms", action="store_true", help="time the belief prediction's forms instead (docstring)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    if args.forms:
        if not args.default_malloc:  # as the environment sets it: each product's result reuses heap blocks
            keep_freed_memory()
        n = builtin_graph("office").n
        for b in args.batch:
            times = prediction_forms(b, args.seconds)
            print(
                f"OFFICE B N={4 * b:<6} n={n} threads={args.threads}  "
                + "  ".join(f"{name} {ms:.3f} ms" for name, ms in times.items())
            )
        return
    for b in args.batch:
        r = run(b, args.seconds, args.rounds, tune_malloc=not args.default_malloc)
        print(
            f"OFFICE N=4 B={b:<5} threads={args.threads} malloc={'default' if args.default_malloc else 'tuned'} median of {args.rounds}  sim {r['sim']:>10,.0f}  sim+belief {r['sim+belief']:>10,.0f}  "
            f"torchrl {r['torchrl']:>10,.0f} team-steps/s  torchrl/sim {r['torchrl/sim']:.2f}  "
            f"torchrl/(sim+belief) {r['torchrl/(sim+belief)']:.2f}  (sim+belief)/sim {r['(sim+belief)/sim']:.2f}"
        )
        print(
            "  ms per step: "
            + "  ".join(f"{k} {b / r[k] * 1e3:.3f}" for k in ("sim", "sim+belief", "torchrl", "cached"))
        )


if __name__ == "__main__":
    main()
