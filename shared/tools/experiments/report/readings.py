"""What the recorded figures say against the paper's claims, computed from their rows: a paired
difference to CE-PG where the rows flew the same episodes, else whether the 95% CIs are disjoint."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

from shared.tools.experiments.recording import maps_in
from shared.tools.experiments.report.text import fmt_ci


def separation(
    r: dict[str, Any], base: dict[str, Any], value: str = "mean_capture_time", half: str = "ci95_halfwidth"
) -> tuple[float, float]:
    """(r - base, the margin it must exceed to count): CE-PG's paired difference and its CI
    half-width when ``r`` carries one (it flew CE-PG's episodes, and ``base`` is CE-PG's row), else
    the difference of the two values and the sum of their CI half-widths (the CIs must not overlap)."""
    if is_paired(r, base, value):
        return r["diff_to_cepg"], r["diff_to_cepg_ci95"]
    return r[value] - base[value], r[half] + base[half]


def is_paired(r: dict[str, Any], base: dict[str, Any], value: str = "mean_capture_time") -> bool:
    """Whether ``separation`` compares ``r`` with ``base`` by CE-PG's paired difference."""
    return "diff_to_cepg" in r and base.get("method") == "cepg" and value == "mean_capture_time"


def fig7_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig7's reading, a line per (map, N): the methods CE-PG captures sooner or later than, those
    not separated from it, and the oracle's bound."""
    out = []
    for env in maps_in(rows):
        for n in sorted({r["robots"] for r in rows if r["map"] == env}):
            cell = {r["method"]: r for r in rows if r["map"] == env and r["robots"] == n}
            if "cepg" not in cell:
                continue
            c = cell["cepg"]
            better: list[str] = []
            worse: list[str] = []
            tied: list[str] = []
            few: list[str] = []
            same: list[str] = []
            for m, r in cell.items():
                if m in ("cepg", "oracle"):
                    continue
                if r["episodes"] < 2 or not math.isfinite(r["ci95_halfwidth"]):
                    few.append(f"{m} {r['mean_capture_time']:.1f}")
                    continue
                if r.get("diff_to_cepg") == 0 and r.get("diff_to_cepg_ci95") == 0:
                    same.append(m)  # every paired difference 0: C-CE-PG at N = 1 is CE-PG
                    continue
                gap, sep = separation(r, c)
                text = f"{m} {r['mean_capture_time']:.1f}" + (
                    f" (paired {gap:+.2f} ± {sep:.2f})" if "diff_to_cepg" in r else ""
                )
                (better if gap > sep else worse if gap < -sep else tied).append(text)
            line = f"- {env.upper()} N={n}: cepg {c['mean_capture_time']:.1f}"
            if better:
                line += f"; sooner than {', '.join(better)}"
            if worse:
                line += f"; later than {', '.join(worse)}"
            if tied:
                line += f"; not separated from {', '.join(tied)}"
            if same:
                line += f"; the same capture time as CE-PG in every episode: {', '.join(same)}"
            if few:
                line += f"; one episode only, not compared: {', '.join(few)}"
            if "oracle" in cell:
                line += f"; oracle bound {cell['oracle']['mean_capture_time']:.1f}"
            out.append(line + ".")
    return out


def training_spread(root: Path, d: dict[str, Any]) -> list[str]:
    """fig7 flies one team per method and the CI is over episodes; how far a team moves with its
    training run, from fig5's recorded training seeds (beta 0.5 against PG, seed for seed)."""
    f5 = root / "fig5" / "fig5.json"
    if d["quick"] or not f5.exists():
        return []
    spans = []
    for r in json.loads(f5.read_text())["rows"]:
        per = r.get("diff_to_pg_per_seed") or []
        if r.get("beta") == 0.5 and len(per) > 1:
            spans.append(f"{r['map'].upper()} {min(per):+.2f} to {max(per):+.2f} over seeds {r['training_seeds']}")
    if not spans:
        return []
    seeds = sorted({s for r in d["rows"] for s in r.get("training_seeds") or []})
    return [
        f"Each method here is one team (training seed {', '.join(map(str, seeds))}), so a paired CI says "
        "that these teams differ, "
        "not that the methods do: another training run moves a team. In Fig. 5 (N = 4) CE-PG's (beta 0.5) "
        f"paired difference to PG ranges {'; '.join(spans)}; a difference here within that spread "
        "of zero may change sign with another training run.",
        "",
    ]


