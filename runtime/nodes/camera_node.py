"""camera_node (hardware): a RealSense D435 -> CameraFrame messages on camera/<name>/color.

    python -m runtime.nodes.camera_node --config '{"name": "scene", "serial": "123456789012"}'

Colour only by default (the policy uses colour; depth doubles the bytes), at the camera's resolution; the
policy node crops/resizes to the bundle's image size. Capture times are the driver's host-monotonic
stamps (RealSense global time mapped to CLOCK_MONOTONIC), which the policy aligns its chunks to.
`source="sim"` publishes a SimCamera on an idle sim rig instead (a dry run of the node without hardware);
`source="software"` uses pyrealsense2's software device (runtime.drivers.realsense.SoftwareD435) feeding a
synthetic scene, which exercises the real driver code path.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from runtime.nodes.common import BusSettings, NodeContext, cli_main

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraNodeConfig:
    bus: BusSettings = field(default_factory=BusSettings)
    name: str = "scene"  # bus camera name (= the bundle's camera name)
    serial: str = ""  # RealSense serial; empty: the only connected camera
    width: int = 640
    height: int = 480
    fps: int = 30
    depth: bool = False
    source: str = "realsense"  # realsense | software | sim


CONFIG = CameraNodeConfig


def _open_camera(cfg: CameraNodeConfig):
    """(camera driver, cleanup callable)."""
    if cfg.source == "sim":
        from sim.build import build_world
        from sim.twins.camera import CameraNoiseConfig
        from sim.twins.rig import SimRig

        rig = SimRig(build_world("pick_place", seed=0, dr="off", fidelity="fast"), "realtime").start()
        mj = {"scene": "scene_cam", "wrist": "gripper/wrist_cam"}.get(cfg.name, cfg.name)
        cam = rig.camera(mj, cfg.width, cfg.height, cfg.fps, CameraNoiseConfig(shadows=False))
        return cam, rig.close
    from runtime.drivers.realsense import RealSenseCamera, RealSenseConfig

    rs_cfg = RealSenseConfig(serial=cfg.serial or None, name=cfg.name, width=cfg.width, height=cfg.height,
                             fps=cfg.fps, depth=cfg.depth)
    if cfg.source == "software":
        from runtime.drivers.realsense import SoftwareD435
        from sim.camera_model import Intrinsics

        dev = SoftwareD435(serial=cfg.serial or "000000000435",
                           intrinsics=Intrinsics.from_fovy(cfg.width, cfg.height, 42.5), fps=cfg.fps)
        cam = RealSenseCamera(rs_cfg, context=dev)
        return cam, lambda: None
    if cfg.source != "realsense":
        raise ValueError(f"source = {cfg.source!r}; expected realsense, software or sim")
    return RealSenseCamera(rs_cfg), lambda: None


def run(cfg: CameraNodeConfig, ctx: NodeContext) -> dict:
    from runtime import bus as B
    from runtime import messages as m

    report = {"frames": 0, "timeouts": 0}
    cam, cleanup = _open_camera(cfg)
    bus = cfg.bus.open()
    feeder = None
    try:
        cam.start()
        if cfg.source == "software":
            feeder = cam._context.feed()  # the SoftwareD435 pushes a synthetic scene from its own thread
        pub = bus.publisher(B.camera_color(cfg.name))
        ctx.ready({"camera": cfg.name, "source": cfg.source})
        while not ctx.should_stop():
            try:
                f = cam.read(timeout_s=0.5)
            except TimeoutError:
                report["timeouts"] += 1
                continue
            pub.publish(m.CameraFrame(camera_id=cfg.name, intrinsics=f.intrinsics, capture_ns=f.capture_ns,
                                      color=f.color, depth=f.depth if cfg.depth else None, frame_seq=f.seq))
            report["frames"] += 1
        report["stop_reason"] = ctx.stop_reason
    finally:
        if feeder is not None:
            try:
                feeder.stop_feed()
            except Exception:
                pass
        try:
            cam.stop()
        except Exception:
            log.exception("camera stop failed")
        cleanup()
        bus.close()
    return report


def main(argv: list[str] | None = None) -> int:
    return cli_main(__name__, argv)


if __name__ == "__main__":
    raise SystemExit(main())
