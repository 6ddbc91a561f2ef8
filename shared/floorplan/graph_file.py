"""A segmented map written out: the fleet's graph file (docs/SPEC.md section 7), the regions
image, and a preview to check the segmentation by eye."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from shared.floorplan.occupancy import OccupancyGrid
from shared.floorplan.rooms import Regions


def graph_dict(grid: OccupancyGrid, regions: Regions, name: str, parameters: dict[str, Any]) -> dict[str, Any]:
    """The graph file: node k for region k (labels 0..n-1), an edge per passage, each node's
    position in the map frame (metres), the start node, and where it came from ("source": the
    map, its image's sha256, the import's parameters, each edge's passage width)."""
    positions = {str(k): [round(v, 3) for v in grid.to_map_frame(*c)] for k, c in enumerate(regions.centers)}
    return {
        "name": name,
        "nodes": list(range(len(regions.centers))),
        "edges": [[i, j] for i, j, _w in regions.edges],
        "start_node": regions.start,
        "positions": positions,
        "source": {
            **grid.source,
            "importer": "mures map import",
            "parameters": parameters,
            "clearance_m": [round(c, 3) for c in regions.clearance],
            "passage_width_m": [round(w, 3) for _i, _j, w in regions.edges],
            "notes": regions.notes,
        },
    }


def write_regions(path: str | Path, labels: np.ndarray) -> None:
    """A 16-bit greyscale PNG of the map's size: node index + 1 on the building's free pixels, 0
    elsewhere; row 0 the image's top row, as in the map's image."""
    if labels.max() > 65535:
        raise ValueError(f"{labels.max()} regions do not fit a 16-bit image")
    Image.fromarray(labels.astype(np.uint16)).save(path)


def write_preview(path: str | Path, grid: OccupancyGrid, regions: Regions) -> None:
    """The map with each region in its colour, its node (a dot, with its label) and the edges."""
    rng = np.random.default_rng(7)
    palette = rng.integers(90, 246, size=(len(regions.centers) + 1, 3)).astype(np.uint8)
    rgb = np.full((*grid.shape, 3), 205, dtype=np.uint8)  # unknown: map_server's grey
    rgb[grid.free] = 254
    rgb[regions.labels > 0] = palette[regions.labels[regions.labels > 0]]
    rgb[grid.occupied] = 0
    scale = max(1, round(600 / max(grid.shape)))  # small maps drawn larger
    im = Image.fromarray(rgb).resize((grid.shape[1] * scale, grid.shape[0] * scale), Image.Resampling.NEAREST)
    draw = ImageDraw.Draw(im)
    at = [((c + 0.5) * scale, (r + 0.5) * scale) for r, c in regions.centers]
    for i, j, _w in regions.edges:
        draw.line([at[i], at[j]], fill=(200, 0, 0), width=max(1, scale))
    dot = 3 * max(1, scale)
    for k, (x, y) in enumerate(at):
        colour = (0, 140, 0) if k == regions.start else (0, 0, 200)
        draw.ellipse([x - dot, y - dot, x + dot, y + dot], fill=colour)
        draw.text((x + dot + 1, y - dot), str(k), fill=(0, 0, 0))
    im.save(path)
