"""``phjax live`` end to end over loopback: the acceptance run, bad input, signals."""

from __future__ import annotations

import os
import signal
import struct
import subprocess
import sys
import time

import jax
import numpy as np
import pytest
from conftest import shared_path
from live_helpers import (  # noqa: F401
    StallProbe,
    UdpListener,
    angle_steps,
    listener,
    model_cache,
    smooth_motion,
)

from phjax.cli import main
from phjax.io import Trajectory, read_tum, write_tum
from phjax.live import opentrack_values


@pytest.fixture
def cli_jax_config():
    """The CLI turns JAX's asynchronous CPU dispatch off; restore it for the other tests."""
    old = jax.config.read("jax_cpu_enable_async_dispatch")
    yield
    jax.config.update("jax_cpu_enable_async_dispatch", old)


def _gt_opentrack(times):
    """opentrack values of the synthetic head's ground truth relative to its first frame
    (the RGB-D front-end's reference), at the frames nearest to ``times``."""
    from phjax._np_quat import np_qconj, np_qmul
    from phjax.vision import open_rgbd

    seq = open_rgbd(f"synthetic:{ACCEPTANCE_FRAMES}")
    gt = seq.ground_truth
    rel = np_qmul(gt.quaternions, np_qconj(gt.quaternions[:1]))
    i = np.clip(np.round(np.asarray(times) * 30.0).astype(int), 0, len(seq) - 1)
    return np.array([opentrack_values(np.zeros(3), q)[3:] for q in rel[i]])


#: frames of the rendered head in the acceptance run: 4 s at 30 Hz, frames 0 ... 120 (with 6 s,
#: as until 2026-11-30, the test took 43 s instead of 29, most of it rendering the 60 frames)
ACCEPTANCE_FRAMES = 121


@pytest.mark.slow
@pytest.mark.serial
def test_acceptance_synthetic_opentrack(listener, model_cache, tmp_path, cli_jax_config, capsys):  # noqa: F811
    """phjax live synthetic:121 --output opentrack://127.0.0.1:PORT --rate 120 --duration 4
    (the 121 frames of 4 s at 30 Hz, rendered before the run: about 30 s on 2 cores)."""
    log = tmp_path / "sent.tum"
    rate = 120.0
    with StallProbe() as probe:
        rc = main(["live", f"synthetic:{ACCEPTANCE_FRAMES}", "--output",
                   f"opentrack://127.0.0.1:{listener.port}", "--rate", str(rate), "--duration", "4",
                   "--log", str(log), "--model-dir", str(model_cache), "--status-interval", "2",
                   "--realtime"])
        listener.close()
    err = capsys.readouterr().err
    assert rc == 0, err
    arrival = np.array([a for a, _ in listener.packets])
    sizes = {len(d) for _, d in listener.packets}
    assert sizes == {48}
    vals = np.array([struct.unpack("<6d", d) for _, d in listener.packets])
    assert np.isfinite(vals).all()
    n = len(vals)
    span = arrival[-1] - arrival[0]
    iv = np.diff(arrival)
    sent = read_tum(log)
    print(f"\n{n} datagrams, {(n - 1) / span:.1f} Hz over {span:.2f} s; intervals p50 "
          f"{1e3 * np.median(iv):.2f} ms p99 {1e3 * np.percentile(iv, 99):.2f} ms max "
          f"{1e3 * iv.max():.2f} ms")
    print(err.strip().splitlines()[-2:])
    print(probe.summary())
    # exactly what was logged was sent (log and datagrams in the same order)
    assert sent.num_samples == n
    expect = np.array([opentrack_values(p, q) for p, q in zip(sent.positions, sent.quaternions)])
    np.testing.assert_allclose(vals, expect, rtol=0, atol=1e-9)
    # rate and jitter. An interval over 3 periods that the stall probe saw the host stall in
    # too (a gap of a period or more on one of its CPUs) is the host's, not the tracker's (CI
    # on 2026-12-02: 16 missed deadlines, intervals up to 59 ms, 7 camera frames late in the
    # front-end's process as well; never seen on an idle machine, nor with both cores busy
    # with other work: p99 9.4 and 14 ms); the host's may not take more than a tenth of the run
    assert 0.9 * rate <= (n - 1) / span <= 1.1 * rate
    long = iv > 3.0 / rate
    host = np.zeros_like(long)
    host[long] = probe.covered(arrival[:-1][long], arrival[1:][long], min_gap=1.0 / rate)
    print(f"intervals over 3 periods: {long.sum()}, {host.sum()} of them host stalls")
    assert iv[host].sum() <= 0.1 * span, probe.summary()
    assert np.percentile(iv[~host], 99) <= 3.0 / rate, probe.summary()
    # smoothness: no step above 1 cm or 2 degrees per render period between consecutive
    # datagrams. Per period of the poses' own times: a render sample that missed its deadline
    # (a stalled host; the rate and jitter bounds above limit those) leaves a gap over which
    # the head really moves (seen in CI on 2026-12-01: 3.3 deg across a 46 ms gap of a 60 deg/s
    # turn, 0.8 deg at the 99th percentile), a jump does not
    periods = np.maximum(np.diff(sent.times) * rate, 1.0)[:, None]
    step_cm = np.abs(np.diff(vals[:, :3], axis=0)) / periods
    step_deg = angle_steps(vals[:, 3:]) / periods
    worst = int(np.argmax(step_deg.max(1)))
    print(f"largest step per period {step_cm.max():.3f} cm, {step_deg.max():.3f} deg (at t = "
          f"{sent.times[worst]:.2f} s, {periods[worst, 0]:.1f} periods); 99th percentile "
          f"{np.percentile(step_deg.max(1), 99):.3f} deg")
    assert step_cm.max() <= 1.0 and step_deg.max() <= 2.0
    # the head's turns are visible: each angle follows the ground truth
    truth = _gt_opentrack(sent.times)
    for j, name in enumerate(("yaw", "pitch", "roll")):
        got, ref = vals[:, 3 + j], truth[:, j]
        corr = np.corrcoef(got, ref)[0, 1]
        print(f"{name}: range {np.ptp(got):.2f} deg (truth {np.ptp(ref):.2f}), corr {corr:.3f}")
        assert np.ptp(got) > 0.5 * np.ptp(ref) and corr > 0.7


