"""The live runner: late updates, lost face, centring, shutdown, and a half-hour soak."""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from live_helpers import (  # noqa: F401
    UdpListener,
    angle_steps,
    listener,
    process_alive,
    smooth_motion,
    wait_until,
    write_pose_file,
)

from phjax._np_quat import np_qconj, np_qmul, np_rotvec
from phjax.io import read_tum
from phjax.live import (
    LiveStream,
    LiveTracker,
    PoseReplaySource,
    SourceError,
    SyntheticSource,
    VirtualClock,
    WorkerSource,
    live_tracker_config,
    open_source,
    opentrack_values,
)
from phjax.tracking import TrackerStream


def _angle_deg(q0, q1):
    return np.degrees(np.linalg.norm(np_rotvec(np_qmul(q1, np_qconj(q0))), axis=-1))


def test_late_update_is_continuous_and_filters_at_capture_time():
    """A measurement that arrives late does not make the rendered pose jump; a plain update
    at the capture time does (the reason for update_late); the filter runs at capture time."""
    t, p, q = smooth_motion(40, 30.0, seed=3)
    cfg = live_tracker_config()  # the runner's config: its compiled update is reused below
    late = LiveStream(cfg)
    on_time = LiveStream(cfg)  # arrives when taken: the tracker's own update
    plain = TrackerStream(cfg, dtype=late.dtype)
    latency = 0.1
    jumps_late, jumps_plain = [], []
    for i in range(40):
        t_now = t[i] + latency
        before_l = np.asarray(late.sample(t_now)[0])
        before_p = np.asarray(plain.sample(t_now)[0])
        late.update_late(t[i], t_now, p[i], q[i])
        on_time.update_late(t[i], t[i], p[i], q[i])
        plain.update(t[i], p[i], q[i])
        for a, b in zip(on_time.sample(t_now), plain.sample(t_now)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-12)
        if i > 3:
            jumps_late.append(np.linalg.norm(np.asarray(late.sample(t_now)[0]) - before_l))
            jumps_plain.append(np.linalg.norm(np.asarray(plain.sample(t_now)[0]) - before_p))
        # the filter state is the one of a filter run at the capture times
        np.testing.assert_allclose(np.asarray(late.state.filter.t), t[i], atol=1e-9)
        np.testing.assert_allclose(np.asarray(late.state.filter.x),
                                   np.asarray(plain.state.filter.x), atol=1e-9)
    assert max(jumps_late) < 1e-9
    assert max(jumps_plain) > 1e-5


def test_fast_start_late_updates_equal_the_optimised_ones(monkeypatch):
    """``fast_start``: the first late update runs the -O0 program and the optimised one takes
    over when its background compilation ends, with the same stream (float32 rounding). (The
    suite compiles everything at -O0, where tiering is off: forced on here.)"""
    import jax.numpy as jnp

    from phjax import _jit
    from phjax.tracking import stream as stream_mod

    monkeypatch.setattr(_jit, "_tiering_pays", lambda: True)
    stream_mod._tiered_on_leaves.cache_clear()  # not a program made with tiering off
    try:
        t, p, q = smooth_motion(12, 30.0, seed=2)
        cfg = live_tracker_config()
        a = LiveStream(cfg, dtype=jnp.float32)
        b = LiveStream(cfg, dtype=jnp.float32, fast_start=False)
        assert b.wait_compiled() and a._late._program is None
        for i in range(12):
            a.update_late(t[i], t[i] + 0.05, p[i], q[i])
            b.update_late(t[i], t[i] + 0.05, p[i], q[i])
            if i == 0:
                assert a._late._program is not a._late._jitted  # the fast program
            if i == 6:
                assert a.wait_compiled(120) and a._late.error is None
            for x, y in zip(a.sample(t[i] + 0.06), b.sample(t[i] + 0.06)):
                np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=2e-5, atol=2e-5)
    finally:
        stream_mod._tiered_on_leaves.cache_clear()


def _run(source, rate, duration=None, **kw):
    lt = LiveTracker(source, rate=rate, duration=duration, clock=VirtualClock(), **kw)
    got = []
    lt.callback = got.append
    lt.run()
    return lt, got


def test_orientation_only_source_is_sent_with_the_position_at_the_origin(tmp_path):
    """A 3-DoF pose source (every position NaN, e.g. a VR head trace) sent nothing at all
    (the stream waited for a whole pose); now it sends from its ``PARTIAL_FRAMES``-th frame on,
    never a NaN, positions exactly 0 and orientations as a 6-DoF source at the origin that
    starts at that frame sends them."""
    from phjax.tracking.stream import PARTIAL_FRAMES

    k = PARTIAL_FRAMES - 1
    t, p, q = smooth_motion(90, 30.0, seed=2)  # 3 s
    lt, got = _run(PoseReplaySource(t, np.full_like(p, np.nan), q), 120.0)
    q_ref, p_ref = q.copy(), np.zeros_like(p)
    q_ref[:k], p_ref[:k] = np.nan, np.nan  # the frames before the stream starts: lost
    _, ref = _run(PoseReplaySource(t, p_ref, q_ref), 120.0)
    assert lt.error is None and len(got) == len(ref) > 0.9 * 120 * (t[-1] - t[k])
    ts = np.array([s.t for s in got])
    pos = np.array([s.position for s in got])
    quat = np.array([s.quaternion for s in got])
    assert ts[0] >= t[k] - t[0] - 1e-9 and np.isfinite(quat).all() and np.all(pos == 0.0)
    np.testing.assert_array_equal(ts, [s.t for s in ref])
    np.testing.assert_allclose(quat, [s.quaternion for s in ref], rtol=0, atol=1e-6)


