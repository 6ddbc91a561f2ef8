"""A map's free space cut into rooms and areas, the nodes of the fleet's graph, and the passages
between them, its edges.

1. **Free space.** The free pixels, their specks of obstacle smaller than ``CLUTTER_M2`` filled
   (scan noise and small furniture do not split a room); their connected parts (8-neighbours):
   the largest is the building. Parts enclosed by it (inside furniture outlines) are dropped, and
   so are pockets apart from it that are small next to it (under ``POCKET_SHARE`` of its area, or
   under ``PIECE_M2``: a closed closet, a scan's stray cells), their areas named in a note; a
   larger part makes the map "in pieces" (an error unless ``largest_part``).
2. **Rooms** (morphological segmentation, as in Bormann et al., "Room segmentation: survey,
   implementation, and analysis", ICRA 2016): the distance of each free pixel to the nearest
   non-free one (its clearance); the pixels with clearance above half of ``max_door_m`` are the
   rooms' cores, which doorways narrower than ``max_door_m`` separate; cores smaller than
   ``CORE_M2`` are noise; a watershed of the clearance from the cores gives every free pixel a
   room (a free part no core reaches gets a room of its own).
3. **Areas**: a room wider than ``max_region_m`` (what a robot's sensor is taken to cover) is
   cut into k areas that each fit in a disc of that diameter, around k-means centres of its
   pixels, grown over the room (a watershed: areas stay connected).
4. **Nodes and edges**: a node per region at its point of largest clearance (a pose a robot can
   reach); an edge between two regions whose shared border is at least ``min_door_m`` wide (twice
   the largest clearance along it). Regions not reachable from the start through such passages
   are left out, and said so.

scikit-image and SciPy do the image work (distance transform, labelling, watershed, k-means).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.cluster.vq import kmeans2
from scipy.spatial import cKDTree
from skimage import morphology, segmentation

from shared.floorplan import MAX_DOOR_M, MAX_REGION_M, MIN_DOOR_M
from shared.floorplan.occupancy import MapError, OccupancyGrid

CLUTTER_M2 = 0.25  # obstacles smaller than this inside free space are filled (square metres)
PIECE_M2 = 1.0  # free parts apart from the building under this are always dropped (square metres)
POCKET_SHARE = 0.05  # and so are those under this share of the building's free area; larger: "in pieces"
MAX_NODES = 10_000  # the most nodes an imported graph may have (the engine's limit)
CORE_M2 = 0.5  # room cores smaller than this are noise
KMEANS_SAMPLE = 4000  # pixels of a room its areas' centres are fitted to
EIGHT = np.ones((3, 3), dtype=bool)  # pixels touch by a side or a corner


@dataclass
class Regions:
    """A segmented map: ``labels`` (H, W) int32, region index + 1 on every free pixel of the
    building and 0 elsewhere; ``rooms`` (H, W) the rooms before areas were cut; per region its
    ``centers`` (row, col) pixel and ``clearance`` (metres); ``edges`` (i, j, width in metres)."""

    labels: np.ndarray
    rooms: np.ndarray
    centers: list[tuple[int, int]]
    clearance: list[float]
    edges: list[tuple[int, int, float]]
    start: int
    notes: list[str] = field(default_factory=list)  # what was dropped, and why


def segment(
    grid: OccupancyGrid,
    max_region_m: float = MAX_REGION_M,
    min_door_m: float = MIN_DOOR_M,
    max_door_m: float = MAX_DOOR_M,
    start_xy: tuple[float, float] | None = None,
    largest_part: bool = False,
    seed: int = 0,
) -> Regions:
    """The regions, nodes and edges of ``grid`` (module docstring); MapError (one line) when
    the map cannot make a graph."""
    if max_region_m <= 0 or min_door_m <= 0 or max_door_m <= 0:
        raise MapError("max_region_m, min_door_m and max_door_m must be positive")
    res = grid.resolution
    notes: list[str] = []
    free = building(grid, largest_part, notes)
    area_m2 = float(free.sum()) * res**2
    fewest = area_m2 / (math.pi / 4 * max_region_m**2)  # areas fitting in discs of max_region_m: at least these
    if fewest > MAX_NODES:
        wider = math.ceil(math.sqrt(area_m2 / (math.pi / 4 * MAX_NODES)))
        raise MapError(
            f"{area_m2:,.0f} m2 of free space cut into areas of at most {max_region_m:g} m gives over {MAX_NODES:,} "
            f"nodes (at least {fewest:,.0f}), more than the engine takes: use --max-region-m {wider} or more, or check "
            "the map's resolution"
        )
    clearance = ndimage.distance_transform_edt(free) * res  # metres to the nearest non-free pixel
    rooms = _rooms(free, clearance, max_door_m, res)
    labels = _areas(rooms, max_region_m, res, seed)
    start_label = _start_label(grid, labels, start_xy)
    labels, edges = _connected(labels, clearance, min_door_m, start_label, notes)
    labels = np.where(grid.free, labels, 0)  # filled clutter is no free pixel: no region's
    centers = _centers(labels)
    rooms = np.where(labels > 0, rooms, 0)
    start = int(labels[_start_pixel(grid, labels, start_xy)]) - 1
    return Regions(labels, rooms, centers, [float(clearance[c]) for c in centers], edges, start, notes)


def _centers(labels: np.ndarray) -> list[tuple[int, int]]:
    """Per region (label k + 1) the (row, col) of its pixel farthest from the region's border
    (walls and other regions alike): a pose deep inside it, as far from the walls as that."""
    border = labels == 0
    for axis in (0, 1):
        for shift in (1, -1):
            border |= labels != np.roll(labels, shift, axis=axis)
    inside = ndimage.distance_transform_edt(~border)
    n = int(labels.max())
    best = ndimage.maximum_position(inside, labels, index=np.arange(1, n + 1))
    return [(int(r), int(c)) for r, c in best]


def building(grid: OccupancyGrid, largest_part: bool, notes: list[str]) -> np.ndarray:
    """The building's free pixels (H, W) bool: clutter filled, its largest connected part. Free
    parts enclosed by it (inside shelving or furniture outlines) and pockets apart from it under
    max(PIECE_M2, POCKET_SHARE of its area) are dropped, with a note; a larger part is a MapError
    unless ``largest_part``."""
    res2 = grid.resolution**2
    free = morphology.remove_small_holes(grid.free, max_size=max(1, int(CLUTTER_M2 / res2)))
    parts, count = ndimage.label(free, structure=EIGHT)
    sizes = np.bincount(parts.ravel())[1:] * res2  # square metres per part
    biggest = int(np.argmax(sizes)) + 1
    main = parts == biggest
    enclosed = ndimage.binary_fill_holes(main)
    outside = [k for k in range(1, count + 1) if k != biggest and not enclosed[parts == k].all()]
    inside = count - 1 - len(outside)
    pocket_m2 = max(PIECE_M2, POCKET_SHARE * sizes[biggest - 1])
    large = sorted((sizes[k - 1] for k in outside if sizes[k - 1] >= pocket_m2), reverse=True)
    pockets = sorted((sizes[k - 1] for k in outside if sizes[k - 1] < pocket_m2), reverse=True)
    if large and not largest_part:
        raise MapError(
            f"the map's free space is in {len(large) + 1} pieces of at least {pocket_m2:.1f} m2 "
            f"({POCKET_SHARE:.0%} of the largest) ({sizes[biggest - 1]:.1f} m2 and "
            f"{', '.join(f'{a:.1f}' for a in large[:5])} m2): a robot cannot drive between them; "
            "--largest-part keeps the largest one only"
        )
    if count > 1:
        dropped = [f"{inside} enclosed by it (inside obstacles)"] if inside else []
        if pockets:
            shown = ", ".join(f"{a:.2g}" for a in pockets[:5]) + (", ..." if len(pockets) > 5 else "")
            dropped.append(
                f"{len(pockets)} pocket{'s' if len(pockets) != 1 else ''} apart from it ({shown} m2; under "
                f"{pocket_m2:.1f} m2, {POCKET_SHARE:.0%} of the building)"
            )
        if large:
            dropped.append(
                f"{len(large)} larger part{'s' if len(large) != 1 else ''} "
                f"({', '.join(f'{a:.1f}' for a in large[:5])} m2)"
            )
        notes.append(f"kept the largest free part ({sizes[biggest - 1]:.1f} m2); dropped " + " and ".join(dropped))
    return main


def _rooms(free: np.ndarray, clearance: np.ndarray, max_door_m: float, res: float) -> np.ndarray:
    """Room labels (H, W) int32 (1..R on free pixels): cores where the clearance exceeds half a
    doorway, grown over the free space by a watershed of the clearance."""
    cores, _ = ndimage.label(clearance > max_door_m / 2)
    sizes = np.bincount(cores.ravel())
    cores[sizes[cores] * res**2 < CORE_M2] = 0
    rooms = segmentation.watershed(-clearance, markers=cores, mask=free, connectivity=2)
    # free pixels no core reached (a narrow part of its own): a room each, seeded at their widest
    rest, count = ndimage.label(free & (rooms == 0), structure=EIGHT)
    top = int(rooms.max())
    for k in range(1, count + 1):
        rooms[rest == k] = top + k
    _, rooms = np.unique(rooms, return_inverse=True)  # 0 stays 0: free pixels are all labelled
    return rooms.reshape(free.shape).astype(np.int32)


def _areas(rooms: np.ndarray, max_region_m: float, res: float, seed: int) -> np.ndarray:
    """Region labels (H, W) int32: each room, or the k areas it is cut into when it does not fit
    in a disc of diameter ``max_region_m``."""
    out = np.zeros_like(rooms)
    top = 0
    radius_px = max_region_m / 2 / res
    for k, where in enumerate(ndimage.find_objects(rooms), 1):
        if where is None:
            continue
        mask = rooms[where] == k
        pts = np.argwhere(mask).astype(np.float64)
        parts = _cut(mask, pts, radius_px, seed)
        out[where][mask] = parts[mask] + top
        top += int(parts.max())
    return out


def _cut(mask: np.ndarray, pts: np.ndarray, radius_px: float, seed: int) -> np.ndarray:
    """Labels 1..k over ``mask`` (its bounding box): the fewest k-means areas whose pixels all lie
    within ``radius_px`` of their centre, each made connected (a pixel cut off from its area's
    main part goes to the area it touches)."""
    whole = np.zeros(mask.shape, dtype=np.int32)
    whole[mask] = 1
    if np.linalg.norm(pts - pts.mean(0), axis=1).max() <= radius_px:
        return whole
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(len(pts), size=min(len(pts), KMEANS_SAMPLE), replace=False)]
    k = max(2, math.ceil(len(pts) / (math.pi * radius_px**2)))
    while True:
        centres, _ = kmeans2(sample, k, minit="++", seed=seed)
        distance, nearest = cKDTree(centres).query(pts)
        far = float(distance.max())
        if far <= radius_px or k >= len(sample):
            break
        k = math.ceil(k * 1.2)
    parts = np.zeros(mask.shape, dtype=np.int32)
    parts[mask] = nearest + 1
    return _made_connected(parts, mask)


def _made_connected(parts: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``parts`` (labels over ``mask``) with each label's largest connected piece kept and its
    other pieces grown over by the pieces kept (a watershed), renumbered 1..k."""
    markers = np.zeros_like(parts)
    for k, where in enumerate(ndimage.find_objects(parts), 1):
        if where is None:
            continue
        pieces, count = ndimage.label(parts[where] == k, structure=EIGHT)
        if count:
            main = int(np.argmax(np.bincount(pieces.ravel())[1:])) + 1
            markers[where][pieces == main] = k
    grown = segmentation.watershed(np.zeros(mask.shape), markers=markers, mask=mask, connectivity=2)
    _, grown = np.unique(grown, return_inverse=True)
    return grown.reshape(mask.shape).astype(np.int32)