@pytest.mark.parametrize("argv, message", [
    (["live", "nonsense:1"], "unknown source"),
    (["live", "poses:/nonexistent/file.tum"], "not found"),
    (["live", "webcam:x"], "bad webcam index"),
    (["live", "synthetic:abc"], "synthetic"),
    # a path that does not exist is named as one (was "unknown source ...: use synthetic...")
    (["live", "/nonexistent/video.avi"], "/nonexistent/video.avi: No such file or directory"),
    (["live", "nonexist.mp4"], "error: nonexist.mp4: No such file or directory"),
    (["live", "no_such_dir/clip"], "no_such_dir/clip: No such file or directory"),
    # OpenCV crashed on -1 (signal 11) and failed twice-prefixed on a huge index
    (["live", "webcam:-1"], "bad webcam index '-1'; use webcam[:INDEX] with INDEX 0-99"),
    (["live", "webcam:99999999999"], "bad webcam index '99999999999'; use webcam[:INDEX]"),
    (["live", "synthetic:3:99999999999999999999"],
     "bad synthetic source 'synthetic:3:99999999999999999999': SEED 99999999999999999999 out "
     "of range; use synthetic[:N[:SEED]] (N >= 1 frames, 0 <= SEED < 2**32)"),
    (["live", "synthetic:3:-1"], "SEED -1 out of range"),
    (["live", "poses:{poses}", "--duration", "inf"],
     "argument --duration: must be a positive finite number, got 'inf'"),
    (["live", "poses:{poses}", "--duration", "nan"], "argument --duration"),
    (["live", "poses:{poses}", "--head-size", "inf"],
     "argument --head-size: must be between 0.05 and 0.5 m, got 'inf'"),
    (["live", "poses:{poses}", "--head-size", "1e-300"], "argument --head-size"),
    (["live", "poses:{poses}", "--head-size", "1e300"], "argument --head-size"),
    (["live", "poses:{poses}", "--ipd", "63"],
     "argument --ipd: must be between 0.03 and 0.1 m, got '63'"),
    (["live", "poses:{poses}", "--ipd", "nan"], "argument --ipd"),
    (["live", "poses:{poses}", "--fov", "inf"],
     "argument --fov: must be between 10 and 170 degrees, got 'inf'"),
    (["live", "poses:{poses}", "--output", "udp://127.0.0.1:5"], "unknown output"),
    (["live", "poses:{poses}", "--output", "opentrack://127.0.0.1:99999"], "port"),
    (["live", "poses:{poses}", "--output", "opentrack://:4242"], "missing host"),
    (["live", "poses:{poses}", "--output", "osc://no-such-host.invalid:9000"], "resolve"),
    (["live", "poses:{poses}", "--output", "opentrack://127.0.0.1:4242?from={busy}"],
     "cannot use local port"),
    (["live", "poses:{poses}", "--log", "/nonexistent/dir/x.tum"], "cannot write the log"),
    # the log replaced the recording it replayed
    (["live", "poses:{poses}", "--log", "{poses}"], "p.tum: is the replayed pose file"),
    # FFmpeg "played" a pose file named without poses: for 27 s, sending nothing
    (["live", "{poses}"], "p.tum: a pose file is replayed with poses:"),
    (["live", "poses:{poses}", "--rate", "0"], "rate"),
    (["live", "poses:{poses}", "--noise-window", "3"],
     "argument --noise-window: must be 0 (off) or an integer >= 8, got '3'"),
    (["live", "poses:{poses}", "--noise-window", "-1"], "argument --noise-window"),
    (["live", "poses:{poses}", "--noise-window", "6.5"], "argument --noise-window"),
    (["live", "poses:{poses}#P01_V1"], "#NAME selects one of several"),
    (["live", "poses:{cwi}"], "holding 27 trajectories; name one as poses:FILE#NAME"),
    (["live", "poses:{cwi}#P99"], "no trajectory named 'P99'"),
    # named as a folder (was "pose file not found"); the option to pass is live's own
    (["live", "poses:{tmp}"], "a folder (poses:FILE takes a pose file)"),
    # comments only: said "cannot detect the format; pass --format", which only led to this
    (["live", "poses:{comment}"], "comment.tum: no data lines (only # comments)"),
    (["live", "poses:{comment}", "--format", "tum"], "comment.tum: no data lines"),
    (["live", "UDP://127.0.0.1:0"], "port 0 out of range"),  # a URL scheme in any case
])
def test_bad_input_exits_2(argv, message, tmp_path, capsys):
    poses = tmp_path / "p.tum"
    write_tum(poses, Trajectory(*smooth_motion(10, 30.0)))
    import socket

    busy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    busy.bind(("", 0))
    try:
        cwi = (shared_path("vr_cwi_6dof_navigation", "H1_longdress_nav.csv")
               if "{cwi}" in " ".join(argv) else None)
        comment = tmp_path / "comment.tum"
        comment.write_text("# only a comment\n")
        args = [a.format(poses=poses, busy=busy.getsockname()[1], cwi=cwi, tmp=tmp_path,
                         comment=comment) for a in argv]
        assert main(args) == 2
    finally:
        busy.close()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("phjax live: error:") and message in err[0], err


