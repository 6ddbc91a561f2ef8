"""The report's section on Fig. 4, the toy."""

from __future__ import annotations

import json
from pathlib import Path


def section(root: Path, rel: str) -> list[str]:
    """Fig. 4's table: per beta, how many seeds' robots split between the two nodes; ``rel``: the
    results directory relative to the report."""
    f4 = root / "fig4" / "fig4.json"
    if not f4.exists():
        return []
    d = json.loads(f4.read_text())
    lines = [
        "## Fig. 4: the toy (two robots, one step, A with 0.6, B with 0.4)",
        "",
        f"Setup: {len(d['rows']) // 2} seeds per beta, reward {d['reward']!r}, quick={d['quick']}; "
        f"{d['machine']['date']}.",
        "",
        "| beta | seeds | split (each robot >= 0.9 on a different node) |",
        "| --- | --- | --- |",
    ]
    for beta in (0.5, 1.0):
        rs = [r for r in d["rows"] if r["beta"] == beta]
        lines.append(f"| {beta} | {len(rs)} | {sum(r['split'] for r in rs)} |")
    lines += ["", f"![fig4]({rel}/fig4/fig4.png)", ""]
    return lines
