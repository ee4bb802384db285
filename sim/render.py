"""Offscreen rendering of a World's cameras (colour and metric depth), headless through EGL or OSMesa."""

from __future__ import annotations

import mujoco
import numpy as np

from sim.camera_model import Intrinsics
from sim.fidelity import model_fidelity, render_settings


class CameraRenderer:
    """Renders named cameras of one world at one resolution; reuse it, since a GL context is costly."""

    def __init__(self, world, width: int, height: int, shadows: bool | None = None):
        """`shadows=None` follows the model's fidelity level (sim.fidelity): on for `full`, off for `fast`."""
        self.world = world
        if shadows is None:
            shadows = render_settings(model_fidelity(world.model)).shadows
        self.width, self.height = int(width), int(height)
        self._rgb = mujoco.Renderer(world.model, height=self.height, width=self.width)
        self._depth: mujoco.Renderer | None = None
        self.shadows = shadows
        self._option = mujoco.MjvOption()

    def intrinsics(self, camera: str) -> Intrinsics:
        fovy = float(self.world.model.cam_fovy[self.world.model.camera(camera).id])
        return Intrinsics.from_fovy(self.width, self.height, fovy)

    def _update(self, renderer: mujoco.Renderer, camera: str) -> None:
        renderer.update_scene(self.world.data, camera=camera, scene_option=self._option)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = self.shadows
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False

    def rgb(self, camera: str) -> np.ndarray:
        """(H, W, 3) uint8 image."""
        self._update(self._rgb, camera)
        return self._rgb.render()

    def depth(self, camera: str) -> np.ndarray:
        """(H, W) float32 metric depth along the optical axis (metres)."""
        if self._depth is None:
            self._depth = mujoco.Renderer(self.world.model, height=self.height, width=self.width)
            self._depth.enable_depth_rendering()
        self._update(self._depth, camera)
        return self._depth.render().astype(np.float32)

    def close(self) -> None:
        for renderer in (self._rgb, self._depth):
            if renderer is not None:
                renderer.close()
        self._depth = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
