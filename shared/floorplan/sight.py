"""What a robot on a pose sees: the free pixels within a range in line of sight, as the continuous
world senses (shared/world/continuous.py), and the graph's sensing table made from it (`mures map
import --sensor-range`: the nodes whose pose each node's robot sees, D(p) for --detection custom)."""

from __future__ import annotations

import math

import numpy as np
from skimage.draw import line


def view(free: np.ndarray, px: tuple[int, int], range_m: float, res: float) -> tuple[int, int, np.ndarray]:
    """What a robot on pixel ``px`` sees: rays to every pixel of the window's border, each until its
    first pixel that is not free, within ``range_m``."""
    radius = max(1, math.ceil(range_m / res))
    r0, c0 = max(0, px[0] - radius), max(0, px[1] - radius)
    r1, c1 = min(free.shape[0], px[0] + radius + 1), min(free.shape[1], px[1] + radius + 1)
    win = np.zeros((r1 - r0, c1 - c0), dtype=bool)
    border = [(r, c) for r in (r0, r1 - 1) for c in range(c0, c1)] + [
        (r, c) for c in (c0, c1 - 1) for r in range(r0, r1)
    ]
    for r, c in border:
        rr, cc = line(px[0], px[1], r, c)
        inside = (rr - px[0]) ** 2 + (cc - px[1]) ** 2 <= radius**2
        ok = free[rr, cc] & inside
        stop = int(np.argmin(ok)) if not ok.all() else len(ok)
        win[rr[:stop] - r0, cc[:stop] - c0] = True
    return r0, c0, win


def sensing_sets(free: np.ndarray, node_px: np.ndarray, range_m: float, res: float) -> dict[int, list[int]]:
    """Per node row p, the rows whose pose (``node_px`` (n, 2) pixels) a robot on p's pose sees
    (``view``): D(p), p itself included."""
    out: dict[int, list[int]] = {}
    for p, px in enumerate(node_px.tolist()):
        r0, c0, win = view(free, (int(px[0]), int(px[1])), range_m, res)
        rr, cc = node_px[:, 0] - r0, node_px[:, 1] - c0
        inside = (rr >= 0) & (rr < win.shape[0]) & (cc >= 0) & (cc < win.shape[1])
        seen = np.zeros(len(node_px), dtype=bool)
        seen[inside] = win[rr[inside], cc[inside]]
        seen[p] = True
        out[p] = np.flatnonzero(seen).tolist()
    return out