def variants_reading(rows: list[dict[str, Any]], root: Path) -> list[str]:
    """fig6 on one map against the paper's claim that CE-PG+ and C-CE-PG both capture sooner
    than CE-PG: from fig7's paired difference (same episodes) where fig7 flew these very cells
    (the same teams: a recorded fig7 may predate fig6's teams), else from whether the two 95%
    CIs are disjoint."""
    f7 = root / "fig7" / "fig7.json"
    f7_rows = {
        (r["map"], r["robots"], r["method"]): r for r in (json.loads(f7.read_text())["rows"] if f7.exists() else [])
    }
    same = ("mean_capture_time", "ci95_halfwidth", "episodes", "seed", "train_episodes")

    def flown_by_fig7(r: dict[str, Any]) -> dict[str, Any] | None:
        q = f7_rows.get((r["map"], r["robots"], r["method"]))
        return q if q is not None and all(q.get(k) == r.get(k) for k in same) else None

    out = []
    for N in dict.fromkeys(r["robots"] for r in rows):
        base = next((r for r in rows if r["robots"] == N and r["method"] == "cepg"), None)
        if base is None:
            continue
        same_cepg = flown_by_fig7(base) is not None  # fig7's CE-PG row is this one
        said = []
        for m in ("cepg+", "c-cepg"):
            r = next((x for x in rows if x["robots"] == N and x["method"] == m), None)
            if r is None:
                continue
            # fig7's cell, paired with fig7's CE-PG: these teams on these episodes
            q = flown_by_fig7(r) if same_cepg else None
            if q is not None and not is_paired(q, base):
                q = None
            gap, sep = separation(q or r, base)
            if q is not None:
                how = f"fig7's paired difference {gap:+.2f} ± {sep:.2f}"
            else:
                ci = "disjoint" if abs(gap) > sep else "overlap"
                how = f"{r['mean_capture_time']:.2f} against {base['mean_capture_time']:.2f}, 95% CIs {ci}"
            verdict = (
                "captures sooner than"
                if gap < -sep
                else "captures later than"
                if gap > sep
                else "is not separated from"
            )
            said.append(f"{m} {verdict} CE-PG ({how})")
        if said:
            out.append(f"at N = {N}, " + "; ".join(said))
    if out:
        out = ["The paper: CE-PG+ and C-CE-PG both capture sooner than CE-PG. Here, " + "; ".join(out) + ".", ""]
    return out


def trend_reading(rows: list[dict[str, Any]], key: str, value: str, half: str) -> list[str]:
    """fig9 / fig10 on one map against the paper's claim that the value (capture time, false
    alarms) grows with the sensor's error rate ``key``: per team size, each step up in the rate
    and whether the two cells' 95% CIs are disjoint."""
    what = value.replace("_", " ")
    out = []
    for N in dict.fromkeys(r["robots"] for r in rows):
        sel = sorted((r for r in rows if r["robots"] == N), key=lambda r: r[key])
        steps = []
        for a, b in itertools.pairwise(sel):
            d, h = separation(b, a, value, half)
            word = "rises" if d > h else "falls" if d < -h else "the 95% CIs overlap"
            steps.append(f"{a[key]} -> {b[key]}: {word} ({a[value]:.2f} to {b[value]:.2f})")
        if steps:
            out.append(f"at N = {N}, " + "; ".join(steps))
    if not out:
        return []
    return [f"The paper: the {what} rises with {key}. Here, " + "; ".join(out) + ".", ""]


