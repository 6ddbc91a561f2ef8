"""Synthetic office floors as a SLAM map shows them, with their true rooms, and the scores a room
segmentation is measured by (benchmarks/segmentation.py).

A floor is a corridor with a row of rooms on each side (offices, and open-plan rooms two or three
offices wide), each room with a door to the corridor and some with a door to the next room; walls
0.15 m thick; furniture (occupied blocks) in the rooms, clear of the doors; unexplored corners
(unknown); and scan noise (occupied specks in free space, ragged wall faces). Around the building
the map is unknown, as beyond a SLAM map's walls.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

FREE, OCCUPIED, UNKNOWN = 254, 0, 205  # map_server's trinary PGM values
WALL_M = 0.15


@dataclass
class Floor:
    """``image`` (H, W) uint8 PGM values (row 0 the top); ``rooms`` (H, W) int32: the true room + 1
    on every free pixel, 0 elsewhere; ``resolution`` metres a pixel."""

    image: np.ndarray
    rooms: np.ndarray
    resolution: float

    def write(self, directory: str | Path, name: str) -> Path:
        """``name``.pgm, ``name``.yaml (map_server's) and ``name``-rooms.png (the truth, 16-bit);
        returns the YAML's path."""
        d = Path(directory)
        d.mkdir(parents=True, exist_ok=True)
        Image.fromarray(self.image).save(d / f"{name}.pgm")
        Image.fromarray(self.rooms.astype(np.uint16)).save(d / f"{name}-rooms.png")
        yaml_path = d / f"{name}.yaml"
        yaml_path.write_text(
            f"image: {name}.pgm\nmode: trinary\nresolution: {self.resolution}\norigin: [0.0, 0.0, 0]\n"
            "negate: 0\noccupied_thresh: 0.65\nfree_thresh: 0.25\n"
        )
        return yaml_path


def office_floor(seed: int, resolution: float = 0.05) -> Floor:
    """A random office floor (module docstring), the same for the same ``seed``."""
    rng = np.random.default_rng(seed)
    px = lambda metres: max(1, round(metres / resolution))  # noqa: E731
    length, corridor = rng.uniform(24.0, 44.0), rng.uniform(1.8, 2.6)
    depth = (rng.uniform(4.0, 7.0), rng.uniform(4.0, 7.0))  # the rooms above and below the corridor
    margin, wall = px(1.0), px(WALL_M)
    H = margin * 2 + wall * 4 + px(depth[0]) + px(corridor) + px(depth[1])
    W = margin * 2 + wall * 2 + px(length)
    image = np.full((H, W), UNKNOWN, dtype=np.uint8)
    rooms = np.zeros((H, W), dtype=np.int32)
    image[margin : H - margin, margin : W - margin] = OCCUPIED  # the walls, then the spaces cut out
    _wing(image, rooms, rng, px, margin + wall, margin + wall, W - margin - wall, corridor, depth, 0)
    _scan_noise(image, rng)
    rooms[image != FREE] = 0
    return Floor(image=image, rooms=rooms, resolution=resolution)


def office_building(seed: int, size_m: float = 98.0, resolution: float = 0.05) -> Floor:
    """A square office building of ``size_m`` metres a side (a 98 m one is a 1,960 x 1,960 px map
    at 5 cm): wings of the office floor's kind (a corridor between two rows of rooms) stacked from
    top to bottom, their corridors joined by a hall along the building's left side; the same for the
    same ``seed``."""
    rng = np.random.default_rng(seed)
    px = lambda metres: max(1, round(metres / resolution))  # noqa: E731
    margin, wall, hall = px(1.0), px(WALL_M), px(2.4)
    size = px(size_m)
    image = np.full((size, size), UNKNOWN, dtype=np.uint8)
    rooms = np.zeros((size, size), dtype=np.int32)
    image[margin : size - margin, margin : size - margin] = OCCUPIED
    left = margin + wall + hall + wall  # the wings start right of the hall
    right, top, count = size - margin - wall, margin + wall, 1
    image[top : size - margin - wall, margin + wall : margin + wall + hall] = FREE  # the hall
    rooms[top : size - margin - wall, margin + wall : margin + wall + hall] = count
    while True:
        corridor, depth = rng.uniform(1.8, 2.6), (rng.uniform(4.0, 7.0), rng.uniform(4.0, 7.0))
        height = px(depth[0]) + px(corridor) + px(depth[1]) + 2 * wall
        if top + height > size - margin - wall:
            break
        first = count + 1
        count, row = _wing(image, rooms, rng, px, top, left, right, corridor, depth, count)
        image[row[0] : row[1], left - wall : left] = FREE  # the wing's corridor opens onto the hall
        rooms[row[0] : row[1], left - wall : left] = first
        top += height + wall
    _scan_noise(image, rng)
    rooms[image != FREE] = 0
    return Floor(image=image, rooms=rooms, resolution=resolution)


def _wing(
    image: np.ndarray,
    rooms: np.ndarray,
    rng: np.random.Generator,
    px,
    top: int,
    left: int,
    right: int,
    corridor: float,
    depth: tuple[float, float],
    count: int,
) -> tuple[int, tuple[int, int]]:
    """Cut a corridor between two rows of rooms into the walls of ``image`` from row ``top`` and
    columns ``left``..``right``, numbering the spaces from ``count`` + 1 in ``rooms``. Returns the
    last number given and the corridor's rows."""
    wall = px(WALL_M)
    bands = [  # (first row, last row + 1) of the upper rooms, the corridor, the lower rooms
        (top, top + px(depth[0])),
        (top + px(depth[0]) + wall, top + px(depth[0]) + wall + px(corridor)),
        (top + px(depth[0]) + 2 * wall + px(corridor), top + px(depth[0]) + 2 * wall + px(corridor) + px(depth[1])),
    ]
    count += 1
    image[bands[1][0] : bands[1][1], left:right] = FREE
    rooms[bands[1][0] : bands[1][1], left:right] = count  # the corridor
    for side, (r0, r1) in ((0, bands[0]), (2, bands[2])):
        door_row = (r1, r1 + wall) if side == 0 else (r0 - wall, r0)
        c0, previous = left, None
        while right - c0 > px(2.5):
            width = px(rng.uniform(3.0, 6.5) * (rng.choice([1, 2, 3], p=[0.75, 0.17, 0.08])))
            c1 = min(c0 + width, right)
            if right - c1 < px(2.5):
                c1 = right
            count += 1
            image[r0:r1, c0:c1] = FREE
            rooms[r0:r1, c0:c1] = count
            door = px(rng.uniform(0.8, 1.0))
            d0 = int(rng.integers(c0 + px(0.3), max(c0 + px(0.3) + 1, c1 - door - px(0.3))))
            image[door_row[0] : door_row[1], d0 : d0 + door] = FREE
            rooms[door_row[0] : door_row[1], d0 : d0 + door] = count
            if previous is not None and rng.random() < 0.3:  # a door to the room before
                e0 = int(rng.integers(r0 + px(0.5), max(r0 + px(0.5) + 1, r1 - door - px(0.5))))
                image[e0 : e0 + door, c0 - wall : c0] = FREE
                rooms[e0 : e0 + door, c0 - wall : c0] = count
            _furnish(image, rng, (r0, r1, c0, c1), (door_row, d0, door), px)
            previous, c0 = count, c1 + wall
    return count, bands[1]


def _furnish(image: np.ndarray, rng: np.random.Generator, box: tuple[int, int, int, int], door, px) -> None:
    """Furniture (0 to 4 blocks) and maybe an unexplored corner in the room ``box``, clear of its
    door (``door``: its rows, first column and width) by a metre."""
    r0, r1, c0, c1 = box
    (dr0, dr1), d0, dw = door
    keep_clear = (min(dr0, dr1) - px(1.2), max(dr0, dr1) + px(1.2), d0 - px(1.0), d0 + dw + px(1.0))
    for _ in range(int(rng.integers(0, 5))):
        h, w = px(rng.uniform(0.4, 1.2)), px(rng.uniform(0.4, 0.9))
        if rng.random() < 0.5:
            h, w = w, h
        if r1 - r0 <= h + 2 or c1 - c0 <= w + 2:
            continue
        a, b = int(rng.integers(r0, r1 - h)), int(rng.integers(c0, c1 - w))
        if a < keep_clear[1] and a + h > keep_clear[0] and b < keep_clear[3] and b + w > keep_clear[2]:
            continue
        image[a : a + h, b : b + w] = OCCUPIED
    if rng.random() < 0.3:  # a corner the scans never reached
        h, w = px(rng.uniform(0.4, 1.2)), px(rng.uniform(0.4, 1.2))
        a = r0 if rng.random() < 0.5 else r1 - h
        b = c0 if rng.random() < 0.5 else c1 - w
        if not (a < keep_clear[1] and a + h > keep_clear[0] and b < keep_clear[3] and b + w > keep_clear[2]):
            image[a : a + h, b : b + w] = UNKNOWN


def _scan_noise(image: np.ndarray, rng: np.random.Generator) -> None:
    """Occupied specks on 0.2 % of the free pixels, and ragged wall faces: a free pixel next to a
    wall turned occupied with probability 0.15."""
    free = image == FREE
    image[free & (rng.random(image.shape) < 0.002)] = OCCUPIED
    wall = image == OCCUPIED
    near = np.zeros_like(wall)
    near[1:, :] |= wall[:-1, :]
    near[:-1, :] |= wall[1:, :]
    near[:, 1:] |= wall[:, :-1]
    near[:, :-1] |= wall[:, 1:]
    image[free & near & (rng.random(image.shape) < 0.15)] = OCCUPIED


def segmentation_scores(truth: np.ndarray, found: np.ndarray) -> tuple[float, float]:
    """(recall, precision) of the room labels ``found`` against ``truth`` ((H, W), 0: no room),
    over the pixels both label (Bormann et al., ICRA 2016): recall is the mean over true rooms of
    the share of a room's area in its best-matching found room, precision the mean over found rooms
    of the share of its area in its best-matching true room."""
    both = (truth > 0) & (found > 0)
    t, f = truth[both].astype(np.int64), found[both].astype(np.int64)
    joint = np.bincount(t * (f.max() + 1) + f, minlength=(t.max() + 1) * (f.max() + 1)).reshape(t.max() + 1, -1)
    rows, cols = joint.sum(1), joint.sum(0)
    recall = np.mean([joint[i].max() / rows[i] for i in range(1, len(rows)) if rows[i]])
    precision = np.mean([joint[:, j].max() / cols[j] for j in range(1, len(cols)) if cols[j]])
    return float(recall), float(precision)
