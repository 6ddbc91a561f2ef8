"""ROS occupancy-grid maps as map_server (Nav2's nav2_map_server) reads them: a YAML file naming an
image (PGM or PNG) and how to read it, turned into free, occupied and unknown pixels.

The YAML's keys: ``image`` (a path relative to the YAML), ``resolution`` (metres a pixel),
``origin`` ([x, y, yaw]: the map-frame pose of the image's lower-left pixel), ``negate`` (0 or 1),
``occupied_thresh`` and ``free_thresh`` (occupancy probabilities), ``mode`` (trinary, the default;
scale; raw). For trinary and scale a pixel's occupancy is p = (255 - v) / 255, or v / 255 when
negated, v its grey value (the mean of its colour channels): occupied when p > occupied_thresh,
free when p < free_thresh, unknown between (scale: a pixel not fully opaque is unknown). For raw,
the value is the occupancy in percent (0-100; above 100: unknown).

One departure: in trinary mode a pixel of grey 205 is unknown whatever the thresholds. map_saver
writes unknown cells as 205 (p = 0.196), and ROS 2's map_saver wrote free_thresh 0.25 into the
YAML until Nav2 fixed it (ros-navigation/navigation2#5278), so that map_server reads the unknown
space of such maps (nav2_bringup's depot among them) as free; here it stays unknown.

Arrays are (H, W) with row 0 the image's top row, as in the image file.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from PIL import Image, UnidentifiedImageError

from shared.core.map_frame import MapFrame

MODES = ("trinary", "scale", "raw")
SAVER_UNKNOWN = 205  # the grey map_saver writes for an unknown cell
MAX_MAP_PIXELS = 50_000_000  # the largest image the import reads (about 7000 x 7000 px; ~2 GB while segmenting)
RESOLUTION_RANGE_M = (0.001, 1.0)  # metres a pixel a building's map can have (Nav2's are 0.02-0.1)


class MapError(ValueError):
    """A map that cannot be read, with one line that says why."""


@dataclass(frozen=True)
class OccupancyGrid:
    """A map's pixels: ``free`` and ``occupied`` (H, W) bools (neither: unknown), row 0 the top."""

    free: np.ndarray
    occupied: np.ndarray
    resolution: float  # metres a pixel
    origin: tuple[float, float, float]  # the lower-left pixel's corner in the map frame (x, y, yaw)
    source: dict[str, Any]  # the YAML's settings, the image's name and sha256

    @property
    def shape(self) -> tuple[int, int]:
        return self.free.shape

    @property
    def frame(self) -> MapFrame:
        return MapFrame(self.resolution, self.origin, self.free.shape[0])

    def to_map_frame(self, row: float, col: float) -> tuple[float, float]:
        """The map-frame point (metres) at the centre of pixel (row, col)."""
        return self.frame.to_map(row, col)

    def to_pixel(self, x: float, y: float) -> tuple[int, int]:
        """The (row, col) of the pixel holding map-frame point (x, y); may lie outside the image."""
        return self.frame.to_pixel(x, y)