def test_face_lost_coasts_then_holds_never_nan(tmp_path):
    t, p, q = smooth_motion(300, 30.0, seed=1)  # 10 s
    lost = (t > 4.0) & (t < 7.0)
    p[lost], q[lost] = np.nan, np.nan
    src = PoseReplaySource(t, p, q)
    lt, got = _run(src, 120.0, log=tmp_path / "log.tum")
    ts = np.array([s.t for s in got])
    pos = np.array([s.position for s in got])
    quat = np.array([s.quaternion for s in got])
    assert np.isfinite(pos).all() and np.isfinite(quat).all()
    np.testing.assert_allclose(np.diff(ts), 1 / 120, atol=1e-9)  # exact deadlines
    assert lt.missed_deadlines == 0 and lt.error is None
    # coasting, then at rest: motion stops within coast_time + a few stop_time constants
    cfg = lt._config_used
    rest = (ts > 4.0 + cfg.coast_time + 6 * cfg.stop_time + 0.05) & (ts < 7.0)
    step_p = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    step_q = _angle_deg(quat[:-1], quat[1:])
    assert step_p[rest[1:]].max() < 1e-4 and step_q[rest[1:]].max() < 1e-2
    coasting = (ts > 4.0) & (ts < 4.0 + 0.5 * cfg.coast_time)
    assert step_q[coasting[1:]].max() > 1e-3 or step_p[coasting[1:]].max() > 1e-5
    # smooth: steps below 1 cm / 2 deg per sample, except while re-acquiring after the 3 s
    # loss (the head has turned by up to ~25 deg meanwhile, and the filter's velocity is
    # stale): there below 1 cm / 3 deg (measured: 0.43 cm, 2.5 deg)
    vals = np.array([opentrack_values(a, b) for a, b in zip(pos, quat)])
    step_cm = np.abs(np.diff(vals[:, :3], axis=0)).max(1)
    step_deg = angle_steps(vals[:, 3:]).max(1)
    reacq = ((ts > 7.0) & (ts < 7.6))[1:]
    assert step_cm.max() <= 1.0
    assert step_deg[~reacq].max() <= 2.0 and step_deg[reacq].max() <= 3.0
    # the log holds exactly the samples
    log = read_tum(tmp_path / "log.tum")
    np.testing.assert_array_equal(log.times, ts)
    np.testing.assert_array_equal(log.positions, pos)


def test_center_and_recenter():
    t, p, q = smooth_motion(90, 30.0, seed=2)
    src = PoseReplaySource(t, p, q)
    lt = LiveTracker(src, rate=60.0, clock=VirtualClock(), center=True)
    got = []

    def cb(s):
        got.append(s)
        if len(got) == 100:
            lt.center()

    lt.callback = cb
    lt.run()
    first = got[0]
    np.testing.assert_allclose(first.position, 0, atol=1e-12)
    np.testing.assert_allclose(np.abs(first.quaternion[0]), 1, atol=1e-12)
    np.testing.assert_allclose(got[100].position, 0, atol=1e-12)
    assert np.linalg.norm(got[99].position) > 1e-4  # it had moved before re-centring


def _fds() -> int:
    return len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else 0


def test_shutdown_real_clock_joins_threads_and_closes_sockets(listener, tmp_path):  # noqa: F811
    t, p, q = smooth_motion(3000, 30.0)
    threads0, fds0 = threading.active_count(), _fds()
    lt = LiveTracker(PoseReplaySource(t, p, q), [f"opentrack://127.0.0.1:{listener.port}",
                                                 f"osc://127.0.0.1:{listener.port}"],
                     rate=120.0, log=tmp_path / "x.tum")
    with lt:
        time.sleep(1.0)
        assert lt.running
    assert not lt.running
    assert not [th for th in threading.enumerate() if th.name.startswith("phjax-live")]
    assert threading.active_count() == threads0
    assert all(o.sock.fileno() == -1 for o in lt.outputs)
    assert _fds() == fds0
    assert read_tum(tmp_path / "x.tum").num_samples == lt.sent > 60


def test_render_loop_never_waits_for_a_slow_front_end():
    """A front-end that takes 0.3 s per frame: the render loop keeps its deadlines."""
    from phjax.live import Measurement, Source

    class Slow(Source):
        name = "slow"

        def run(self, clock, t0, stop, emit):
            _, p, q = smooth_motion(20, 30.0)
            for i in range(20):
                t_cap = clock.now()
                time.sleep(0.3)  # "processing"
                if stop.is_set():
                    return
                emit(Measurement(t_cap, p[i], q[i]))

    lt = LiveTracker(Slow(), rate=100.0, duration=2.0)
    got = []
    lt.callback = got.append
    lt.run()
    ts = np.array([s.t for s in got])
    assert lt.frames >= 3
    assert lt.sent > 0.8 * 100 * (2.0 - ts[0])
    assert np.isfinite([s.position for s in got]).all()