def test_bad_input_process_has_no_traceback(tmp_path):
    """As a process: exit code 2, one line on stderr, no traceback."""
    r = subprocess.run([sys.executable, "-m", "phjax", "live", "realsense:123",
                        "--output", "opentrack://127.0.0.1:4242"], capture_output=True,
                       text=True, timeout=120, check=False)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("phjax")]
    assert len(lines) == 1 and "realsense" in lines[0].lower(), r.stderr
    assert "Traceback" not in r.stderr


def test_process_errors_are_one_line_without_library_logs(tmp_path, model_cache):  # noqa: F811
    """What reached stderr besides the one-line error: FFmpeg's ``moov atom not found`` before
    "cannot open video file", OpenCV's ``[ WARN ...] setPreferableTarget`` on every vision run,
    and the worker's errors as ``RGBDFormatError: ... (rgbd_io.py:256)`` where track-rgbd says
    the message alone (found by probing)."""
    import cv2

    garbage = tmp_path / "garbage.mp4"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, np.uint8).tobytes())
    folder = tmp_path / "rgbd"
    for sub in ("color", "depth"):
        (folder / sub).mkdir(parents=True)
    for i in range(1, 5):
        cv2.imwrite(str(folder / "color" / f"{i}.png"), np.full((48, 64, 3), 90, np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), np.full((48, 64), 900, np.uint16))
    damaged = tmp_path / "damaged"  # every colour image unreadable: the worker refuses it
    (damaged / "color").mkdir(parents=True)
    (damaged / "depth").symlink_to(folder / "depth")
    for i in range(1, 5):
        (damaged / "color" / f"{i}.png").write_text("not an image")
    (folder / "color" / "3.png").write_text("not an image")  # one unreadable: a lost frame

    def live(source, seconds):
        r = subprocess.run([sys.executable, "-m", "phjax", "live", str(source), "--quiet",
                            "--duration", str(seconds), "--model-dir", str(model_cache)],
                           capture_output=True, text=True, timeout=300, check=False)
        lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
        assert not [ln for ln in lines if "WARN" in ln or "moov" in ln], r.stderr
        return r, lines

    for source in (garbage, damaged):
        r, lines = live(source, 20)
        errors = [ln for ln in lines if "error" in ln.lower()]
        assert r.returncode == 2 and len(errors) == 1, r.stderr
        assert errors[0].startswith("phjax live: error:"), r.stderr
        assert ".py:" not in errors[0] and "FormatError" not in errors[0], r.stderr
    # one damaged image of four is a lost frame (it ended the replay before), said at the end
    r, lines = live(folder, 4)
    assert r.returncode == 0, r.stderr
    assert any("1 of 4 camera frames could not be read" in ln for ln in lines), r.stderr