def unmoved_reading(rows: list[dict[str, Any]], key: str) -> list[str]:
    """fig10 on one map against the paper's other claim there: eta_fp (``key``) raises the false
    alarms but not the capture time. Per team size, the capture time at the lowest and the highest
    rate and whether their 95% CIs are disjoint."""
    out = []
    for N in dict.fromkeys(r["robots"] for r in rows):
        sel = sorted((r for r in rows if r["robots"] == N), key=lambda r: r[key])
        if len(sel) < 2:
            continue
        lo, hi = sel[0], sel[-1]
        d, h = separation(hi, lo)
        word = (
            "it rises (95% CIs disjoint)" if d > h else "it falls (95% CIs disjoint)" if d < -h else "95% CIs overlap"
        )
        out.append(
            f"at N = {N}, {key} {lo[key]} -> {hi[key]}: "
            f"{fmt_ci(lo['mean_capture_time'], lo['ci95_halfwidth'], lo['episodes'])} to "
            f"{fmt_ci(hi['mean_capture_time'], hi['ci95_halfwidth'], hi['episodes'])}, {word}"
        )
    if not out:
        return []
    return [f"The paper: {key} does not change the capture time. Here, " + "; ".join(out) + ".", ""]


def _rank(rows: list[dict[str, Any]], key: str, base_method: str, label: str = "", say: str = "") -> list[str]:
    """Per value of ``key``: ``base_method``'s rank by mean capture time among ``rows`` (cells of
    one episode, which have no CI, left out) and the rows that capture sooner, separated from it
    (``separation``: by the paired difference's 95% CI where the row flew CE-PG's episodes, else by
    disjoint CIs),
    as "SAY V: LABEL ranks R of M (mean ± h); sooner ..." phrases (SAY: ``say`` or the key)."""
    out = []
    for v in dict.fromkeys(r[key] for r in rows):
        sel = [r for r in rows if r[key] == v and r["episodes"] >= 2 and math.isfinite(r["ci95_halfwidth"])]
        base = next((r for r in sel if r["method"] == base_method), None)
        if base is None or len(sel) < 2:
            continue
        ranked = sorted(sel, key=lambda r: r["mean_capture_time"])
        rank = 1 + ranked.index(base)
        sooner = []
        for r in ranked[: rank - 1]:
            gap, sep = separation(r, base)
            if gap < -sep:
                how = f"paired {gap:+.2f} ± {sep:.2f}" if is_paired(r, base) else "CIs disjoint"
                sooner.append(f"{r['method']} {r['mean_capture_time']:.2f} ± {r['ci95_halfwidth']:.2f} ({how})")
        out.append(
            f"{say or key} {v}: {label or base_method} ranks {rank} of {len(ranked)} "
            f"({base['mean_capture_time']:.2f} ± {base['ci95_halfwidth']:.2f}); "
            + (f"sooner, separated: {', '.join(sooner)}" if sooner else "none is sooner and separated")
        )
    return out


def ranking_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig11 on one map against the paper's claim that CE-PG is among the three best methods at
    every eta_fn (MILP or D-MILP sometimes ahead of it): per eta_fn, CE-PG's rank among the
    methods that sense as it does (CE-PG+ senses N[p] and is left out) and those that capture
    sooner, separated from it (``_rank``)."""
    out = _rank([r for r in rows if r["method"] != "cepg+"], "eta_fn", "cepg")
    if not out:
        return []
    return [
        "The paper: CE-PG is among the three best methods at every eta_fn (MILP or D-MILP sometimes ahead). "
        "Here (cepg+, with its broader sensor, left out): " + "; ".join(out) + ".",
        "",
    ]


def dropout_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig13 on one map against the paper's claim that CE-PG does best of the MARL methods when
    robots of a 5-robot team drop out: per k flown, the 5-robot teams ranked (CE-PG's rank, and the
    teams that capture sooner, separated from it: ``_rank``). The teams trained for k are the table's
    reference, not part of the ranking."""
    five = [{**r, "method": r["method"].removesuffix(" trained for 5")} for r in rows if r["method"].endswith(" for 5")]
    out = _rank([r for r in five if r["robots"] < 5], "robots", "cepg", "cepg trained for 5", "k =")
    if not out:
        return []
    return [
        "The paper: CE-PG does best of the MARL methods when robots of a 5-robot team drop out. Here, of the "
        "teams trained for 5: " + "; ".join(out) + ".",
        "",
    ]


