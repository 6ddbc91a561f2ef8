"""`mures experiment NAME [--quick]` and `mures report`: the paper's figures as data, plots and a report.

Each experiment writes ``results/<name>/<name>.json`` (every cell with mean, 95% CI, episodes,
seed; the setup; the machine and date), ``<name>.csv`` and ``<name>.png``. Trained snapshots are
cached under ``results/snapshots/`` and reused. ``mures report`` turns whatever results exist into
docs/results.md; nothing in it is typed by hand.

Implemented: fig4 (toy learning curves), fig7 (all methods, N = 1..5, OFFICE and MUSEUM), fig8
(decision time per team step, measured in fig7), fig5 (beta), fig12 and fig13 (robustness). Not yet:
fig6, fig9, fig10, fig11.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

EXPERIMENTS = ("fig4", "fig5", "fig7", "fig8", "fig12", "fig13")
PLANNERS = ("fhpe", "fhpe-sa", "milp", "d-milp")


def machine() -> dict[str, Any]:
    return {"platform": platform.platform(), "python": platform.python_version(), "cpus": os.cpu_count(),
            "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")}  # fmt: skip


def _write(out: Path, name: str, data: dict[str, Any], rows: list[dict[str, Any]]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps({**data, "rows": rows}, indent=1) + "\n", encoding="utf-8")
    if rows:
        with open(out / f"{name}.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)


def _say(text: str) -> None:
    print(text, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------- fig4
def fig4(root: Path, quick: bool) -> Path:
    """The toy of paper Fig. 4: P(A) of both robots over updates, CE-PG (beta 0.5) vs PG (beta 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from shared.toy import toy_fig4

    seeds = range(3 if quick else 10)
    updates = 150 if quick else 400
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), sharey=True)
    for ax, beta in zip(axes, (0.5, 1.0), strict=True):
        for s in seeds:
            run = toy_fig4(beta, seed=s, updates=updates, reward="own")
            pa = np.asarray(run.p_a)
            ax.plot(pa[:, 0], color="C0", alpha=0.5)
            ax.plot(pa[:, 1], color="C1", alpha=0.5)
            split = bool(max(pa[-1]) >= 0.9 and min(pa[-1]) <= 0.1)
            rows.append({"beta": beta, "seed": s, "updates": updates, "p_a_robot1": round(float(pa[-1, 0]), 4),
                         "p_a_robot2": round(float(pa[-1, 1]), 4), "split": split})  # fmt: skip
        ax.set_title(f"{'CE-PG' if beta < 1 else 'PG'} (beta = {beta})")
        ax.set_xlabel("update")
    axes[0].set_ylabel("P(go to A)")
    fig.tight_layout()
    out = root / "fig4"
    _write(out, "fig4", {"experiment": "fig4", "quick": quick, "reward": "own", "machine": machine()}, rows)
    fig.savefig(out / "fig4.png", dpi=110)
    plt.close(fig)
    return out


