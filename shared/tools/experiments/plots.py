"""The figures' plots (matplotlib, Agg): one panel per map, one look per method in every plot."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from shared.tools.experiments.budget import PAPER_MAPS
from shared.tools.experiments.recording import maps_in


def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (files only, no display), imported when first plotted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# One look per method in every plot: the CE-PG family solid, the MARL baselines dashed, the
# planners dotted, the references (random, greedy, oracle) grey; 16 methods outrun a 10-colour cycle.
LOOKS = {
    "pg": ("tab:blue", "o", "-"),
    "cepg": ("tab:red", "o", "-"),
    "cepg+": ("tab:purple", "o", "-"),
    "c-cepg": ("tab:brown", "o", "-"),
    "maddpg": ("tab:pink", "s", "--"),
    "masac": ("tab:olive", "s", "--"),
    "facmac": ("tab:cyan", "s", "--"),
    "mambpo": ("tab:orange", "s", "--"),
    "mappo": ("tab:green", "s", "--"),
    "fhpe": ("#9467bd", "^", ":"),
    "fhpe-sa": ("#2ca02c", "^", ":"),
    "milp": ("#1f77b4", "^", ":"),
    "d-milp": ("#d62728", "^", ":"),
    "random": ("0.55", "x", "-."),
    "greedy": ("0.35", "+", "-."),
    "oracle": ("0.1", "*", "-."),
}


def style(method: str) -> dict[str, Any]:
    """matplotlib keywords of a method's line (``LOOKS``; others get the default cycle)."""
    if method not in LOOKS:
        return {"marker": "o"}
    color, marker, line = LOOKS[method]
    return {"color": color, "marker": marker, "linestyle": line}


def map_panels(plt: Any, rows: list[dict[str, Any]]) -> tuple[Any, list[tuple[Any, str]]]:
    """A figure with one panel per map of ``rows`` (``maps_in``): the figure and (axes, map) pairs."""
    maps = maps_in(rows) or list(PAPER_MAPS)
    fig, axes = plt.subplots(1, len(maps), figsize=(5.5 * len(maps), 4), squeeze=False)
    return fig, list(zip(axes[0], maps, strict=True))


def team_ticks(ax: Any, sizes: list[int]) -> None:
    """Team sizes on the x axis: a tick at each N drawn, half a robot of margin either side."""
    if sizes:
        ticks = sorted(set(sizes))
        ax.set_xticks(ticks)
        ax.set_xlim(ticks[0] - 0.5, ticks[-1] + 0.5)


def legend(fig: Any, axes: list[Any]) -> None:
    """Lay the panels out, then one legend for the whole figure, right of them, with every method any
    panel drew."""
    seen: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(label, handle)
    fig.tight_layout()
    fig.legend(list(seen.values()), list(seen), fontsize=8, loc="center left", bbox_to_anchor=(1.0, 0.5))


def team_size_lines(
    path: Path, rows: list[dict[str, Any]], value: str, ylabel: str, half: str | None = None, log: bool = False
) -> None:
    """One panel per map, a line per method over the team sizes N: ``value`` (with ``half`` as
    error bars when given; a log axis with ``log``). Fig. 7's capture times, Fig. 8's decision times."""
    plt = pyplot()

    fig, panels = map_panels(plt, rows)
    for ax, env in panels:
        for method in dict.fromkeys(r["method"] for r in rows):
            pts = [r for r in rows if r["map"] == env and r["method"] == method]
            if not pts:
                continue
            x, y = [r["robots"] for r in pts], [r[value] for r in pts]
            if half is None:
                ax.plot(x, y, label=method, **style(method))
            else:
                ax.errorbar(x, y, yerr=[r[half] for r in pts], capsize=3, label=method, **style(method))
        if log:
            ax.set_yscale("log")
        ax.set_title(env.upper())
        ax.set_xlabel("robots N")
        ax.set_ylabel(ylabel)
        team_ticks(ax, [r["robots"] for r in rows if r["map"] == env])
    legend(fig, [ax for ax, _ in panels])
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def bars(path: Path, rows: list[dict[str, Any]], key: str, ylabel: str) -> None:
    """One panel per map, a group of bars per value of ``key``, a bar per method (capture time, CI)."""
    plt = pyplot()

    fig, panels = map_panels(plt, rows)
    for ax, env in panels:
        sel = [r for r in rows if r["map"] == env]
        groups = list(dict.fromkeys(r[key] for r in sel))
        methods = list(dict.fromkeys(r["method"] for r in sel))
        w = 0.8 / len(methods)
        for j, m in enumerate(methods):
            pts = [(i, r) for i, gk in enumerate(groups) for r in sel if r[key] == gk and r["method"] == m]
            ax.bar(
                [i + j * w for i, _ in pts],
                [r["mean_capture_time"] for _, r in pts],
                w,
                yerr=[r["ci95_halfwidth"] for _, r in pts],
                capsize=2,
                label=m,
                color=style(m).get("color"),
            )
        ax.set_xticks(np.arange(len(groups)) + 0.4 - w / 2, [str(gk) for gk in groups])
        ax.set_xlabel(key)
        ax.set_title(env.upper())
        ax.set_ylabel(ylabel)
    legend(fig, [ax for ax, _ in panels])
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def lines_per_team_size(path: Path, rows: list[dict[str, Any]], key: str, value: str, ylabel: str) -> None:
    """One line per team size N: ``value`` (with its CI) against ``key``."""
    plt = pyplot()

    half = "ci95_halfwidth" if value == "mean_capture_time" else "false_alarms_ci95_halfwidth"
    fig, panels = map_panels(plt, rows)
    for ax, env in panels:
        for N in sorted({r["robots"] for r in rows if r["map"] == env}):
            pts = [r for r in rows if r["map"] == env and r["robots"] == N]
            ax.errorbar(
                [r[key] for r in pts],
                [r[value] for r in pts],
                yerr=[r[half] for r in pts],
                marker="o",
                capsize=3,
                label=f"N = {N}",
            )
        ax.set_title(env.upper())
        ax.set_xlabel(key)
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def learning_curves(path: Path, curves: dict[str, list[dict[str, Any]]]) -> None:
    """One panel per map: each MARL baseline's training episodes' capture time ("map/method" curves)."""
    plt = pyplot()

    maps = sorted({k.split("/")[0] for k in curves})
    fig, axes = plt.subplots(1, len(maps), figsize=(6 * len(maps), 4), squeeze=False)
    for ax, env in zip(axes[0], maps, strict=True):
        for key, pts in curves.items():
            if key.startswith(env + "/") and pts:
                ax.plot([p["episodes"] for p in pts], [p["mean_capture_time"] for p in pts], label=key.split("/")[1])
        ax.set_title(f"{env.upper()}, N = 4: training episodes' capture time")
        ax.set_xlabel("training episodes")
        ax.set_ylabel("capture time (steps)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
