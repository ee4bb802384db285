"""RealSenseCamera on librealsense's software_device: frames pushed with `on_video_frame` go through the real
pyrealsense2 pipeline, syncer and align block into the driver, so everything but USB and the sensor is real.
(The shared CameraDriver contract runs on the same source: `realsense-software` in test_device_contract.py.)
"""

from __future__ import annotations

import subprocess
import sys
import time
import types

import numpy as np
import pytest

from runtime.drivers.realsense import (GLOBAL_TIME, HARDWARE_CLOCK, SYSTEM_TIME, CameraNotFoundError, HostClock,
                                       RealSenseCamera, RealSenseConfig, _depth_mm)
from sim.camera_model import Intrinsics
from sim.devices import CameraDriver, StaleFrameError

K = Intrinsics(64, 48, 50.0, 51.0, 31.0, 24.5)


@pytest.fixture
def rs():
    return pytest.importorskip("pyrealsense2")


@pytest.fixture
def source(rs):
    from runtime.drivers.realsense import SoftwareD435

    return SoftwareD435(serial="111", intrinsics=K)


@pytest.fixture
def camera(source):
    cam = RealSenseCamera(RealSenseConfig(serial="111", name="wrist", width=K.width, height=K.height), context=source)
    cam.start()
    yield cam
    cam.stop()


def _images(n: int):
    color = np.random.default_rng(n).integers(0, 256, (K.height, K.width, 3), dtype=np.uint8)
    depth = np.full((K.height, K.width), 700 + n, np.uint16)
    return color, depth


def test_injected_frames_arrive_with_pixels_intrinsics_and_seq(camera, source):
    assert isinstance(camera, CameraDriver)
    assert camera.intrinsics("color") == K and camera.intrinsics("depth") == K
    assert camera.distortion() == ("brown_conrady", (0.0,) * 5)
    for n in (1, 2, 3):
        color, depth = _images(n)
        source.push(color, depth)
        f = camera.read(timeout_s=2.0)
        assert f.seq == n and f.camera_id == "wrist" and f.intrinsics == K
        np.testing.assert_array_equal(f.color, color)  # rgb8 passes through untouched
        assert f.depth.dtype == np.uint16 and f.depth.shape == (K.height, K.width)
        valid = f.depth[f.depth > 0]
        # align with identical intrinsics and identity extrinsics re-projects onto the same pixels; its
        # per-pixel footprint rounding leaves a few holes (0), never other values
        assert valid.size > 0.8 * f.depth.size and np.all(valid == 700 + n)
    with pytest.raises(ValueError, match="stream"):
        camera.intrinsics("infrared")


def test_read_waits_for_a_newer_frame_and_times_out(camera, source):
    with pytest.raises(TimeoutError, match="no new frame"):
        camera.read(timeout_s=0.1)
    source.push(*_images(1))
    assert camera.read(1.0).seq == 1
    with pytest.raises(TimeoutError):
        camera.read(timeout_s=0.1)  # the same frame is not returned twice


def test_read_latest_staleness(camera, source):
    with pytest.raises(StaleFrameError, match="no frame yet"):
        camera.read_latest(max_age_s=1.0)
    source.push(*_images(1))
    camera.read(1.0)
    assert camera.read_latest(max_age_s=1.0).seq == 1
    time.sleep(0.05)
    with pytest.raises(StaleFrameError, match="ms old"):
        camera.read_latest(max_age_s=0.02)
    source.push(*_images(2))
    camera.read(1.0)
    assert camera.read_latest(max_age_s=0.02).seq == 2


@pytest.mark.parametrize("domain", [SYSTEM_TIME, GLOBAL_TIME])
def test_host_clock_domains_map_to_monotonic_time(camera, source, domain):
    for n in range(1, 4):
        m0, wall, m1 = time.monotonic_ns(), time.time_ns(), time.monotonic_ns()
        stamp_ms = wall / 1e6 - 30.0  # exposed 30 ms ago, on the host wall clock
        source.push(*_images(n), timestamp_ms=stamp_ms, domain=domain)
        f = camera.read(1.0)
        expected = stamp_ms * 1e6 + (m0 + m1) / 2 - wall  # the same instant on the monotonic clock
        assert abs(f.capture_ns - expected) < 2_000_000 + (m1 - m0)
        assert f.capture_ns <= time.monotonic_ns()