# ---------------------------------------------------------------------- fig7 / fig8
def _snapshot(root: Path, env: str, robots: int, beta: float, episodes: int, seed: int) -> Path:
    """A cached CE-PG (beta < 1) or PG (beta = 1) team trained with the EM-estimated model."""
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk
    from shared.snapshot import save_snapshot
    from shared.train import TrainConfig, config_dict, train

    path = root / "snapshots" / f"{env}-N{robots}-beta{beta}-{episodes}-s{seed}"
    if (path / "policy.json").exists():
        return path
    g = builtin_graph(env)
    cfg = TrainConfig(robots=robots, episodes=episodes, beta=[beta], seed=seed,
                      em_first=min(8192, episodes // 2), em_missions=128 if episodes < 100_000 else 512)  # fmt: skip
    _say(f"  training {'PG' if beta == 1 else 'CE-PG'} {env} N={robots}, {episodes:,} episodes")
    res = train(g, uniform_walk(g), Sensor(), cfg)
    save_snapshot(path, res.policy, g, res.model, Sensor(), "cepg", [beta] * robots,
                  {**config_dict(cfg), "map": g.name}, res.summary)  # fmt: skip
    return path


def _cell(env: str, robots: int, method: str, make: Callable[[int], Any], episodes: int, seed: int) -> dict[str, Any]:
    from shared.evaluate import evaluate
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk

    g = builtin_graph(env)
    t0 = time.perf_counter()
    batched = method in ("random", "greedy", "pg", "cepg")
    res = evaluate(g, uniform_walk(g), Sensor(), robots, make, episodes=episodes, seed=seed,
                   chunk=4096 if batched or method == "oracle" else 1)  # fmt: skip
    wall = time.perf_counter() - t0
    s = res.summary()
    steps = float(res.capture_time.sum())
    lat_ms = wall / max(1.0, steps) * 1e3  # planners run one episode at a time
    if batched:  # decision time one episode at a time, so batching does not hide the per-step latency
        t1 = time.perf_counter()
        one = evaluate(g, uniform_walk(g), Sensor(), robots, make, episodes=3, seed=seed + 99, chunk=1)
        lat_ms = (time.perf_counter() - t1) / max(1.0, float(one.capture_time.sum())) * 1e3
    return {"map": env, "robots": robots, "method": method, "episodes": episodes, "seed": seed,
            "mean_capture_time": round(s["mean_capture_time"], 3), "ci95_halfwidth": round(s["ci95_halfwidth"], 3),
            "censored_fraction": round(s["censored_fraction"], 4), "team_steps": int(steps),
            "wall_seconds": round(time.perf_counter() - t0, 2), "decision_ms": round(lat_ms, 4)}  # fmt: skip


def _maker(kind: str, what: Any, g: Any, model: Any, sensor: Any, N: int, **kw: Any) -> Callable[[int], Any]:
    """seed -> searcher for the evaluator."""
    from shared.baselines import make_baseline
    from shared.searchers import make_searcher
    from shared.snapshot import PolicySearcher

    if kind == "ref":
        return lambda s: make_searcher(what, g, model, sensor, s)
    if kind == "policy":
        return lambda s: PolicySearcher(what, g, sensor, N, seed=s)
    return lambda s: make_baseline(what, g, model, sensor, N, s, **kw)


def fig7(root: Path, quick: bool) -> Path:
    """All methods, N = 1..5, OFFICE and MUSEUM (paper Fig. 7), and their decision times (Fig. 8)."""
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk
    from shared.snapshot import load_snapshot

    maps = ("office", "museum")
    team = range(1, 6)
    episodes = 300 if quick else 1500
    planner_episodes = 1 if quick else 100  # milp, d-milp, fhpe; fhpe-sa runs 4x as many
    train_eps = 10_000 if quick else 400_000
    seed = 1
    milp_limit = 0.1 if quick else 1.0
    rows: list[dict[str, Any]] = []
    t_start = time.perf_counter()
    for env in maps:
        g = builtin_graph(env)
        model, sensor = uniform_walk(g), Sensor()
        for N in team:
            _say(f"fig7: {env} N={N}")
            for name in ("random", "greedy"):
                rows.append(_cell(env, N, name, _maker("ref", name, g, model, sensor, N), episodes, seed))
            for label, beta in (("pg", 1.0), ("cepg", 0.5)):
                snap = load_snapshot(_snapshot(root, env, N, beta, train_eps, 0), g)
                rows.append(_cell(env, N, label, _maker("policy", snap, g, model, sensor, N), episodes, seed))
            for name in PLANNERS:
                if name == "fhpe" and N > 3:
                    continue  # 36^4 joint paths and more per decision: see the report
                kw = {"time_limit": milp_limit} if "milp" in name else {}
                eps = planner_episodes if name != "fhpe-sa" else planner_episodes * 4
                rows.append(_cell(env, N, name, _maker("baseline", name, g, model, sensor, N, **kw), eps, seed))
            if N <= 2:
                rows.append(_cell(env, N, "oracle", _maker("baseline", "oracle", g, model, sensor, N), episodes, seed))
            _say("  " + ", ".join(f"{r['method']} {r['mean_capture_time']:.1f}" for r in rows if r["map"] == env
                                  and r["robots"] == N))  # fmt: skip
    out = root / "fig7"
    setup = {"experiment": "fig7", "quick": quick, "episodes": episodes, "planner_episodes": planner_episodes,
             "fhpe_sa_episodes": planner_episodes * 4, "training_episodes": train_eps, "seed": seed,
             "horizons": {"fhpe": 2, "fhpe-sa": 5, "milp": 5, "d-milp": 5}, "discount": 0.97,
             "milp_time_limit_s": milp_limit, "machine": machine(),
             "wall_seconds": round(time.perf_counter() - t_start, 1)}  # fmt: skip
    _write(out, "fig7", setup, rows)
    _plot_fig7(out, rows)
    _plot_fig8(root / "fig8", rows, setup)
    return out


def _plot_fig7(out: Path, rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, env in zip(axes, ("office", "museum"), strict=True):
        for method in dict.fromkeys(r["method"] for r in rows):
            pts = [r for r in rows if r["map"] == env and r["method"] == method]
            if pts:
                ax.errorbar([r["robots"] for r in pts], [r["mean_capture_time"] for r in pts],
                            yerr=[r["ci95_halfwidth"] for r in pts], marker="o", capsize=3, label=method)  # fmt: skip
        ax.set_title(env.upper())
        ax.set_xlabel("robots N")
        ax.set_ylabel("capture time (steps)")
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "fig7.png", dpi=110)
    plt.close(fig)


def _plot_fig8(out: Path, rows: list[dict[str, Any]], setup: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sel = [{k: r[k] for k in ("map", "robots", "method", "decision_ms")} for r in rows]
    _write(out, "fig8", {"experiment": "fig8", "from": "fig7", "quick": setup["quick"], "machine": setup["machine"],
                         "note": "ms per team step, one episode at a time, simulator step included"}, sel)  # fmt: skip
    fig, ax = plt.subplots(figsize=(6, 4))
    for method in dict.fromkeys(r["method"] for r in sel):
        pts = [r for r in sel if r["map"] == "museum" and r["method"] == method]
        if pts:
            ax.plot([r["robots"] for r in pts], [r["decision_ms"] for r in pts], marker="o", label=method)
    ax.set_yscale("log")
    ax.set_xlabel("robots N (MUSEUM)")
    ax.set_ylabel("decision time per team step (ms)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "fig8.png", dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------- fig5
def fig5(root: Path, quick: bool) -> Path:
    """beta in {0.1, 0.3, 0.5, 0.7, 0.9} and 1 (PG) for a 4-robot team on OFFICE and MUSEUM (paper Fig. 5)."""
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk
    from shared.snapshot import load_snapshot

    episodes, train_eps, seed, N = (300 if quick else 1500), (10_000 if quick else 400_000), 1, 4
    rows = []
    for env in ("office", "museum"):
        g = builtin_graph(env)
        model, sensor = uniform_walk(g), Sensor()
        for beta in (0.1, 0.3, 0.5, 0.7, 0.9, 1.0):
            snap = load_snapshot(_snapshot(root, env, N, beta, train_eps, 0), g)
            rows.append({**_robust_cell(env, N, "pg" if beta == 1.0 else "cepg",
                                        _maker("policy", snap, g, model, sensor, N), episodes, seed, None),
                         "beta": beta})  # fmt: skip
    out = root / "fig5"
    _write(out, "fig5", {"experiment": "fig5", "quick": quick, "episodes": episodes, "training_episodes": train_eps,
                         "seed": seed, "robots": N, "machine": machine()}, rows)  # fmt: skip
    _bars(out / "fig5.png", rows, "beta", "capture time (steps), N = 4")
    return out


# ---------------------------------------------------------------------- fig12 / fig13
def _robust_cell(env: str, N: int, method: str, make: Callable[[int], Any], episodes: int, seed: int,
                 withdraw_at: list[int | None] | None) -> dict[str, Any]:  # fmt: skip
    from shared.evaluate import evaluate
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk

    g = builtin_graph(env)
    s = evaluate(g, uniform_walk(g), Sensor(), N, make, episodes=episodes, seed=seed, withdraw_at=withdraw_at).summary()
    return {"map": env, "robots": N, "method": method, "episodes": episodes, "seed": seed,
            "withdrawn": "none" if not withdraw_at or all(w is None for w in withdraw_at) else
            ",".join(f"r{i + 1}@t{w}" for i, w in enumerate(withdraw_at) if w is not None),
            "mean_capture_time": round(s["mean_capture_time"], 3), "ci95_halfwidth": round(s["ci95_halfwidth"], 3),
            "censored_fraction": round(s["censored_fraction"], 4)}  # fmt: skip


def fig12(root: Path, quick: bool) -> Path:
    """Robustness: a 4-robot team loses robot 4 at t = 5 (paper Fig. 12), against the intact team."""
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk
    from shared.snapshot import load_snapshot

    episodes, train_eps, seed, N = (300 if quick else 1500), (10_000 if quick else 400_000), 1, 4
    rows = []
    for env in ("office", "museum"):
        g = builtin_graph(env)
        model, sensor = uniform_walk(g), Sensor()
        for withdraw in (None, [None, None, None, 5]):
            for name in ("random", "greedy"):
                rows.append(_robust_cell(env, N, name, _maker("ref", name, g, model, sensor, N), episodes, seed,
                                         withdraw))  # fmt: skip
            for label, beta in (("pg", 1.0), ("cepg", 0.5)):
                snap = load_snapshot(_snapshot(root, env, N, beta, train_eps, 0), g)
                rows.append(_robust_cell(env, N, label, _maker("policy", snap, g, model, sensor, N), episodes, seed,
                                         withdraw))  # fmt: skip
    out = root / "fig12"
    _write(out, "fig12", {"experiment": "fig12", "quick": quick, "episodes": episodes, "training_episodes": train_eps,
                          "seed": seed, "machine": machine()}, rows)  # fmt: skip
    _bars(out / "fig12.png", rows, "withdrawn", "capture time (steps), N = 4")
    return out


def fig13(root: Path, quick: bool) -> Path:
    """Robustness: a team trained for 5 robots flown by k = 1..5 of them (paper Fig. 13), against teams
    trained for k."""
    from shared.graph import builtin_graph
    from shared.models import Sensor, uniform_walk
    from shared.snapshot import load_snapshot

    episodes, train_eps, seed = (300 if quick else 1500), (10_000 if quick else 400_000), 1
    rows = []
    for env in ("office", "museum"):
        g = builtin_graph(env)
        model, sensor = uniform_walk(g), Sensor()
        five = load_snapshot(_snapshot(root, env, 5, 0.5, train_eps, 0), g)
        for k in range(1, 6):
            rows.append({**_robust_cell(env, k, "cepg trained for 5", _maker("policy", five, g, model, sensor, k),
                                        episodes, seed, None), "trained_for": 5})  # fmt: skip
            own = load_snapshot(_snapshot(root, env, k, 0.5, train_eps, 0), g)
            rows.append({**_robust_cell(env, k, "cepg trained for k", _maker("policy", own, g, model, sensor, k),
                                        episodes, seed, None), "trained_for": k})  # fmt: skip
    out = root / "fig13"
    _write(out, "fig13", {"experiment": "fig13", "quick": quick, "episodes": episodes, "training_episodes": train_eps,
                          "seed": seed, "machine": machine()}, rows)  # fmt: skip
    _bars(out / "fig13.png", rows, "robots", "capture time (steps)")
    return out


def _bars(path: Path, rows: list[dict[str, Any]], key: str, ylabel: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, env in zip(axes, ("office", "museum"), strict=True):
        sel = [r for r in rows if r["map"] == env]
        groups = list(dict.fromkeys(r[key] for r in sel))
        methods = list(dict.fromkeys(r["method"] for r in sel))
        w = 0.8 / len(methods)
        for j, m in enumerate(methods):
            pts = [(i, r) for i, gk in enumerate(groups) for r in sel if r[key] == gk and r["method"] == m]
            ax.bar([i + j * w for i, _ in pts], [r["mean_capture_time"] for _, r in pts], w,
                   yerr=[r["ci95_halfwidth"] for _, r in pts], capsize=2, label=m)  # fmt: skip
        ax.set_xticks(np.arange(len(groups)) + 0.4 - w / 2, [str(gk) for gk in groups])
        ax.set_title(env.upper())
        ax.set_ylabel(ylabel)
    axes[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(name: str, root: Path, quick: bool) -> Path:
    if name == "fig4":
        return fig4(root, quick)
    if name == "fig5":
        return fig5(root, quick)
    if name == "fig12":
        return fig12(root, quick)
    if name == "fig13":
        return fig13(root, quick)
    if name in ("fig7", "fig8"):
        return fig7(root, quick) if name == "fig7" else fig7(root, quick).parent / "fig8"
    raise ValueError(f"experiment {name!r} is not implemented (have: {', '.join(EXPERIMENTS)})")


# ---------------------------------------------------------------------- report
def report(root: Path, out: Path) -> Path:
    """docs/results.md from the recorded results (tables, plots, setup, a reading computed from the data)."""
    lines = ["# Results", "", "Generated by `mures report` from the data under `results/`; do not edit by hand.",
             "Regenerate with `mures experiment NAME [--quick]` then `mures report`.", ""]  # fmt: skip
    rel = os.path.relpath(root, out.parent)
    f4 = root / "fig4" / "fig4.json"
    if f4.exists():
        d = json.loads(f4.read_text())
        lines += ["## Fig. 4: the toy (two robots, one step, A with 0.6, B with 0.4)", "",
                  f"Setup: {len(d['rows']) // 2} seeds per beta, reward {d['reward']!r}, quick={d['quick']}; "
                  f"{d['machine']['date']}.", "", "| beta | seeds | split (each robot >= 0.9 on a different node) |",
                  "| --- | --- | --- |"]  # fmt: skip
        for beta in (0.5, 1.0):
            rs = [r for r in d["rows"] if r["beta"] == beta]
            lines.append(f"| {beta} | {len(rs)} | {sum(r['split'] for r in rs)} |")
        lines += ["", f"![fig4]({rel}/fig4/fig4.png)", ""]
    f7 = root / "fig7" / "fig7.json"
    if f7.exists():
        d = json.loads(f7.read_text())
        rows = d["rows"]
        methods = list(dict.fromkeys(r["method"] for r in rows))
        lines += ["## Fig. 7: capture time of all methods, N = 1..5", "",
                  f"Setup: {d['episodes']} episodes per cell for random, greedy, pg, cepg and oracle; "
                  f"{d['planner_episodes']} for fhpe, milp and d-milp, {d['fhpe_sa_episodes']} for fhpe-sa "
                  f"(planners are slow; see Fig. 8); seed {d['seed']}; learned teams trained for "
                  f"{d['training_episodes']:,} episodes with EM-estimated beliefs (Gamma_hat_0 = I); horizons "
                  f"{d['horizons']}, discount {d['discount']}, MILP time limit {d['milp_time_limit_s']} s per solve "
                  f"(HiGHS); quick={d['quick']}; {d['machine']['cpus']} CPUs, {d['machine']['date']}; the whole "
                  f"grid took {d['wall_seconds']:.0f} s.", "",
                  "The planners (fhpe, fhpe-sa, milp, d-milp) and the oracle get the true target model and see all "
                  "robots' observations (centralised); pg and cepg robots use only their own observations and an "
                  "estimated model; oracle robots see the target (a lower bound, exact DP, N <= 2 only). fhpe is "
                  "not run for N > 3: the joint paths per decision exceed 10^6.", ""]  # fmt: skip
        for env in ("office", "museum"):
            Ns = sorted({r["robots"] for r in rows if r["map"] == env})
            lines += [f"### {env.upper()} (mean capture time ± 95% CI half-width, episodes)", "",
                      "| method | " + " | ".join(f"N={n}" for n in Ns) + " |",
                      "| --- |" + " --- |" * len(Ns)]  # fmt: skip
            for m in methods:
                cells = []
                for n in Ns:
                    r = next((x for x in rows if x["map"] == env and x["robots"] == n and x["method"] == m), None)
                    txt = (
                        "—"
                        if r is None
                        else f"{r['mean_capture_time']:.1f}"
                        + (f" ± {r['ci95_halfwidth']:.1f}" if math.isfinite(r["ci95_halfwidth"]) else "")
                    )
                    cells.append(txt if r is None else f"{txt} ({r['episodes']})")
                lines.append(f"| {m} | " + " | ".join(cells) + " |")
            lines.append("")
        lines += [f"![fig7]({rel}/fig7/fig7.png)", "", "### Reading (computed from the table)", "",
                  f"The learned teams here were trained for {d['training_episodes']:,} episodes, "
                  f"{100 * d['training_episodes'] / 400_000:.1f}% of the paper's budget of 400,000"
                  + (", and the planners ran on one to four episodes: a quick run, not the paper's protocol."
                     if d["quick"] else "."), ""]  # fmt: skip
        lines += _reading(rows)
        lines += ["", "## Fig. 8: decision time per team step", "",
                  "Milliseconds per team step, one episode at a time (batch 1), the simulator's step included "
                  "(about 0.1 ms), MUSEUM:", "", "| method | " + " | ".join(f"N={n}" for n in range(1, 6)) + " |",
                  "| --- |" + " --- |" * 5]  # fmt: skip
        for m in methods:
            cells = []
            for n in range(1, 6):
                r = next((x for x in rows if x["map"] == "museum" and x["robots"] == n and x["method"] == m), None)
                cells.append("—" if r is None else f"{r['decision_ms']:.3g}")
            lines.append(f"| {m} | " + " | ".join(cells) + " |")
        r4 = {r["method"]: r for r in rows if r["map"] == "museum" and r["robots"] == 4}
        if "cepg" in r4:
            ratios = [f"{m} / cepg = {r4[m]['decision_ms'] / r4['cepg']['decision_ms']:.0f}x"
                      for m in ("fhpe-sa", "milp", "d-milp") if m in r4]  # fmt: skip
            lines += ["", f"Decision-time ratios at N = 4 on MUSEUM: {', '.join(ratios)}."]
        lines += ["", f"![fig8]({rel}/fig8/fig8.png)", ""]
    robust = (
        ("fig5", "Fig. 5: beta of Eq. 9 (N = 4; beta = 1 is PG)", "beta"),
        ("fig12", "Fig. 12: one robot withdrawn during execution (N = 4)", "withdrawn"),
        ("fig13", "Fig. 13: a team trained for 5 robots, flown by k of them", "robots"),
    )
    for fig, title, key in robust:
        f = root / fig / f"{fig}.json"
        if not f.exists():
            continue
        d = json.loads(f.read_text())
        rows = d["rows"]
        lines += [
            f"## {title}",
            "",
            f"Setup: {d['episodes']} episodes per cell, seed {d['seed']}; learned teams "
            f"trained for {d['training_episodes']:,} episodes; quick={d['quick']}; {d['machine']['date']}.",
            "",
        ]
        for env in ("office", "museum"):
            sel = [r for r in rows if r["map"] == env]
            groups = list(dict.fromkeys(r[key] for r in sel))
            methods = list(dict.fromkeys(r["method"] for r in sel))
            lines += [f"{env.upper()}:", "", "| method | " + " | ".join(f"{key} {gk}" for gk in groups) + " |",
                      "| --- |" + " --- |" * len(groups)]  # fmt: skip
            for m in methods:
                cells = []
                for gk in groups:
                    r = next((x for x in sel if x[key] == gk and x["method"] == m), None)
                    cells.append("—" if r is None else f"{r['mean_capture_time']:.1f} ± {r['ci95_halfwidth']:.1f}")
                lines.append(f"| {m} | " + " | ".join(cells) + " |")
            lines.append("")
        lines += [f"![{fig}]({rel}/{fig}/{fig}.png)", ""]
    missing = [e for e in ("fig6", "fig9", "fig10", "fig11") if not (root / e).exists()]
    lines += ["## Not yet reproduced", "", ", ".join(missing) + ": no experiment code yet.", ""]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines), encoding="utf-8")
    return out


def _reading(rows: list[dict[str, Any]]) -> list[str]:
    out = []
    for env in ("office", "museum"):
        for n in sorted({r["robots"] for r in rows if r["map"] == env}):
            cell = {r["method"]: r for r in rows if r["map"] == env and r["robots"] == n}
            if "cepg" not in cell:
                continue
            c = cell["cepg"]
            better, worse, tied, few = [], [], [], []
            for m, r in cell.items():
                if m in ("cepg", "oracle"):
                    continue
                if r["episodes"] < 2 or not math.isfinite(r["ci95_halfwidth"]):
                    few.append(f"{m} {r['mean_capture_time']:.1f}")
                    continue
                gap = r["mean_capture_time"] - c["mean_capture_time"]
                sep = r["ci95_halfwidth"] + c["ci95_halfwidth"]
                (better if gap > sep else worse if gap < -sep else tied).append(f"{m} {r['mean_capture_time']:.1f}")
            line = f"- {env.upper()} N={n}: cepg {c['mean_capture_time']:.1f}"
            if better:
                line += f"; sooner than {', '.join(better)}"
            if worse:
                line += f"; later than {', '.join(worse)}"
            if tied:
                line += f"; not separated from {', '.join(tied)} (CIs overlap)"
            if few:
                line += f"; one episode only, not compared: {', '.join(few)}"
            if "oracle" in cell:
                line += f"; oracle bound {cell['oracle']['mean_capture_time']:.1f}"
            out.append(line + ".")
    return out