def read_map(yaml_path: str | Path) -> OccupancyGrid:
    """The map described by ``yaml_path``; MapError (one line) for anything that cannot be read."""
    path = Path(yaml_path)
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise MapError(f"{path}: no such map file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise MapError(f"{path}: cannot read it: {exc}") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" (line {where.line + 1})" if where is not None else ""
        raise MapError(f"{path}: not valid YAML{line}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(raw, dict):
        raise MapError(f"{path}: expected a YAML mapping with image, resolution and origin")
    settings = _settings(path, raw)
    image_path = (path.parent / settings["image"]).resolve()
    value, opaque = _pixels(image_path, path)
    free, occupied = _classify(value, opaque, settings)
    if not free.any():
        raise MapError(f"{path}: no free pixel in {settings['image']}: nothing a robot could search")
    source = {
        "map": path.name,
        "image": settings["image"],
        "image_sha256": hashlib.sha256(image_path.read_bytes()).hexdigest(),
        **{k: settings[k] for k in ("resolution", "origin", "negate", "occupied_thresh", "free_thresh", "mode")},
    }
    return OccupancyGrid(
        free=free,
        occupied=occupied,
        resolution=settings["resolution"],
        origin=tuple(settings["origin"]),
        source=source,
    )


def _settings(path: Path, raw: dict[str, Any]) -> dict[str, Any]:
    """The YAML's settings, checked, with map_server's defaults."""

    def number(key: str, v: Any) -> float:
        if isinstance(v, str):  # YAML 1.1 (PyYAML) reads 1e-9 as a string; map_server's yaml-cpp as a number
            with contextlib.suppress(ValueError):
                v = float(v)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise MapError(f"{path}: '{key}' must be a number, got {v!r}")
        return float(v)

    image = raw.get("image")
    if not isinstance(image, str) or not image:
        raise MapError(f"{path}: 'image' must name the map's image file")
    resolution = number("resolution", raw.get("resolution"))
    low, high = RESOLUTION_RANGE_M
    if not low <= resolution <= high:
        raise MapError(
            f"{path}: 'resolution' is {resolution:g} metres a pixel; a building's map has {low:g} to {high:g} "
            "(Nav2's maps: 0.05)"
        )
    origin = raw.get("origin")
    if not isinstance(origin, list) or len(origin) != 3:
        raise MapError(f"{path}: 'origin' must be [x, y, yaw], got {origin!r}")
    origin = [number("origin", v) for v in origin]
    negate = raw.get("negate", 0)
    if negate not in (0, 1):
        raise MapError(f"{path}: 'negate' must be 0 or 1, got {negate!r}")
    occupied = number("occupied_thresh", raw.get("occupied_thresh", 0.65))
    free = number("free_thresh", raw.get("free_thresh", 0.25))
    if not 0.0 <= free <= occupied <= 1.0:
        raise MapError(f"{path}: need 0 <= free_thresh <= occupied_thresh <= 1, got {free} and {occupied}")
    mode = raw.get("mode", "trinary")
    if mode not in MODES:
        raise MapError(f"{path}: 'mode' must be one of {', '.join(MODES)}, got {mode!r}")
    return {
        "image": image,
        "resolution": resolution,
        "origin": origin,
        "negate": int(negate),
        "occupied_thresh": occupied,
        "free_thresh": free,
        "mode": mode,
    }


def _pixels(image_path: Path, yaml_path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(grey value (H, W) float in [0, 255], fully opaque (H, W) bool) of the map's image."""
    try:
        with Image.open(image_path) as im:
            width, height = im.size
            if width * height > MAX_MAP_PIXELS:
                raise MapError(
                    f"{yaml_path}: its image {image_path.name} is {width} x {height} px; the import reads at most "
                    f"{MAX_MAP_PIXELS / 1e6:g} million pixels: crop it to the building, or save it at a coarser "
                    "resolution (and the YAML's resolution with it)"
                )
            im.load()
            bands = im.getbands()
            alpha = np.asarray(im.getchannel("A")) if "A" in bands else None
            if im.mode in ("I", "I;16", "F"):  # 16-bit or float grey: scaled to 0-255
                arr = np.asarray(im, dtype=np.float64)
                top = 65535.0 if im.mode.startswith("I") else max(float(arr.max()), 1.0)
                value = arr * (255.0 / top)
            else:
                colour = im.convert("RGB") if bands not in (("L",), ("P",)) else im.convert("L")
                value = np.asarray(colour, dtype=np.float64)
                if value.ndim == 3:
                    value = value.mean(axis=2)
    except FileNotFoundError:
        raise MapError(f"{yaml_path}: its image {image_path.name} is missing ({image_path})") from None
    except Image.DecompressionBombError as exc:  # its header claims more pixels than PIL opens at all
        raise MapError(
            f"{yaml_path}: its image {image_path.name} is too large to read ({exc}); the import reads at most "
            f"{MAX_MAP_PIXELS / 1e6:g} million pixels"
        ) from None
    except MapError:
        raise
    except (UnidentifiedImageError, OSError, ValueError) as exc:
        raise MapError(f"{yaml_path}: its image {image_path.name} cannot be read: {exc}") from None
    if value.ndim != 2 or min(value.shape) < 1:
        raise MapError(f"{yaml_path}: its image {image_path.name} has no pixels")
    opaque = np.ones(value.shape, dtype=bool) if alpha is None else alpha == 255
    return value, opaque


def _classify(value: np.ndarray, opaque: np.ndarray, s: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(free, occupied) as map_server reads the pixels under the YAML's settings ``s``."""
    if s["mode"] == "raw":
        percent = np.rint(value)
        known = percent <= 100
        p = percent / 100.0
        return known & (p < s["free_thresh"]), known & (p > s["occupied_thresh"])
    p = value / 255.0 if s["negate"] else (255.0 - value) / 255.0
    known = opaque if s["mode"] == "scale" else np.rint(value) != SAVER_UNKNOWN
    return known & (p < s["free_thresh"]), known & (p > s["occupied_thresh"])
