"""A filmstrip of a closed-loop episode: the scene and wrist cameras every few seconds, one PNG, to see how it
failed.

A failure class says "held the named object, never placed it"; a strip shows whether it let go over the rim,
carried it to the wrong bin or pressed the fingers into a wall. `sudd eval --filmstrips` writes one per
failed policy episode. Rendering reads the sim state and changes nothing, so an episode with a strip runs
exactly as one without.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from sim.render import CameraRenderer
from sim.robot import WRIST_CAMERA
from sim.scene import SCENE_CAMERA

_CAPTION_H = 18
_GAP = 4
_BG = (24, 24, 28)
_FG = (235, 235, 235)


class Filmstrip:
    """An observer for `run_policy_episode`: keeps a frame of `cameras` (stacked top to bottom) every `every_s`
    of sim time (and the last one seen), each captioned with the sim time and how far the gripper is closed."""

    def __init__(self, every_s: float = 2.0, size: tuple[int, int] = (240, 180),
                 cameras: tuple[str, ...] = (SCENE_CAMERA, WRIST_CAMERA)):
        if every_s <= 0:
            raise ValueError(f"every_s = {every_s}: expected a positive interval in seconds")
        self.every_s, self.size, self.cameras = float(every_s), (int(size[0]), int(size[1])), tuple(cameras)
        self.frames: list[tuple[str, np.ndarray]] = []
        self._next = 0.0
        self._renderer: CameraRenderer | None = None
        self._world = None
        self._grabbed_t: float | None = None

    def __call__(self, world, inst) -> None:
        self._world = world
        if world.time + 1e-9 >= self._next:
            self._grab(world)
            while self._next <= world.time + 1e-9:  # the next multiple of every_s, however late this call
                self._next += self.every_s

    def _grab(self, world) -> None:
        if self._renderer is None:
            self._renderer = CameraRenderer(world, *self.size, shadows=False)
        closed = 100 * world.gripper_position()
        image = np.concatenate([self._renderer.rgb(c) for c in self.cameras], axis=0)
        self.frames.append((f"{world.time:.1f} s  closed {closed:.0f}%", image))
        self._grabbed_t = world.time

    def save(self, path: Path, title: str, columns: int = 8) -> Path:
        """Write the frames (plus the final state, if it was not the last frame) as a tiled PNG."""
        if self._world is not None and self._grabbed_t != self._world.time:
            self._grab(self._world)
        w, h = self.size[0], self.size[1] * len(self.cameras)
        n = max(1, len(self.frames))
        cols = min(columns, n)
        rows = -(-n // cols)
        header = 22
        sheet = Image.new("RGB", (cols * (w + _GAP) + _GAP, header + rows * (h + _CAPTION_H + _GAP) + _GAP), _BG)
        draw = ImageDraw.Draw(sheet)
        draw.text((_GAP, 5), title, fill=_FG)
        for k, (caption, frame) in enumerate(self.frames):
            r, c = divmod(k, cols)
            x0, y0 = _GAP + c * (w + _GAP), header + _GAP + r * (h + _CAPTION_H + _GAP)
            draw.text((x0 + 2, y0 + 3), caption, fill=_FG)
            sheet.paste(Image.fromarray(frame), (x0, y0 + _CAPTION_H))
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        sheet.save(path)
        return path

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