# exec the command with SIGINT ignored (an ignored disposition survives exec; no preexec_fn,
# which is unsafe beside the test runner's threads)
_EXEC_IGNORING_SIGINT = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
                         "os.execv(sys.argv[1], sys.argv[1:])")
# ... and with SIGINT at its default, as in a terminal, whatever the test runner's worker has
# (seen in a full run: a worker ignoring SIGHUP, SIGINT and SIGQUIT after earlier tests, so the
# commands it started ignored Ctrl-C until live's own handler took over)
_EXEC_WITH_DEFAULT_SIGINT = _EXEC_IGNORING_SIGINT.replace("SIG_IGN", "SIG_DFL")


@pytest.mark.parametrize("sig, ignored", [(signal.SIGTERM, False), (signal.SIGINT, False),
                                          (signal.SIGINT, True)],
                         ids=["SIGTERM", "SIGINT", "SIGINT-inherited-ignored"])
def test_signal_stops_cleanly(sig, ignored, listener, tmp_path):  # noqa: F811
    """SIGTERM / Ctrl-C: exit 0, the log flushed and complete (in a child process, so that the
    signal can never reach the test runner; the in-process shutdown -- threads joined, sockets
    closed -- is checked by the runner tests). ``ignored``: the child starts with SIGINT
    ignored, as a job started with '&' from a non-interactive shell (or CI) does; Python then
    raises no KeyboardInterrupt, and before phjax installed its own SIGINT handler the child
    ran on after Ctrl-C until the test killed it."""
    poses = tmp_path / "p.tum"
    write_tum(poses, Trajectory(*smooth_motion(3000, 30.0)))
    log = tmp_path / "sent.tum"
    cmd = [sys.executable, "-m", "phjax", "live", f"poses:{poses}", "--output",
           f"opentrack://127.0.0.1:{listener.port}", "--log", str(log), "--rate", "120",
           "--quiet", "--duration", "300"]
    if ignored:
        cmd = [sys.executable, "-c", _EXEC_IGNORING_SIGINT, *cmd]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while len(listener.packets) < 30 and time.monotonic() < deadline:  # running: handlers set
            if proc.poll() is not None:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()[1]
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    time.sleep(0.2)
    listener.close()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    sent = read_tum(log)
    assert sent.num_samples == len(listener.packets) > 20
    assert "sent" in err


def test_ctrl_c_while_the_background_compilation_ends_is_harmless(tmp_path):
    """After a short run the tracker's optimised program is still compiling (3-4 s of one core;
    the interpreter waits for it at exit). A Ctrl-C in that wait aborted the process from
    inside XLA ("terminate called ...", SIGABRT) once the stop handlers were restored; now the
    command waits for it itself with the signals held, says so once, and exits 0. Run as a
    process at XLA's default level (the suite's -O0 flag has no background compilation)."""
    poses = tmp_path / "p.tum"
    write_tum(poses, Trajectory(*smooth_motion(300, 30.0)))
    env = dict(os.environ)
    env["XLA_FLAGS"] = env.get("XLA_FLAGS", "").replace("--xla_backend_optimization_level=0", "")
    proc = subprocess.Popen([sys.executable, "-m", "phjax", "live", f"poses:{poses}",
                             "--duration", "0.3", "--quiet"], stderr=subprocess.PIPE, text=True,
                            env=env)
    lines = []
    try:
        for line in proc.stderr:  # the run's summary: the wait for the compilation follows
            lines.append(line)
            if line.startswith("phjax live: sent"):
                break
        for _ in range(2):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                time.sleep(0.2)
        rest = proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    err = "".join(lines) + rest
    assert proc.returncode == 0, err
    assert "terminate" not in err and "Traceback" not in err, err
    assert rest.count("finishing a background compilation") <= 1, err


