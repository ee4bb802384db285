"""Pinhole intrinsics shared by the sim cameras and the real RealSense, and the D435-like defaults."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera intrinsics in pixels (OpenCV convention: x right, y down, principal point cx, cy)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fovy(cls, width: int, height: int, fovy_deg: float) -> "Intrinsics":
        """Square pixels, centred principal point: what a MuJoCo camera with this vertical fov renders."""
        f = 0.5 * height / math.tan(math.radians(fovy_deg) / 2)
        return cls(width, height, f, f, (width - 1) / 2, (height - 1) / 2)

    @property
    def fovy_deg(self) -> float:
        return math.degrees(2 * math.atan(0.5 * self.height / self.fy))

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same lens at another resolution (RealSense streams scale this way)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5)

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


# RealSense D435 colour stream at 640x480: fx = fy ~ 615 px (vertical fov ~42.6 degrees).
D435_COLOR = Intrinsics(640, 480, 615.0, 615.0, 319.5, 239.5)
# Wide wrist camera (D405-like), used on the gripper.
WRIST_FOVY_DEG = 75.0
