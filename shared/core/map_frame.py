"""Where a pixel of a ROS occupancy-grid map lies in the map frame, and back: map_server's
convention (the origin is the map-frame pose of the image's lower-left pixel's corner; row 0 is
the image's top row). Used by the map import (shared/floorplan) and by a robot's backend that
looks its pose up in the regions image (robot_agent/nav2.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class MapFrame:
    """An image of ``height`` rows at ``resolution`` metres a pixel, its lower-left corner at
    ``origin`` = (x, y, yaw) in the map frame."""

    resolution: float
    origin: tuple[float, float, float]
    height: int

    def to_map(self, row: float, col: float) -> tuple[float, float]:
        """The map-frame point (metres) at the centre of pixel (row, col)."""
        dx, dy = (col + 0.5) * self.resolution, (self.height - row - 0.5) * self.resolution
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        return x0 + c * dx - s * dy, y0 + s * dx + c * dy

    def to_pixel(self, x: float, y: float) -> tuple[int, int]:
        """The (row, col) of the pixel holding map-frame point (x, y); may lie outside the image."""
        x0, y0, yaw = self.origin
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = c * (x - x0) + s * (y - y0), -s * (x - x0) + c * (y - y0)
        return self.height - 1 - math.floor(dy / self.resolution), math.floor(dx / self.resolution)
