"""A figure's recorded data: results/<figure>/<figure>.json and .csv, its setup (``figure_setup``,
with the machine it ran on), and a figure recorded in several runs (`--add`), each covering some
(map, N) pairs, merged without losing rows (``refuse_loss``, ``_merge``)."""

from __future__ import annotations

import csv
import datetime as dt
import json
import os
import platform
from pathlib import Path
from typing import Any

from shared.core.files import atomic_write
from shared.tools.experiments.budget import MARL_DEFAULT, MARL_OWN, PAPER_MAPS, SEED, Budget


def machine() -> dict[str, Any]:
    """Where and when a figure ran, as its setup records it."""
    return {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


def write_figure(
    out: Path, name: str, data: dict[str, Any], rows: list[dict[str, Any]], add: bool = False
) -> list[dict[str, Any]]:
    """Write a figure's data under ``out``: ``name``.json (``data``, the setup, with the rows) and a
    CSV of its rows; returns the rows written. With ``add`` (`--add`) the rows recorded for maps and
    team sizes this run did not cover are kept beside the new ones, and ``parts`` lists each run's
    setup and the (map, N) it covers (``_merge``)."""
    recorded = out / f"{name}.json"
    if add and recorded.exists():
        data, rows = _merge(json.loads(recorded.read_text()), data, rows)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(recorded, json.dumps({**data, "rows": rows}, indent=1) + "\n")
    if rows:
        with open(out / f"{name}.csv", "w", newline="", encoding="utf-8") as fh:
            w = csv.DictWriter(fh, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))  # rows differ
            w.writeheader()
            w.writerows(rows)
    return rows


def refuse_loss(
    recorded: Path, old: dict[str, Any], data: dict[str, Any], rows: list[dict[str, Any]], add: bool
) -> None:
    """Raise a ValueError, naming what would be lost, where writing this run's rows would drop
    recorded ones without `--overwrite`: without `--add`, rows of maps and team sizes the run does
    not cover (a run narrowed with --maps or --robots would otherwise leave only its own), and a
    `--quick` run's rows in place of the paper's protocol rows of the same map and team size."""
    covers = covered_pairs(rows)
    new = {tuple(c) for c in covers}
    held = old.get("rows") or []
    if not add:
        dropped = [c for c in covered_pairs(held) if tuple(c) not in new]
        if dropped:
            raise ValueError(
                f"{recorded} holds rows of {describe_pairs(dropped)}, which this run does not cover: --add keeps them "
                "beside this run's, --overwrite drops them; nothing was run or written"
            )
    if data.get("quick"):
        runs = old.get("parts") or [{**old, "covers": covered_pairs(held)}]
        protocol = {tuple(c) for p in runs if p.get("quick") is False for c in p["covers"]}
        lost = [c for c in covers if tuple(c) in protocol]
        if lost:
            raise ValueError(
                f"{recorded} holds the paper's protocol rows of {describe_pairs(lost)}; a --quick run would replace "
                "them with its own: --results DIR writes elsewhere, --overwrite replaces them; "
                "nothing was run or written"
            )


def describe_pairs(covers: list[list[Any]]) -> str:
    """(map, N) pairs as 'OFFICE N = 1, 2; MUSEUM N = 4'."""
    by_map: dict[str, list[int]] = {}
    for env, N in covers:
        by_map.setdefault(env, []).append(N)
    return "; ".join(f"{env.upper()} N = {', '.join(map(str, Ns))}" for env, Ns in by_map.items())


def figure_order(env: str, N: int) -> tuple[int, int]:
    """Where a (map, N) goes in a figure: the paper's maps in its order (others after), then N."""
    return (PAPER_MAPS.index(env) if env in PAPER_MAPS else len(PAPER_MAPS), N)


def covered_pairs(rows: list[dict[str, Any]]) -> list[list[Any]]:
    """The (map, N) pairs a figure's rows hold, in ``figure_order`` order."""
    return [list(p) for p in sorted({(r["map"], r["robots"]) for r in rows}, key=lambda p: figure_order(*p))]


def _merge(
    old: dict[str, Any], setup: dict[str, Any], rows: list[dict[str, Any]]
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """A recorded figure with a new run's rows added: the new rows replace the recorded ones of
    the same (map, N), the others stay. The setup's top level is the new run's, with ``maps`` and
    ``team_sizes`` widened to all rows, and ``parts``: every run whose rows remain, its setup and
    the (map, N) pairs it still covers, oldest first."""
    covered = {(r["map"], r["robots"]) for r in rows}
    kept = [r for r in old["rows"] if (r["map"], r["robots"]) not in covered]
    earlier = old.get("parts") or [
        {**{k: v for k, v in old.items() if k != "rows"}, "covers": covered_pairs(old["rows"])}
    ]
    parts = []
    for p in earlier:
        still = [c for c in p["covers"] if tuple(c) not in covered]
        if still:
            parts.append({**p, "covers": still})
    parts.append({**setup, "covers": covered_pairs(rows)})
    merged = sorted(kept + rows, key=lambda r: figure_order(r["map"], r["robots"]))
    data = {**setup, "parts": parts}
    data["maps"] = list(dict.fromkeys(c[0] for c in covered_pairs(merged)))
    if "team_sizes" in setup:
        data["team_sizes"] = sorted({r["robots"] for r in merged})
    return data, merged


def maps_in(rows: list[dict[str, Any]]) -> list[str]:
    """The maps a figure's rows cover, the paper's first, in the paper's order."""
    have = list(dict.fromkeys(r["map"] for r in rows))
    return [m for m in PAPER_MAPS if m in have] + [m for m in have if m not in PAPER_MAPS]


def figure_setup(name: str, b: Budget, **extra: Any) -> dict[str, Any]:
    """A figure's setup as its JSON records it: the run's budget, ``extra``, and the machine."""
    return {
        "experiment": name,
        "quick": b.quick,
        "episodes": b.episodes,
        "training_episodes": b.train,
        "marl_training_episodes": b.marl_train or (MARL_OWN if b.marl_train_for else MARL_DEFAULT),
        **(
            {}
            if b.marl_train
            else {"marl_training_episodes_by_method": {m: b.marl_episodes(m) for m in b.marl_methods}}
        ),
        "seed": SEED,
        "maps": list(b.maps),
        **extra,
        "machine": machine(),
    }


def planner_setup(b: Budget) -> dict[str, Any]:
    """The planners' budget as the setup of a figure that flies them (fig7, fig11) records it."""
    return {
        "planner_episodes": b.planner,
        "fhpe_sa_episodes": b.planner_episodes("fhpe-sa"),
        "d_milp_episodes": b.planner_episodes("d-milp"),
        "milp_time_limit_s": b.milp_limit,
    }