def test_stop_with_timeout_leaves_a_hung_camera_behind_and_closes_everything(listener):  # noqa: F811
    """A camera read that never returns (a hung driver): ``stop(timeout)`` returns in about the
    timeout, with the outputs and the source closed; ``request_stop`` alone ends a healthy run."""
    from phjax.live import Measurement, Source

    release = threading.Event()
    closed = []

    class Hung(Source):
        name = "hung"

        def run(self, clock, t0, stop, emit):
            _, p, q = smooth_motion(2, 30.0)
            emit(Measurement(clock.now(), p[0], q[0]))
            release.wait(30.0)  # blocks and ignores ``stop``, like a read stuck in a driver

        def close(self):
            closed.append(True)

    lt = LiveTracker(Hung(), [f"opentrack://127.0.0.1:{listener.port}"], rate=100.0).start()
    try:
        time.sleep(0.5)
        t0 = time.monotonic()
        lt.stop(timeout=0.3)
        assert time.monotonic() - t0 < 2.0
        assert closed == [True] and all(o.sock.fileno() == -1 for o in lt.outputs)
        assert lt.sent > 0
    finally:
        release.set()

    t, p, q = smooth_motion(3000, 30.0)
    lt = LiveTracker(PoseReplaySource(t, p, q), rate=100.0)
    threading.Timer(0.5, lt.request_stop).start()
    t0 = time.monotonic()
    lt.run()  # returns once the request is seen, threads joined
    assert time.monotonic() - t0 < 10.0 and not lt.running


# ------------------------------------------------------------------------ render deadlines
def test_virtual_clock_deadline_k_is_exactly_t0_plus_k_over_rate():
    """Absolute deadlines: sample k is rendered at t0 + k / rate, computed from k (a schedule
    built by adding the period to the previous deadline, or to "now", drifts by its rounding
    errors: 1e-7 s after 30 s at t0 = 1e6 s, a typical monotonic-clock reading)."""
    t0, rate = 1e6 + 0.1234, 120.0
    t, p, q = smooth_motion(900, 30.0, seed=4)  # 30 s
    lt = LiveTracker(PoseReplaySource(t, p, q), rate=rate, clock=VirtualClock(t0),
                     linger=0.0)
    times = []
    lt.callback = lambda s: times.append(lt.clock.now())
    lt.run()
    rel = np.array(times) - t0
    k = np.round(rel * rate)
    assert lt.missed_deadlines == 0 and len(times) == lt.sent >= 3500
    assert (np.diff(k) == 1).all() and k[0] == lt.waiting <= 1
    # the render times themselves (absolute, on the clock): t0 + k / rate up to the rounding
    # of that one sum (ulp(1e6) = 1.2e-10)
    np.testing.assert_allclose(rel, k / rate, rtol=0, atol=5e-10)


@pytest.mark.parametrize("rate, duration", [(0.4, 3.0), (1.0, 2.5), (120.0, 1.0)])
def test_run_lasts_its_duration_at_slow_rates(rate, duration):
    """A run ends ``duration`` after its start, also when the render period is longer than what
    is left of it (0.4 Hz for 3 s ended after 2.5 s, at its last whole period); the samples are
    the deadlines inside the run."""
    t, p, q = smooth_motion(int(30 * (duration + 2)), 30.0, seed=2)
    t0 = 500.0
    lt = LiveTracker(PoseReplaySource(t, p, q), rate=rate, duration=duration,
                     clock=VirtualClock(t0))
    lt.run()
    assert lt._t_render_end == pytest.approx(t0 + duration, abs=1e-9)
    assert lt.stats()["elapsed"] == pytest.approx(duration, abs=1e-9)
    assert lt.sent + lt.waiting + lt.missed_deadlines == math.floor(duration * rate + 1e-9) + 1


@pytest.mark.serial
def test_real_clock_keeps_the_deadline_grid_and_the_mean_rate():
    """Real time, 120 Hz for 3 s: every sent sample is rendered at a deadline t0 + k / rate
    (missed deadlines are skipped, never shifted) and the deadlines passed per second of wall
    time are the rate within 2 % (a schedule computed from "now + period" ran at 103 Hz)."""
    rate, duration = 120.0, 3.0
    t, p, q = smooth_motion(int(30 * (duration + 1)), 30.0)
    lt = LiveTracker(PoseReplaySource(t, p, q), rate=rate, duration=duration)
    got = []
    lt.callback = lambda s: got.append((time.perf_counter(), s.t))
    lt.run()
    wall = np.array([w for w, _ in got])
    ts = np.array([x for _, x in got])
    k = np.round(ts * rate)
    assert np.abs(ts * rate - k).max() < 1e-6  # on the grid
    assert (np.diff(k) >= 1).all()
    # every deadline is accounted for: sent, skipped (missed) or before the first pose
    assert lt.sent + lt.missed_deadlines + lt.waiting == k[-1] + 1 == lt.k
    # the mean rate over the run: deadlines passed per second of wall time (a late sample is
    # less than a period late, so this does not drift)
    mean_rate = (lt.k - 1) / (wall[-1] - lt.t0)
    print(f"\nmean rate {mean_rate:.2f} Hz, sent {lt.sent}, missed {lt.missed_deadlines}, "
          f"lateness p50 {1e3 * np.median(wall - lt.t0 - ts):.2f} ms")
    assert abs(mean_rate / rate - 1) < 0.02
    assert lt.sent >= 0.8 * rate * duration


@pytest.mark.parametrize("rate", [0.0, -5.0, float("nan"), float("inf"), 1000.5, 1e9])
def test_rate_outside_the_sane_range_is_one_line_value_error(rate):
    t, p, q = smooth_motion(3, 30.0)
    with pytest.raises(ValueError, match=r"rate must be in \(0, 1000\] Hz") as e:
        LiveTracker(PoseReplaySource(t, p, q), rate=rate)
    assert "\n" not in str(e.value)
    LiveTracker(PoseReplaySource(t, p, q), rate=1000.0, clock=VirtualClock())  # the bound