def withdrawal_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig12 on one map against the paper's claim that CE-PG does best of the learned methods
    when a robot is withdrawn: the lowest capture time and the runner-up (are their 95% CIs
    disjoint?), and how much each learned method's capture time rises over its intact team's."""
    intact = {r["method"]: r for r in rows if r["withdrawn"] == "none"}
    out = []
    for label in dict.fromkeys(r["withdrawn"] for r in rows if r["withdrawn"] != "none"):
        learned = sorted(
            (r for r in rows if r["withdrawn"] == label and r["method"] not in ("random", "greedy")),
            key=lambda r: r["mean_capture_time"],
        )
        if len(learned) < 2:
            continue
        best, second = learned[:2]
        gap, sep = separation(second, best)  # rows of one withdrawal: none carries a paired difference
        apart = gap > sep
        rises = ", ".join(
            f"{r['method']} {r['mean_capture_time'] - intact[r['method']]['mean_capture_time']:+.2f}"
            for r in learned
            if r["method"] in intact
        )
        out.append(
            f"With {label} withdrawn, {best['method']} captures soonest of the learned methods "
            f"({best['mean_capture_time']:.2f} ± {best['ci95_halfwidth']:.2f}), then {second['method']} "
            f"({second['mean_capture_time']:.2f} ± {second['ci95_halfwidth']:.2f}; 95% CIs "
            f"{'disjoint' if apart else 'overlap'}). Rise over the intact team: {rises}."
        )
    if not out:
        return []
    return ["The paper: CE-PG does best of the learned methods when a robot is withdrawn. " + " ".join(out), ""]


def beta_reading(rows: list[dict[str, Any]]) -> list[str]:
    """fig5's paired differences to beta = 1 on one map, and what they say."""
    diffs = [r for r in rows if "diff_to_pg" in r]
    if not diffs:
        return []
    seeds = diffs[0].get("training_seeds", [0])
    out = [
        f"Paired difference to beta = 1 (PG) of the same training seed (negative: CE-PG captures sooner), "
        f"training seeds {seeds}, each team on the same {diffs[0]['episodes']} episodes; 95% CI over the "
        "pooled episodes, and over the training seeds (Student t):",
        "",
        "| beta | difference | CI (episodes) | CI (seeds) | per seed |",
        "| --- | --- | --- | --- | --- |",
    ]
    for r in diffs:
        out.append(
            f"| {r['beta']} | {r['diff_to_pg']:+.2f} | ± {r['diff_to_pg_ci95_episodes']:.2f} | "
            f"± {r['diff_to_pg_ci95_seeds']:.2f} | {', '.join(f'{x:+.2f}' for x in r['diff_to_pg_per_seed'])} |"
        )
    sig = [r["beta"] for r in diffs if r["diff_to_pg"] + r["diff_to_pg_ci95_seeds"] < 0]
    worse = [r["beta"] for r in diffs if r["diff_to_pg"] - r["diff_to_pg_ci95_seeds"] > 0]
    if len(seeds) > 1:
        out += [
            "",
            "Across training seeds (a difference counts when its 95% CI over the seeds excludes 0): "
            + (f"beta in {sig} captures sooner than PG" if sig else "no beta < 1 captures sooner than PG")
            + (f"; beta in {worse} captures later" if worse else "")
            + ".",
        ]
    # the pooled-episode CI holds the teams fixed: it says these teams differ, not that training
    # with that beta does; reported too, so that a reader sees both
    ep_sooner = [r["beta"] for r in diffs if r["diff_to_pg"] + r["diff_to_pg_ci95_episodes"] < 0]
    ep_later = [r["beta"] for r in diffs if r["diff_to_pg"] - r["diff_to_pg_ci95_episodes"] > 0]
    if ep_sooner or ep_later:
        out += [
            "",
            "Over the pooled episodes (these teams, not the training's variation): "
            + "; ".join(
                x
                for x in (
                    f"beta in {ep_sooner} captures sooner than PG" if ep_sooner else "",
                    f"beta in {ep_later} captures later" if ep_later else "",
                )
                if x
            )
            + (
                f". With {len(seeds)} training seeds per beta that is not separated from the seed-to-seed spread."
                if len(seeds) > 1 and not (set(ep_sooner) & set(sig) or set(ep_later) & set(worse))
                else "."
            ),
        ]
    return [*out, ""]