def _fits(parts: np.ndarray, radius_px: float) -> bool:
    """Every part's pixels lie within ``radius_px`` of its centre."""
    for k, where in enumerate(ndimage.find_objects(parts), 1):
        pts = np.argwhere(parts[where] == k)
        if len(pts) and np.linalg.norm(pts - pts.mean(0), axis=1).max() > radius_px:
            return False
    return True


def _start_pixel(grid: OccupancyGrid, labels: np.ndarray, start_xy: tuple[float, float] | None) -> tuple[int, int]:
    """The start's pixel: ``start_xy`` (map frame), else the map frame's origin when it is in
    the building (where SLAM began), else the building's pixel of largest clearance."""
    h, w = labels.shape
    for xy in (start_xy, (0.0, 0.0)):
        if xy is None:
            continue
        r, c = grid.to_pixel(*xy)
        if 0 <= r < h and 0 <= c < w and labels[r, c] > 0:
            return r, c
        if xy is start_xy:
            raise MapError(f"--start {xy[0]:g},{xy[1]:g} is not on the building's free space")
    dist = ndimage.distance_transform_edt(labels > 0)
    best = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return int(best[0]), int(best[1])


def _start_label(grid: OccupancyGrid, labels: np.ndarray, start_xy: tuple[float, float] | None) -> int:
    return int(labels[_start_pixel(grid, labels, start_xy)])


