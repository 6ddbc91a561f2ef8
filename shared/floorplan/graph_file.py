"""A segmented map written out: the fleet's graph file (docs/SPEC.md section 7), the regions
image, and a preview to check the segmentation by eye."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from shared.floorplan.occupancy import MapError, OccupancyGrid, read_map
from shared.floorplan.rooms import Regions
from shared.floorplan.travel import edge_lengths


def graph_dict(grid: OccupancyGrid, regions: Regions, name: str, parameters: dict[str, Any]) -> dict[str, Any]:
    """The graph file: node k for region k (labels 0..n-1), an edge per passage and its length
    along free space (metres, shared/floorplan/travel.py), each node's position in the map frame
    (metres), the start node, and where it came from ("source": the map, its image's sha256, the
    import's parameters, each edge's passage width)."""
    positions = {str(k): [round(v, 3) for v in grid.to_map_frame(*c)] for k, c in enumerate(regions.centers)}
    pairs = [(i, j) for i, j, _w in regions.edges]
    return {
        "name": name,
        "nodes": list(range(len(regions.centers))),
        "edges": [[i, j] for i, j in pairs],
        "edge_lengths_m": edge_lengths(regions.labels, regions.centers, pairs, grid.resolution),
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


def route_geojson(data: dict[str, Any]) -> dict[str, Any]:
    """The graph file ``data`` (graph_dict's) as Nav2's route server reads a graph (nav2_route's
    GeoJSON): a FeatureCollection of a Point feature per node (its id, frame "map", its position)
    and a MultiLineString feature per direction of each edge (its own id, startid, endid, and its
    length along free space as its cost); node ids are the graph's labels, edge ids follow the
    largest node id, so that every id is unique."""
    positions = data["positions"]
    lengths = data.get("edge_lengths_m") or [None] * len(data["edges"])
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "properties": {"id": int(v), "frame": "map"},
            "geometry": {"type": "Point", "coordinates": list(positions[str(v)])},
        }
        for v in data["nodes"]
    ]
    next_id = max(int(v) for v in data["nodes"]) + 1
    for (u, v), length in zip(data["edges"], lengths, strict=True):
        for a, b in ((u, v), (v, u)):  # the route server's edges are directed: both ways
            props: dict[str, Any] = {"id": next_id, "startid": int(a), "endid": int(b)}
            if length is not None:
                props["cost"] = length
                props["metadata"] = {"length_m": length}
            features.append(
                {
                    "type": "Feature",
                    "properties": props,
                    "geometry": {"type": "MultiLineString", "coordinates": [[positions[str(a)], positions[str(b)]]]},
                }
            )
            next_id += 1
    return {"type": "FeatureCollection", "name": data.get("name", "graph"), "features": features}


PICTURE_MAX_PX = 2048  # the longest side of the picture the console draws (larger maps are shrunk)


@dataclass(frozen=True)
class MapPicture:
    """A map as the console draws it under its graph: ``png`` (free white, occupied black, unknown
    grey, at most PICTURE_MAX_PX a side) and the map-frame ``bounds`` it covers (x_min, y_min,
    x_max, y_max, metres)."""

    png: bytes
    bounds: tuple[float, float, float, float]


def map_picture(yaml_path: str | Path, graph_source: dict[str, Any] | None) -> MapPicture:
    """The picture of the map ``yaml_path``; MapError when it cannot be read or its image is not
    the one the graph was imported from (``graph_source``: the graph file's "source")."""
    import io

    grid = read_map(yaml_path)
    if grid.origin[2] != 0:
        raise MapError(f"{yaml_path}: its origin's yaw is {grid.origin[2]:g}; the console draws maps of yaw 0 only")
    want = (graph_source or {}).get("image_sha256")
    if want and want != grid.source["image_sha256"]:
        raise MapError(
            f"{yaml_path}: its image is not the one this graph was imported from "
            f"(sha256 {grid.source['image_sha256'][:12]}..., the graph's {str(want)[:12]}...)"
        )
    grey = np.full(grid.shape, 205, dtype=np.uint8)
    grey[grid.free] = 255
    grey[grid.occupied] = 0
    im = Image.fromarray(grey)
    scale = PICTURE_MAX_PX / max(grid.shape)
    if scale < 1:
        im = im.resize(
            (max(1, round(grid.shape[1] * scale)), max(1, round(grid.shape[0] * scale))), Image.Resampling.BOX
        )
    buf = io.BytesIO()
    im.save(buf, format="PNG", optimize=True)
    h, w = grid.shape
    x_min, y_min = grid.to_map_frame(h - 0.5, -0.5)  # the lower-left pixel's outer corner
    x_max, y_max = grid.to_map_frame(-0.5, w - 0.5)  # the upper-right pixel's outer corner
    return MapPicture(buf.getvalue(), (x_min, y_min, x_max, y_max))


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
