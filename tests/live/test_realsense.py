"""The RealSense source on frames injected through librealsense's software device."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from live_helpers import model_cache  # noqa: F401

from phjax._np_quat import np_qconj, np_qmul, np_rotvec
from phjax.live import RealClock, RealSenseSource, SourceError

N = 8


def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError as e:  # the wheel also needs the system's libusb-1.0
        pytest.skip(f"pyrealsense2 cannot be imported: {e}")
    try:
        rs.software_device()
    except Exception as e:  # noqa: BLE001
        pytest.skip(f"librealsense software device unavailable here: {e}")
    return rs


def _software_camera(rs, seq):
    """A software device with registered colour (bgr8) and depth (z16, mm) streams."""
    dev = rs.software_device()
    sensor = dev.add_sensor("rgbd")
    k = seq.intrinsics
    intr = rs.intrinsics()
    intr.width, intr.height = seq.width, seq.height
    intr.fx, intr.fy, intr.ppx, intr.ppy = float(k.fx), float(k.fy), float(k.cx), float(k.cy)
    intr.model = rs.distortion.none
    intr.coeffs = [0.0] * 5
    profiles = []
    for uid, (stream, fmt, bpp) in enumerate([(rs.stream.color, rs.format.bgr8, 3),
                                               (rs.stream.depth, rs.format.z16, 2)]):
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = stream, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = seq.width, seq.height, 30, bpp, fmt
        vs.intrinsics = intr
        profiles.append(sensor.add_video_stream(vs))
    sensor.add_read_only_option(rs.option.depth_units, 0.001)
    dev.create_matcher(rs.matchers.default)
    syncer = rs.syncer()
    sensor.open(profiles)
    sensor.start(syncer)
    return dev, sensor, profiles, syncer


def test_realsense_source_on_injected_frames(model_cache):  # noqa: F811
    rs = _rs()
    from phjax.vision import synthetic_rgbd_sequence

    seq = synthetic_rgbd_sequence(4 * N, depth_noise=True)
    frames = [seq[i] for i in range(0, 4 * N, 4)]
    _dev, sensor, (cp, dp), syncer = _software_camera(rs, seq)  # _dev: keep the device alive
    src = RealSenseSource(frames=syncer, model_dir=model_cache, timeout=5.0)
    src.open()
    got = []
    stop = threading.Event()

    def emit(m):
        got.append(m)
        if len(got) >= N:
            stop.set()

    def feed():
        for i, f in enumerate(frames):
            for prof, data, bpp in ((cp, np.ascontiguousarray(f.color[..., ::-1]), 3),
                                    (dp, np.round(f.depth * 1000).astype(np.uint16), 2)):
                vf = rs.software_video_frame()
                vf.pixels, vf.bpp, vf.stride = data, bpp, seq.width * bpp
                vf.timestamp, vf.frame_number = i * 1000 / 30, i
                vf.domain = rs.timestamp_domain.hardware_clock
                vf.profile = prof.as_video_stream_profile()
                if bpp == 2:
                    vf.depth_units = 0.001
                sensor.on_video_frame(vf)
            # the next frame once this one has been taken (the front-end compiles at first)
            deadline = time.monotonic() + 120
            while len(got) <= i and time.monotonic() < deadline and not stop.is_set():
                time.sleep(0.01)

    feeder = threading.Thread(target=feed)
    feeder.start()
    clock = RealClock()
    try:
        src.run(clock, clock.now(), stop, emit)
    finally:
        stop.set()
        feeder.join()
        src.close()
        sensor.stop()
        sensor.close()
    ok = [m for m in got if m.status == "OK"]
    assert len(got) >= N - 1 and len(ok) >= N - 2, [m.status for m in got]
    assert src.intrinsics.width == seq.width and float(src.intrinsics.fx) == pytest.approx(
        float(seq.intrinsics.fx))
    # the poses follow the head: rotation relative to the first frame vs ground truth
    idx = [i for i, m in enumerate(got[:N]) if m.status == "OK"]
    q = np.array([got[i].quaternion for i in idx])
    gt = np.array([frames[i].head_quaternion for i in idx])
    rel_e = np_qmul(q, np_qconj(q[:1]))
    rel_g = np_qmul(gt, np_qconj(gt[:1]))
    err = np.degrees(np.linalg.norm(np_rotvec(np_qmul(rel_e, np_qconj(rel_g))), axis=1))
    print(f"\nrealsense (injected): {len(ok)} poses, rotation error max {err.max():.2f} deg")
    assert err.max() < 3.0


def test_realsense_without_camera_is_a_clear_error():
    _rs()
    with pytest.raises(SourceError, match="RealSense"):
        RealSenseSource("123456").open()