def passages(labels: np.ndarray, clearance: np.ndarray) -> dict[tuple[int, int], float]:
    """{(a, b): width in metres} for every pair of labels a < b that touch (4-neighbours): twice
    the largest clearance along their shared border."""
    out: dict[tuple[int, int], float] = {}
    for a_lab, b_lab, a_cl, b_cl in (
        (labels[:, :-1], labels[:, 1:], clearance[:, :-1], clearance[:, 1:]),
        (labels[:-1, :], labels[1:, :], clearance[:-1, :], clearance[1:, :]),
    ):
        touch = (a_lab != b_lab) & (a_lab > 0) & (b_lab > 0)
        a, b = a_lab[touch], b_lab[touch]
        width = 2 * np.minimum(a_cl[touch], b_cl[touch])
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        for u, v, wdt in zip(lo.tolist(), hi.tolist(), width.tolist(), strict=True):
            if wdt > out.get((u, v), -1.0):
                out[u, v] = wdt
    return out


def _connected(
    labels: np.ndarray, clearance: np.ndarray, min_door_m: float, start_label: int, notes: list[str]
) -> tuple[np.ndarray, list[tuple[int, int, float]]]:
    """Labels renumbered 1..n over the regions reachable from ``start_label`` through passages at
    least ``min_door_m`` wide (others set to 0), and the edges (i, j, width) between them (0-based)."""
    wide = {pair: w for pair, w in passages(labels, clearance).items() if w >= min_door_m}
    adjacency: dict[int, list[int]] = {}
    for u, v in wide:
        adjacency.setdefault(u, []).append(v)
        adjacency.setdefault(v, []).append(u)
    seen, todo = {start_label}, [start_label]
    while todo:
        for v in adjacency.get(todo.pop(), []):
            if v not in seen:
                seen.add(v)
                todo.append(v)
    total = int(labels.max())
    if len(seen) < total:
        notes.append(
            f"left out {total - len(seen)} of {total} regions: reachable only through passages "
            f"narrower than {min_door_m:g} m (--min-door-m)"
        )
    keep = sorted(seen)
    renumber = np.zeros(total + 1, dtype=np.int32)
    renumber[keep] = np.arange(1, len(keep) + 1)
    edges = sorted(
        (int(renumber[u]) - 1, int(renumber[v]) - 1, round(w, 3))
        for (u, v), w in wide.items()
        if u in seen and v in seen
    )
    return renumber[labels], edges
