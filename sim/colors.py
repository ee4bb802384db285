"""Named colour classes: the words a command uses ("the red block") and the range of shades each covers.

Domain randomization samples a shade inside the named class, so "red" stays red to a person while the
policy never sees one fixed RGB value. Classes are hue bands in HSV with saturation/value ranges.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ColorClass:
    name: str
    hue: tuple[float, float]  # degrees; may wrap (e.g. 350..10 for red)
    sat: tuple[float, float]
    val: tuple[float, float]

    @property
    def nominal(self) -> tuple[float, float, float]:
        h = _mid_hue(self.hue)
        return colorsys.hsv_to_rgb(h / 360.0, sum(self.sat) / 2, sum(self.val) / 2)


COLOR_CLASSES: dict[str, ColorClass] = {c.name: c for c in (
    ColorClass("red", (352.0, 8.0), (0.75, 0.95), (0.65, 0.9)),
    ColorClass("orange", (22.0, 34.0), (0.8, 0.95), (0.8, 0.95)),
    ColorClass("yellow", (50.0, 60.0), (0.75, 0.95), (0.8, 0.95)),
    ColorClass("green", (105.0, 140.0), (0.6, 0.85), (0.45, 0.75)),
    ColorClass("blue", (210.0, 230.0), (0.7, 0.9), (0.55, 0.85)),
    ColorClass("purple", (272.0, 290.0), (0.5, 0.75), (0.45, 0.7)),
    ColorClass("pink", (318.0, 335.0), (0.35, 0.55), (0.85, 0.97)),
    ColorClass("white", (0.0, 360.0), (0.0, 0.06), (0.88, 0.97)),
    ColorClass("black", (0.0, 360.0), (0.0, 0.1), (0.06, 0.14)),
)}


def get_color(name: str) -> ColorClass:
    try:
        return COLOR_CLASSES[name]
    except KeyError:
        raise ValueError(f"unknown colour {name!r}; expected one of {sorted(COLOR_CLASSES)}") from None


def sample_rgba(name: str, rng: np.random.Generator, spread: float) -> list[float]:
    """A shade of colour class `name`; spread 0 gives the class's nominal colour, 1 its full range."""
    cls = get_color(name)
    if spread <= 0.0:
        return [*cls.nominal, 1.0]
    h0, h1 = cls.hue
    width = (h1 - h0) % 360.0 if h1 != h0 + 360.0 else 360.0
    centre = _mid_hue(cls.hue)
    hue = (centre + (rng.uniform(-0.5, 0.5) * width * spread)) % 360.0
    sat = _around(cls.sat, rng, spread)
    val = _around(cls.val, rng, spread)
    return [*colorsys.hsv_to_rgb(hue / 360.0, sat, val), 1.0]


def _around(bounds: tuple[float, float], rng: np.random.Generator, spread: float) -> float:
    mid, half = (bounds[0] + bounds[1]) / 2, (bounds[1] - bounds[0]) / 2
    return float(mid + rng.uniform(-1.0, 1.0) * half * spread)


def _mid_hue(hue: tuple[float, float]) -> float:
    h0, h1 = hue
    if h1 - h0 >= 360.0:
        return 0.0
    return (h0 + ((h1 - h0) % 360.0) / 2) % 360.0


def classify_rgb(rgb) -> str:
    """The colour class whose nominal shade is nearest in HSV (used to check randomized colours stay named)."""
    h, s, v = colorsys.rgb_to_hsv(*rgb[:3])
    best, best_d = "", float("inf")
    for cls in COLOR_CLASSES.values():
        ch, cs, cv = colorsys.rgb_to_hsv(*cls.nominal)
        dh = min(abs(h - ch), 1 - abs(h - ch)) * min(s, cs) * 4
        d = dh ** 2 + (s - cs) ** 2 + (v - cv) ** 2
        if d < best_d:
            best, best_d = cls.name, d
    return best