def test_hardware_clock_maps_to_monotonic_time(camera, source):
    stamps, arrivals = [], []
    for n in range(1, 6):
        source.push(*_images(n), timestamp_ms=5000.0 + 33.3 * n, domain=HARDWARE_CLOCK)
        f = camera.read(1.0)
        stamps.append(f.capture_ns)
        arrivals.append(time.monotonic_ns())
        time.sleep(0.0333)
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    assert all(s <= a and a - s < 250_000_000 for s, a in zip(stamps, arrivals))  # mapped near the arrival


def test_seq_keeps_increasing_across_restart(camera, source):
    source.push(*_images(5), frame_number=5)
    assert camera.read(1.0).seq == 5
    camera.stop()
    camera.start()  # a restarted device counts frames from 1 again
    source.push(*_images(1), frame_number=1)
    assert camera.read(1.0).seq > 5


def test_serial_selection_errors_list_connected_cameras(rs, source):
    from runtime.drivers.realsense import SoftwareD435

    with pytest.raises(CameraNotFoundError, match=r"serial '999'.*connected: 111 \(Intel RealSense D435"):
        RealSenseCamera(RealSenseConfig(serial="999"), context=source).start()
    with pytest.raises(CameraNotFoundError, match="no RealSense camera connected"):
        RealSenseCamera(RealSenseConfig(), context=types.SimpleNamespace(query_devices=lambda: [])).start()
    other = SoftwareD435(serial="222", intrinsics=K)
    both = types.SimpleNamespace(query_devices=lambda: [source.device, other.device])
    with pytest.raises(CameraNotFoundError, match="2 RealSense cameras connected: 111 .*222 .*RealSenseConfig.serial"):
        RealSenseCamera(RealSenseConfig(), context=both).start()
    cam = RealSenseCamera(RealSenseConfig(serial="222", width=K.width, height=K.height), context=both)
    with cam:
        assert cam.serial == "222"
        other.push(*_images(1))
        assert cam.read(1.0).seq == 1


def test_unsupported_mode_and_lifecycle_errors(rs, source):
    cam = RealSenseCamera(RealSenseConfig(serial="111", width=1280, height=720), context=source)
    with pytest.raises(RuntimeError, match="cannot stream rgb8\\+z16 1280x720"):
        cam.start()
    cam = RealSenseCamera(RealSenseConfig(serial="111", width=K.width, height=K.height), context=source)
    with pytest.raises(RuntimeError, match="start"):
        cam.intrinsics()
    with pytest.raises(RuntimeError, match="not started"):
        cam.read(0.1)
    cam.stop()  # stopping a camera that never started is harmless


def test_colour_only_config(rs, source):
    cam = RealSenseCamera(RealSenseConfig(serial="111", width=K.width, height=K.height, depth=False), context=source)
    with cam:
        color, depth = _images(1)
        source.push(color, depth)
        f = cam.read(1.0)
        assert f.depth is None
        np.testing.assert_array_equal(f.color, color)


def test_config_validation():
    with pytest.raises(ValueError, match="fps"):
        RealSenseConfig(fps=0)


def test_host_clock_is_monotonic_through_clock_jumps():
    clock = HostClock(resync_s=1.0)
    now = time.monotonic_ns()
    t1 = clock.to_monotonic(time.time() * 1000, SYSTEM_TIME, now)
    t2 = clock.to_monotonic(time.time() * 1000 - 3_600_000, SYSTEM_TIME, now + 1000)  # wall clock stepped back
    assert t2 > t1
    a = clock.to_monotonic(10_000.0, HARDWARE_CLOCK, now + 10_000_000)
    b = clock.to_monotonic(10_033.0, HARDWARE_CLOCK, now + 45_000_000)
    c = clock.to_monotonic(5.0, HARDWARE_CLOCK, now + 80_000_000)  # device clock reset: a new offset
    assert a < b < c <= now + 80_000_000 and b - a == 33_000_000


def test_depth_in_other_units_is_converted_to_mm():
    raw = np.array([[0, 1000, 65535]], np.uint16)
    frame = types.SimpleNamespace(get_data=lambda: raw, get_units=lambda: 0.0001)  # 0.1 mm units
    np.testing.assert_array_equal(_depth_mm(frame), [[0, 100, 6554]])


def test_import_is_cheap_and_torch_free():
    code = ("import sys, runtime.drivers.realsense, runtime.drivers.robotiq; "
            "assert 'pyrealsense2' not in sys.modules and 'torch' not in sys.modules and 'mujoco' not in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True)