def test_cli_rate_out_of_range_is_exit_code_2(tmp_path, capsys):
    from phjax.cli import main
    from phjax.io import Trajectory, write_tum

    t, p, q = smooth_motion(10, 30.0)
    write_tum(tmp_path / "p.tum", Trajectory(t, p, q))
    assert main(["live", f"poses:{tmp_path / 'p.tum'}", "--rate", "1e9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rate must be in (0, 1000] Hz" in err[0], err


# ------------------------------------------------------------------- coasting and stopping
def _lin_rot_motion(n, rate, v, w):
    """Constant linear velocity ``v`` (m/s) and world-frame angular velocity ``w`` (rad/s)."""
    from phjax._np_quat import np_from_rotvec

    t = np.arange(n) / rate
    p = np.array([0.02, -0.01, 0.7]) + t[:, None] * v
    q0 = np_from_rotvec(np.array([0.1, -0.2, 0.05]))
    q = np_qmul(np_from_rotvec(t[:, None] * w), np.broadcast_to(q0, (n, 4)))
    return t, p, q


@pytest.mark.parametrize("lookahead,rotation_horizon", [(0.0, None), (0.03, None), (0.0, 0.07)])
def test_lost_face_coasts_then_decays_continuously(lookahead, rotation_horizon):
    """After the last measurement the stream keeps its end velocity for ``coast_time``, then
    the velocity decays as exp(-(t - coast end) / stop_time): position and velocity are
    continuous through both phases (finite differences of consecutive samples at 240 Hz), so
    a stream that stopped abruptly at the end of the coast would fail here. With an
    orientation horizon of its own, each channel coasts from its own segment end."""
    from phjax._np_quat import np_rotvec

    rate = 240.0
    v, w = np.array([0.08, -0.03, 0.04]), np.array([0.3, 0.6, -0.2])
    t, p, q = _lin_rot_motion(90, 30.0, v, w)  # 3 s
    lost = t >= 2.0
    p[lost], q[lost] = np.nan, np.nan
    cfg = dataclasses.replace(live_tracker_config(), lookahead=lookahead,
                              rotation_horizon=rotation_horizon)
    lt, got = _run(PoseReplaySource(t, p, q), rate, config=cfg, adaptive=False, linger=0.0)
    ts = np.array([s.t for s in got])
    pos = np.array([s.position for s in got])
    quat = np.array([s.quaternion for s in got])
    assert np.isfinite(pos).all() and np.isfinite(quat).all()
    seg = lt.stream.state.segment
    # display times at which the last segment ends (2 s + horizon): position, orientation
    ends = np.asarray(seg.end, np.float64)
    np.testing.assert_allclose(ends[1] - ends[0], (rotation_horizon or cfg.horizon) - cfg.horizon,
                               atol=1e-9)
    v_end, w_end = np.asarray(seg.v_end), np.asarray(seg.w_end)
    coast, stop = float(cfg.coast_time), float(cfg.stop_time)
    # the end velocities are the motion's (the filter had converged)
    np.testing.assert_allclose(v_end, v, atol=0.02 * np.linalg.norm(v))
    np.testing.assert_allclose(w_end, w, atol=0.02 * np.linalg.norm(w))
    # finite-difference velocities at the midpoints of consecutive samples (display time)
    vel = np.diff(pos, axis=0) * rate
    omega = np_rotvec(np_qmul(quat[1:], np_qconj(quat[:-1]))) * rate
    settled = ts[1:] > 1.0  # after the filter's start-up
    for fd, end_v, end in ((vel, v_end, ends[0]), (omega, w_end, ends[1])):
        delta = 0.5 * (ts[1:] + ts[:-1]) + lookahead - end  # time past the segment's end
        assert (delta > coast + 6 * stop).sum() > 50 and ((delta > 0) & (delta < coast)).sum() > 20
        scale = np.linalg.norm(end_v)
        # continuity: consecutive finite differences differ by at most the largest change of
        # the exact motion over one step, |v_end| / (stop_time * rate) = 0.083 |v_end|,
        # plus 0.02 |v_end| for the tracking error
        dv = np.linalg.norm(np.diff(fd, axis=0), axis=1)[settled[1:]]
        assert dv.max() <= (1 / (stop * rate) + 0.02) * scale, dv.max() / scale
        # coasting: the end velocity, unchanged
        coasting = (delta > 0.5 / rate) & (delta < coast - 0.5 / rate)
        np.testing.assert_allclose(fd[coasting], np.broadcast_to(end_v, fd[coasting].shape),
                                   atol=0.01 * scale)
        # stopping: the end velocity times exp(-(delta - coast) / stop_time)
        stopping = delta > coast + 0.5 / rate
        expect = end_v * np.exp(-(delta[stopping] - coast) / stop)[:, None]
        np.testing.assert_allclose(fd[stopping], expect, atol=0.01 * scale)
    # and at rest: the total coasting displacement is end velocity * (coast + stop)
    np.testing.assert_allclose(pos[-1] - np.asarray(seg.p_end), v_end * (coast + stop),
                               atol=1e-3 * np.linalg.norm(v))


# ----------------------------------------------------------------- the front-end's worker
def _worker_poses(tmp_path, seconds: float):
    """A WorkerSource replaying ``seconds`` of a 30 Hz pose file (a cheap worker: no vision)."""
    path = tmp_path / "p.tum"
    truth = write_pose_file(path, int(30 * seconds), 30.0)
    spec = f"poses:{path}"
    return WorkerSource(open_source(spec, worker=False), spec, {}), truth


def test_worker_source_runs_in_another_process_and_ends_with_the_run(tmp_path):
    """The source runs in a worker process; its measurements arrive at their capture times
    (the worker's clock is this process's), the stream follows them, and the worker is gone
    when the run ends (no orphan)."""
    src, (t, p, _) = _worker_poses(tmp_path, 4.0)
    lt = LiveTracker(src, rate=100.0, duration=2.0)
    got = []
    lt.callback = got.append
    lt.start()
    pid = src.pid
    assert pid is not None and pid != os.getpid() and process_alive(pid)
    lt.run()
    assert lt.error is None and src.pid is None
    assert wait_until(lambda: not process_alive(pid), 5.0)
    # 2 s of a 30 Hz file: 60 measurements (61 with the one at the end time)
    assert 58 <= lt.frames <= 61 and lt.dropped == 0
    ages = lt.applied_ages.values()  # capture (in the worker) -> applied (here)
    assert ages.min() >= 0 and np.median(ages) < 0.05
    ts = np.array([s.t for s in got])
    pos = np.array([s.position for s in got])
    assert np.isfinite(pos).all()
    late = ts > 0.5
    truth = np.stack([np.interp(ts[late], t, p[:, j]) for j in range(3)], -1)
    assert np.abs(pos[late] - truth).max() < 0.01


def test_worker_errors_are_one_line_source_errors(tmp_path):
    spec = f"poses:{tmp_path / 'missing.tum'}"
    local = PoseReplaySource([0.0], [[0.0, 0.0, 0.7]], [[1.0, 0.0, 0.0, 0.0]])
    src = WorkerSource(local, spec, {})
    with pytest.raises(SourceError, match="pose file not found") as e:
        src.open()
    assert "\n" not in str(e.value)
    src.close()
    assert src.pid is None
    # an unexpected exception: its type, message and where, on one line
    src = WorkerSource(local, spec, {"bogus": 1})
    with pytest.raises(SourceError, match=r"^TypeError: .*bogus.* \(\w+\.py:\d+\)$"):
        src.open()
    src.close()


def test_worker_that_dies_ends_the_run_with_one_line_and_never_a_nan(tmp_path):
    src, _ = _worker_poses(tmp_path, 30.0)
    lt = LiveTracker(src, rate=100.0)
    got = []
    lt.callback = got.append
    lt.start()
    assert wait_until(lambda: lt.sent > 20, 10.0)
    pid = src.pid
    os.kill(pid, signal.SIGINT)  # ignored: the parent stops the worker
    time.sleep(0.3)
    assert process_alive(pid) and lt.running
    os.kill(pid, signal.SIGKILL)
    with pytest.raises(SourceError, match=r"ended without a reply \(signal 9\)$"):
        lt.run()
    assert not lt.running and src.pid is None
    assert np.isfinite([s.position for s in got]).all()
    assert np.isfinite([s.quaternion for s in got]).all()


_PARENT = """
import sys, threading
from phjax.live import RealClock, WorkerSource, open_source
spec = sys.argv[1]
src = WorkerSource(open_source(spec, worker=False), spec, {})
src.open()
print(src.pid, flush=True)
src.run(RealClock(), RealClock.now(), threading.Event(), lambda m: None)
"""


@pytest.mark.skipif(not hasattr(signal, "SIGKILL"), reason="needs SIGKILL")
def test_worker_exits_when_its_parent_is_killed(tmp_path):
    """No orphan: a worker whose parent dies (SIGKILL, no clean-up) sees its stdin close and
    exits within seconds."""
    path = tmp_path / "p.tum"
    write_pose_file(path, 3000, 30.0)
    parent = subprocess.Popen([sys.executable, "-c", _PARENT, f"poses:{path}"],
                              stdout=subprocess.PIPE, text=True)
    try:
        line = parent.stdout.readline()
        assert line.strip().isdigit(), line
        pid = int(line)
        assert process_alive(pid)
        parent.kill()
        parent.wait(10)
        assert wait_until(lambda: not process_alive(pid), 10.0)
    finally:
        parent.kill()
        parent.wait(10)


def test_request_stop_ends_a_worker_run_promptly(tmp_path):
    """What the CLI's SIGINT / SIGTERM handlers call: the run ends, the worker with it."""
    src, _ = _worker_poses(tmp_path, 30.0)
    lt = LiveTracker(src, rate=100.0).start()
    pid = src.pid
    assert wait_until(lambda: lt.sent > 10, 10.0)
    threading.Timer(0.2, lt.request_stop).start()
    t0 = time.monotonic()
    lt.run()
    assert time.monotonic() - t0 < 5.0 and lt.error is None
    assert wait_until(lambda: not process_alive(pid), 5.0)


def test_a_worker_source_needs_the_real_clock(tmp_path):
    src, _ = _worker_poses(tmp_path, 1.0)
    with pytest.raises(ValueError, match="real time"):
        LiveTracker(src, rate=60.0, clock=VirtualClock())
    # a SOURCE string with a virtual clock is opened in this process
    lt = LiveTracker(f"poses:{tmp_path / 'p.tum'}", rate=60.0, clock=VirtualClock())
    assert not isinstance(lt.source, WorkerSource)


def test_open_source_puts_only_vision_sources_in_a_worker(tmp_path):
    write_pose_file(tmp_path / "p.tum", 3)
    assert isinstance(open_source("synthetic:3"), WorkerSource)
    assert isinstance(open_source("synthetic:3", worker=False), SyntheticSource)
    assert isinstance(open_source(f"poses:{tmp_path / 'p.tum'}"), PoseReplaySource)


# ----------------------------------------------------- RGB-D sources: camera and front-end
class _Frames:
    """A stand-in RGB-D sequence: frame ``i`` is the integer ``i``, at 30 Hz."""

    def __init__(self, n):
        self.timestamps = 100.0 + np.arange(n) / 30.0
        self.intrinsics = None
        self.loads = []

    def __len__(self):
        return self.timestamps.shape[0]

    def __getitem__(self, i):
        self.loads.append(i)
        return i


class _SlowEstimator:
    """A front-end taking ``seconds`` per frame; remembers which frames it processed."""

    def __init__(self, seconds):
        self.seconds, self.frames = seconds, []

    def process_frame(self, frame):
        from types import SimpleNamespace

        time.sleep(self.seconds)
        self.frames.append(frame)
        return SimpleNamespace(position=np.array([0.0, 0.0, 0.7]),
                               quaternion=np.array([1.0, 0.0, 0.0, 0.0]),
                               status=SimpleNamespace(name="OK"))

    def reset(self):
        pass


@pytest.mark.serial
def test_rgbd_camera_thread_hands_the_newest_frame_to_a_slow_front_end():
    """Real clock, 60 frames at 30 Hz, a front-end of 0.1 s a frame: the camera delivers
    every frame at its timestamp, the front-end takes the newest one whenever it is free (the
    others are counted as dropped, never queued), and each measurement carries its frame's
    capture time."""
    from phjax.live import RealClock, RGBDReplaySource

    seq, est = _Frames(60), _SlowEstimator(0.1)
    src = RGBDReplaySource(seq, estimator=est, name="stub")
    clock, stop, got = RealClock(), threading.Event(), []
    t0 = clock.now() + 0.05
    src.run(clock, t0, stop, lambda m: got.append((clock.now(), m)))
    frames = est.frames
    assert seq.loads == list(range(60))  # the camera read every frame once, in order
    assert 14 <= len(frames) <= 21 and frames == sorted(frames)
    assert len(frames) + sum(m.dropped for _, m in got) == 60  # each frame used or dropped
    for (_, m), i in zip(got, frames):
        assert m.t == t0 + (seq.timestamps[i] - seq.timestamps[0])
        assert abs(m.work - 0.1) < 0.05
    # the front-end takes a frame within a camera period of its capture, plus scheduling
    # delays (a queue would make the wait grow by 67 ms a frame, to over a second)
    wait = np.array([t_emit - m.t - m.work for t_emit, m in got])
    assert np.median(wait) < 1 / 30 + 0.02 and wait.max() < 1 / 30 + 0.15, wait


def test_synthetic_frames_are_rendered_once_into_the_cache(tmp_path):
    from phjax.live._sources import CACHE_DEPTH_STEP, _frame_keys
    from phjax.vision import open_rgbd, synthetic_rgbd_sequence

    # folders of other renderer versions: removed once unused for 30 days, not before
    day = 86400.0
    old, recent, notes = "synthetic-" + "0" * 16, "synthetic-" + "1" * 16, "synthetic-notes"
    mixed = "synthetic-" + "5" * 16  # a frame folder's name, but not only frames in it
    frame = "2" * 24 + ".bin"
    for name, age, file in ((old, 31, frame), (recent, 29, frame), (notes, 40, frame),
                            (mixed, 40, frame), (mixed, 40, "notes.txt")):
        (tmp_path / name).mkdir(exist_ok=True)
        (tmp_path / name / file).write_bytes(bytes(3 << 20))
        os.utime(tmp_path / name, (time.time() - age * day,) * 2)
    (tmp_path / ("synthetic-" + "4" * 16)).write_text("a file, not a folder")
    os.utime(tmp_path / ("synthetic-" + "4" * 16), (time.time() - 40 * day,) * 2)
    lines = []
    src = SyntheticSource(3, 1, estimator=_SlowEstimator(0.0), cache=tmp_path,
                          report=lines.append)
    src.open()
    assert lines[0] == (f"synthetic head: removed 1 frame folder(s) of other renderer versions "
                        f"unused for 30 days from {tmp_path} (3 MB)"), lines
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [recent, notes, mixed, "synthetic-" + "4" * 16, src.folder.name])  # only the old frames
    lines.pop(0)
    assert src.rendered == 3 and len(lines) == 2 and "rendering 3 of 3 frames" in lines[0]
    # a run that renders nothing still marks its folder as used
    os.utime(src.folder, (time.time() - 40 * day,) * 2)
    again = SyntheticSource(3, 1, estimator=_SlowEstimator(0.0), cache=tmp_path,
                            report=lines.append)
    again.open()
    assert again.rendered == 0 and len(lines) == 2
    assert time.time() - src.folder.stat().st_mtime < day
    ref = open_rgbd("synthetic:3:1")
    np.testing.assert_array_equal(src.sequence.timestamps, ref.timestamps)
    for i in range(3):
        a, b = src.sequence[i], ref[i]
        np.testing.assert_array_equal(a.color, b.color)
        np.testing.assert_allclose(a.depth, b.depth, rtol=0, atol=CACHE_DEPTH_STEP / 2 + 1e-6)
        np.testing.assert_array_equal(a.depth == 0, b.depth == 0)
    # a longer sequence with the same frames reuses them; only the new frames are rendered
    more = SyntheticSource(4, 1, estimator=_SlowEstimator(0.0), cache=tmp_path,
                           report=lines.append)
    more.open()
    assert more.rendered == 1
    np.testing.assert_array_equal(more.sequence[3].color, open_rgbd("synthetic:4:1")[3].color)
    # ... but not a sequence over a minute long: its motion is another (the frames' keys
    # are of what they show, not of their index)
    short, long = (_frame_keys(synthetic_rgbd_sequence(n, seed=1)) for n in (4, 1900))
    assert short[:4] != long[:4]


def test_a_frame_cache_that_is_a_file_renders_in_memory_with_one_warning(tmp_path,
                                                                         monkeypatch):
    """$PHJAX_FRAME_CACHE naming a file was 'error: NotADirectoryError ...', exit 2."""
    from phjax.live._sources import FRAME_CACHE_ENV

    not_a_folder = tmp_path / "file"
    not_a_folder.write_text("x")
    monkeypatch.setenv(FRAME_CACHE_ENV, str(not_a_folder))
    lines = []
    src = SyntheticSource(1, 1, estimator=_SlowEstimator(0.0), report=lines.append)
    src.open()
    assert src.cache is None and src.rendered == 1 and src.sequence[0].color.shape[2] == 3
    assert f"${FRAME_CACHE_ENV}={not_a_folder} is unusable" in lines[0], lines
    assert "in memory" in lines[0] and "in memory" in lines[1] and len(lines) == 3, lines
    assert not_a_folder.read_text() == "x"


@pytest.mark.parametrize("spec", ["synthetic:3:-1", "synthetic:3:4294967296",
                                  "synthetic:3:99999999999999999999"])
def test_a_synthetic_seed_outside_0_to_2_32_is_one_line(spec):
    """A huge seed was an OverflowError, a negative one a message not naming the seed."""
    seed = spec.split(":")[2]
    with pytest.raises(SourceError, match=rf"bad synthetic source '{spec}': SEED {seed} out "
                       r"of range; use synthetic\[:N\[:SEED\]\] \(N >= 1 frames, 0 <= SEED < "
                       r"2\*\*32\)"):
        open_source(spec, worker=False)
    with pytest.raises(SourceError, match=f"SEED {seed} out of range"):
        SyntheticSource(3, int(seed))
    assert open_source("synthetic:3:4294967295", worker=False).seed == 2**32 - 1


# ------------------------------------------------------------------------------- status
def test_status_line_reports_input_output_lost_age_and_lookahead():
    import re

    import equinox as eqx

    t, p, q = smooth_motion(150, 30.0, seed=6)  # 5 s, the face lost for 1 s
    lost = (t >= 2.0) & (t < 3.0)
    p[lost], q[lost] = np.nan, np.nan
    cfg = eqx.tree_at(lambda c: c.lookahead, live_tracker_config(), 0.02)
    lt, _ = _run(PoseReplaySource(t, p, q), 120.0, config=cfg, linger=0.0)
    line = lt.status_line()
    print("\n" + line)
    assert "\n" not in line
    fps = float(re.search(r"in +([\d.]+) fps", line).group(1))
    hz = float(re.search(r"out +([\d.]+) Hz", line).group(1))
    # the send at the start's deadline opens the window, it is not in it (counted, the first
    # status and the summary read (n + 1) / n of the rate: 416 Hz on a one-frame run)
    assert abs(fps - 30.0) < 0.5 and abs(hz - 120.0) < 0.05
    assert f"lost {lost.sum()} (no pose {lost.sum()})" in line
    assert "lookahead 20 ms" in line and "missed 0" in line
    s = lt.stats()
    assert s["lost"] == lost.sum() and s["lookahead"] == 0.02
    assert s["sent_hz"] == pytest.approx(120.0, abs=1e-6)  # the virtual clock: exact


def test_status_line_shows_the_noise_the_floor_measured():
    """A pose source with 20 mm / 3 deg of white noise (the live filter assumes 5 mm / 1 deg):
    the online noise floor raises the filter's noise, and the status line says so, with a
    value near the truth (the same source without noise: no noise field)."""
    import re

    from phjax._np_quat import np_from_rotvec, np_qmul

    t, p, q = smooth_motion(240, 30.0, seed=7)  # 8 s
    rng = np.random.default_rng(7)
    noisy_p = p + rng.normal(0, 0.02, p.shape)
    noisy_q = np_qmul(np_from_rotvec(rng.normal(0, np.radians(3.0), (len(t), 3))), q)
    lt, _ = _run(PoseReplaySource(t, noisy_p, noisy_q), 120.0, linger=0.0)
    line = lt.status_line()
    print("\n" + line)
    mm, deg = (float(x) for x in re.search(r"\| noise (\d+) mm, ([\d.]+) deg$", line).groups())
    # the truth is 20 mm / 3 deg (the running estimate: within 15 %)
    assert 17 <= mm <= 23 and 2.55 <= deg <= 3.45, line
    s = lt.stats()
    assert s["noise_raised"] and s["noise"][0] == pytest.approx(mm / 1e3, abs=5e-4)
    clean, _ = _run(PoseReplaySource(t, p, q), 120.0, linger=0.0)
    assert "noise" not in clean.status_line() and not clean.stats()["noise_raised"]


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


@pytest.mark.optimised
@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs /proc (Linux)")
@pytest.mark.slow
def test_soak_a_quarter_hour_of_camera_frames(tmp_path):
    """27 000 camera frames at 30 Hz (a quarter of an hour) replayed on the virtual clock with a
    30 Hz render loop, opentrack output and log: bounded memory, no drift, no leak. (An hour,
    then half an hour, cost 80 s and 35-39 s of the suite's CPU time; the RSS bound below is
    scaled with the span, so the smallest leak per frame it catches is the same: ~60 bytes.)"""
    counter = UdpListener(keep=False)  # counts only: its own memory stays constant
    n, rate = 27_000, 30.0
    t, p, q = smooth_motion(n, 30.0, seed=5)
    threads0, fds0 = threading.active_count(), _fds()
    src = PoseReplaySource(t, p, q)
    rss = []  # at 3 and 13 virtual minutes

    def cb(s):
        if s.t in (180.0, 780.0):
            rss.append(_rss_mb())

    wall = time.perf_counter()
    lt = LiveTracker(src, [f"opentrack://127.0.0.1:{counter.port}"], rate=rate,
                     clock=VirtualClock(), log=tmp_path / "soak.tum", callback=cb, linger=0.0)
    lt.run()
    wall = time.perf_counter() - wall
    s = lt.stats()
    print(f"\nsoak: {lt.frames} frames, {lt.sent} samples in {wall:.1f} s wall "
          f"({s['elapsed']:.0f} s virtual); RSS {rss} MB")
    assert lt.frames == n and lt.error is None
    # the render clock: sample k at exactly k / rate, none missed
    last = lt.latest.t
    assert lt.sent + lt.waiting == lt.k
    assert abs(last - (lt.k - 1) / rate) < 1e-6 and lt.missed_deadlines == 0
    assert abs(last - t[-1]) <= 1 / rate
    # measured: +0.004 MB over 20 virtual minutes (half an hour's run); 1 MB over these 10
    # minutes catches a leak of 58 bytes a frame
    assert len(rss) == 2 and rss[1] - rss[0] < 1.0
    assert threading.active_count() == threads0 and _fds() == fds0
    assert os.path.getsize(tmp_path / "soak.tum") > 0
    counter.close()
    assert counter.count == lt.sent


def test_a_pose_file_with_one_pose_is_refused(tmp_path):
    """One pose is no motion to replay (as for phjax smooth); it was sent for ~2 s."""
    f = tmp_path / "one.txt"
    f.write_text("1 0 0 0 0 0 0 1\n")
    with pytest.raises(SourceError, match="1 pose\\(s\\); a replay needs at least 2"):
        open_source(f"poses:{f}")


def test_a_stray_first_pose_does_not_send_the_live_stream_away():
    """The live config gates outliers; a first pose 20 cm / 10 deg off a still head made the
    filter coast away on a wrong velocity and reject every later frame (the sent pose was
    16 m away after 8 s). The gate's reset takes the head up again within gate_reset."""
    t = np.arange(120) / 30
    p = np.tile([0.0, 0.0, 0.6], (120, 1))
    q = np.tile([1.0, 0.0, 0.0, 0.0], (120, 1))
    p[0] = [0.2, 0.0, 0.65]
    from phjax._np_quat import np_from_rotvec

    q[0] = np_from_rotvec(np.radians([0.0, 10.0, 0.0]))
    out = []
    lt = LiveTracker(PoseReplaySource(t, p, q), [], rate=120, clock=VirtualClock(),
                     callback=lambda s: out.append((s.t, s.position.copy())))
    lt.run()
    late = np.array([x for ts, x in out if ts > 1.0])
    assert late.size and np.abs(late - [0.0, 0.0, 0.6]).max() < 0.01


def test_a_failing_log_still_closes_the_source_and_stop_before_start_is_final(tmp_path):
    """A log on a full disk made stop() raise before the source was closed (its UDP socket
    stayed bound); stop() before start() left start() running nothing on a re-bound socket."""
    import os
    import socket

    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    from phjax.live._udp import UdpSource

    lt = LiveTracker(UdpSource("127.0.0.1", 0, report=lambda line: None), [], rate=60,
                     duration=1.0, log="/dev/full")
    lt.start()
    port = lt.source.port
    lt.wait(5)
    from phjax.live import OutputError

    with pytest.raises(OutputError, match="cannot write the log /dev/full: No space left"):
        lt.stop()  # the log named (was the bare OSError)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))  # free again
    s.close()
    early = LiveTracker(PoseReplaySource([0.0, 0.1], np.zeros((2, 3)),
                                         np.tile([1.0, 0, 0, 0], (2, 1))), [])
    early.stop()
    with pytest.raises(RuntimeError, match="stopped before it started"):
        early.start()


@pytest.mark.parametrize("rotation_horizon", [None, 0.06])
def test_adaptive_settling_lengthens_each_horizon_to_the_measurement_interval(rotation_horizon):
    """A source at 5 Hz: the runner's adaptive settling sets the horizon (and an orientation
    horizon of its own, if the config has one) to the interval between measurements, 0.2 s,
    and ``coast_time`` to 1.5 times the longer one; the configured values are the floor."""
    t, p, q = smooth_motion(15, 5.0, seed=4)  # 3 s at 5 Hz
    cfg = dataclasses.replace(live_tracker_config(), rotation_horizon=rotation_horizon)
    lt, got = _run(PoseReplaySource(t, p, q), 60.0, config=cfg)
    used = lt._config_used
    assert lt.error is None and len(got) > 100
    np.testing.assert_allclose(float(used.horizon), 0.2, rtol=0.16)
    if rotation_horizon is None:
        assert used.rotation_horizon is None
    else:
        np.testing.assert_allclose(float(used.rotation_horizon), 0.2, rtol=0.16)
    h = max(float(used.horizon), float(used.rotation_horizon or 0))
    assert float(used.coast_time) == pytest.approx(max(float(cfg.coast_time), 1.5 * h))
    stats = lt.stats()
    assert stats["horizon"] == float(used.horizon)
    assert stats["rotation_horizon"] == float(used.rotation_horizon or used.horizon)