def test_help_text():
    r = subprocess.run([sys.executable, "-m", "phjax", "live", "--help"], capture_output=True,
                       text=True, timeout=120, check=False)
    assert r.returncode == 0
    for word in ("opentrack://", "osc://", "--rate", "--duration", "--log", "--center",
                 "synthetic", "webcam", "realsense", "poses:FILE"):
        assert word in r.stdout, word


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_stop_signal_during_the_start_ends_in_one_line(tmp_path, capsys, monkeypatch, sig):
    """The start (rendering frames, compiling) can take a minute; a stop signal then printed
    a KeyboardInterrupt traceback (SIGINT), or killed the process without a word (SIGTERM:
    status -15; SIGUSR1: -10). Now: one line, status 0, the handlers put back."""
    import os

    import phjax.live as live

    def slow_open(*args, **kwargs):  # the signal arrives while the source opens
        os.kill(os.getpid(), getattr(signal, sig))
        time.sleep(1.0)
        raise AssertionError("the signal did not interrupt the start")

    monkeypatch.setattr(live, "open_source", slow_open)
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    rc = main(["live", "poses:whatever.txt", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 0, err
    assert err.strip() == f"phjax live: stopped by {sig} during the start; nothing was sent"
    assert {s: signal.getsignal(s) for s in before} == before


def _usr1_ignored(pid: int) -> bool:
    """Whether the process ignores SIGUSR1 (its SigIgn mask in /proc)."""
    with open(f"/proc/{pid}/status") as f:
        mask = next(int(line.split()[1], 16) for line in f if line.startswith("SigIgn:"))
    return bool(mask >> (signal.SIGUSR1 - 1) & 1)


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="needs Linux's /proc")
@pytest.mark.parametrize("sig, delay", [("SIGUSR1", 0.0), ("SIGINT", 0.0), ("SIGINT", 0.05),
                                        ("SIGINT", 0.3)])
def test_a_signal_while_the_command_imports_is_one_line_or_nothing(tmp_path, sig, delay):
    """In the first second (imports, before ``live`` installs its handlers) SIGUSR1 killed the
    process (status 138) and Ctrl-C printed a traceback. Sent as soon as ``main`` runs (it then
    ignores SIGUSR1 until live's own handler takes over): SIGUSR1 changes nothing (a re-centre
    before the start), SIGINT ends the run in one line. SIGINT also 50 ms and 0.3 s later: in
    jaxlib's import a KeyboardInterrupt crashed the process (status -11), in XLA's gc callback
    it was dropped and the poses were sent (CI, 2026-12-02); both moments measured on the
    2-core machine, where 2 of 16 delays between 0 and 2.5 s hit them."""
    src = tmp_path / "p.txt"
    write_tum(src, Trajectory(np.arange(30) / 30, np.zeros((30, 3)),
                              np.tile([1.0, 0, 0, 0], (30, 1))))
    proc = subprocess.Popen([sys.executable, "-c", _EXEC_WITH_DEFAULT_SIGINT, sys.executable, "-m",
                             "phjax", "live", f"poses:{src}", "--duration", "0.3", "--quiet"],
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not _usr1_ignored(proc.pid):  # main has started
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.005)
        time.sleep(delay)
        proc.send_signal(getattr(signal, sig))
        err = proc.communicate(timeout=300)[1]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert "Traceback" not in err, err
    if sig == "SIGUSR1":
        assert proc.returncode == 0, err
    else:  # interrupted while importing, or stopped by live's handler if it was already there
        assert (proc.returncode, err.strip()) in {
            (130, "phjax: interrupted"), (130, "phjax live: interrupted"),
            (0, "phjax live: stopped by SIGINT during the start; nothing was sent")}, err


def test_send_failures_are_reported_and_the_status_interval_is_checked(tmp_path, capsys):
    """Nothing listening on the output port: about half the packets were refused and the run
    said nothing (a mistyped port looked like a working one); --status-interval 0 printed a
    line every 0.1 s and nan none."""
    src = tmp_path / "p.txt"
    write_tum(src, Trajectory(np.arange(60) / 30, np.zeros((60, 3)),
                              np.tile([1.0, 0, 0, 0], (60, 1))))
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()  # a port nobody listens on
    rc = main(["live", f"poses:{src}", "-o", f"opentrack://127.0.0.1:{port}", "--duration",
               "1", "--quiet", "--rate", "60"])
    err = capsys.readouterr().err
    assert rc == 0
    assert f"opentrack://127.0.0.1:{port}: " in err and "packets could not be sent" in err
    for bad in ("0", "-1", "nan"):
        assert main(["live", f"poses:{src}", "--status-interval", bad]) == 2
        assert "argument --status-interval" in capsys.readouterr().err


def test_a_replaced_log_is_named_as_replaced(tmp_path, capsys):
    """Like the other commands' outputs, an existing --log file is said to be replaced (it was
    emptied without a word); a new one is not."""
    src = tmp_path / "p.txt"
    write_tum(src, Trajectory(np.arange(30) / 30, np.zeros((30, 3)),
                              np.tile([1.0, 0, 0, 0], (30, 1))))
    log = tmp_path / "sent.tum"
    argv = ["live", f"poses:{src}", "--duration", "0.2", "--quiet", "--log", str(log)]
    assert main(argv) == 0
    first = capsys.readouterr().err
    assert f", log {log}" in first and "(replaced the existing file)" not in first
    assert main(argv) == 0
    assert f", log {log} (replaced the existing file)" in capsys.readouterr().err
    assert read_tum(log).num_samples > 0


def test_reacquire_and_noise_window_options(tmp_path, capsys, monkeypatch):
    """The flags reach the tracker's config (--noise-window N, default 60; --reacquire), and
    re-acquisition works in the live runner, whose adaptive settling lengthens the horizon
    and coast time after a loss: a pose file with a 0.4 s gap across which the head moved
    0.3 m. By default the sent stream glides to the new pose (largest step per sample
    measured 0.052 m); with --reacquire it jumps there in one sample (0.300 m). The CLI's
    tracker runs on the virtual clock: on the real clock a render loop held up by the
    optimised program's background compilation (one core per test worker) skipped the whole
    glide once in ten runs, and sent it as one step."""
    import phjax.live as live

    configs = []

    class Recording(live.LiveTracker):
        def __init__(self, *args, config=None, **kwargs):
            configs.append(config)
            super().__init__(*args, config=config, **{**kwargs, "clock": live.VirtualClock()})

    monkeypatch.setattr(live, "LiveTracker", Recording)
    t = np.concatenate([np.arange(30) / 30, 1.4 + np.arange(15) / 30])
    p = np.zeros((len(t), 3))
    p[t >= 1.4, 0] = 0.3
    src = tmp_path / "gap.txt"
    write_tum(src, Trajectory(t, p, np.tile([1.0, 0, 0, 0], (len(t), 1))))
    steps = {}
    for flags, window, reacquire in (((), 60, False), (("--reacquire", "--noise-window", "0"),
                                                      0, True)):
        log = tmp_path / f"sent{len(flags)}.tum"
        assert main(["live", f"poses:{src}", "--quiet", "--log", str(log), *flags]) == 0, (
            capsys.readouterr().err)
        assert (configs[-1].noise_window, configs[-1].reacquire) == (window, reacquire)
        sent = read_tum(log).positions
        assert np.isfinite(sent).all() and abs(sent[-1, 0] - 0.3) < 0.01
        steps[reacquire] = np.abs(np.diff(sent[:, 0])).max()
    assert steps[True] > 0.25, steps  # one jump
    assert steps[False] < 0.1, steps  # a glide over several samples


@pytest.mark.parametrize("fails", [True, False])
def test_the_handlers_come_back_after_a_run_that_ends_or_fails(tmp_path, capsys, monkeypatch,
                                                               fails):
    """After the run Ctrl-C and SIGTERM are held (the optimised program may still be
    compiling) and then put back, on the error path as well: there the holder was left
    installed (installed in a ``finally`` that ran after the error's return), so a caller
    of ``main`` in-process could no longer be stopped with Ctrl-C."""
    import phjax.live as live

    src = tmp_path / "p.txt"
    write_tum(src, Trajectory(np.arange(60) / 30, np.zeros((60, 3)),
                              np.tile([1.0, 0.0, 0.0, 0.0], (60, 1))))

    def run(self, *args, **kwargs):
        if fails:
            raise RuntimeError("the camera was unplugged")

    monkeypatch.setattr(live.LiveTracker, "start", lambda self: None)
    monkeypatch.setattr(live.LiveTracker, "run", run)
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    rc = main(["live", f"poses:{src}", "--quiet"])
    err = capsys.readouterr().err
    assert rc == (1 if fails else 0), err
    assert ("phjax live: error: the camera was unplugged" in err) == fails
    assert {s: signal.getsignal(s) for s in before} == before
