"""The live sim cameras show the episode's sensor DR: a seed's live frames have the colour gain its recorded
frames (datagen.recorder, the lockstep eval) have, in sim_render's process and in the robot node's own."""

from __future__ import annotations

import time

import numpy as np
import pytest

from runtime import bus as B
from runtime.launch import Launcher, sim_stack

TASK, SEED = "pick_place", 0  # heavy DR draws a blue gain of 0.94 for this seed: ~7 levels on this scene


def _channel_means(img: np.ndarray) -> np.ndarray:
    return img.reshape(-1, 3).astype(np.float64).mean(axis=0)


def _recorded_and_clean() -> tuple[np.ndarray, np.ndarray]:
    """The scene camera's first frame as the recorder keeps it, and the same render without the sensor DR."""
    from datagen.recorder import CAMERA_NAMES, Recorder
    from sim.build import build_episode
    from sim.render import CameraRenderer

    ep = build_episode(TASK, SEED, "heavy", "fast")
    rec = Recorder(ep, image_size=(128, 128))
    try:
        rec.start()
        recorded = rec.window(1)[0]["scene"][-1]
    finally:
        rec.close()
    with CameraRenderer(ep.world, 128, 128, shadows=False) as cams:
        clean = cams.rgb(CAMERA_NAMES["scene"])
    return recorded, clean


@pytest.mark.parametrize("render_process", [True, False])
def test_live_frames_have_the_seeds_sensor_gain(untrained_bundle, render_process):
    recorded, clean = _recorded_and_clean()
    want, bare = _channel_means(recorded), _channel_means(clean)
    assert np.max(np.abs(want - bare)) > 4.0  # the seed's gain is visible at all (else the test proves nothing)
    frames: list[np.ndarray] = []
    la = Launcher(sim_stack(str(untrained_bundle), task=TASK, seed=SEED, dr="heavy", render_process=render_process),
                  hub="tcp/127.0.0.1:0")
    with la:
        la.bus.subscribe(B.camera_color("scene"), lambda f: frames.append(np.array(f.color)))
        la.wait_ready(90)
        deadline = time.monotonic() + 20
        while len(frames) < 5 and time.monotonic() < deadline:
            time.sleep(0.05)
        la.monitor(duration_s=0.0)
    assert len(frames) >= 5, len(frames)
    live = _channel_means(frames[2])  # no command: the arm and the objects are at rest where they started
    assert np.max(np.abs(live - want)) < 1.5, (live, want, bare)
    assert float(np.std(frames[2].astype(np.float64) - frames[3].astype(np.float64))) > 1.0  # fresh noise per frame
