"""Bad input the CLI took without a word (found in review): a value starting with '-' and a
digit read as an option, a pose file of absurd positions replayed as nothing, an 8-bit depth
folder that failed only after every frame, implausible --intrinsics. Each ends in ONE line on
stderr naming the file or option, exit status 2, or (some rows of a pose file) in a count.
Called in-process, without the tracker's compilation: the file runs in a few seconds."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli


@pytest.fixture(autouse=True)
def _jax_dispatch():
    """phjax live turns JAX's asynchronous CPU dispatch off; restore it for the other tests."""
    import jax

    old = jax.config.read("jax_cpu_enable_async_dispatch")
    yield
    jax.config.update("jax_cpu_enable_async_dispatch", old)


def _tum(path, positions):
    """A TUM file of the given positions at 30 Hz, identity orientation."""
    rows = [f"{i / 30:.6f} {x:.17g} {y:.17g} {z:.17g} 0 0 0 1"
            for i, (x, y, z) in enumerate(np.asarray(positions, float))]
    path.write_text("# t x y z qx qy qz qw\n" + "\n".join(rows) + "\n")
    return path


def _head(n=60):
    t = np.arange(n) / 30
    return np.stack([0.05 * np.sin(t), 0.02 * np.cos(t), 0.6 + 0.0 * t], -1)


# ----------------------------------------------------------------- 1: '-5,1' is a value
@pytest.mark.parametrize("value", ["-5,1", "-0.5,2", "-.5", "-1e3", "-5"])
def test_a_value_starting_with_minus_and_a_digit_is_the_options_value_in_every_command(value):
    """argparse read only plain negative numbers as values: '--measurement-noise -5,1' was
    "expected one argument". Every command's parser (one class) now reads such a word as the
    value of the option before it."""
    from phjax.cli._main import build_parser

    parser = build_parser()
    for name, command in parser.commands.items():
        command.add_argument("--probe")
        argv = [name]
        for action in command._actions:
            if not action.option_strings and action.required:
                argv.append("X")
            elif action.option_strings and action.required:
                argv += [action.option_strings[-1], "1"]
        args, extra = parser.parse_known_args([*argv, "--probe", value])
        assert (args.probe, extra) == (value, []), name


@pytest.mark.parametrize("value", ["-5,1", "-0.5,2"])
@pytest.mark.parametrize("command", ["smooth", "track-rgbd"])
def test_negative_measurement_noise_gives_the_options_own_error(tmp_path, capsys, command,
                                                                 value):
    good = _tum(tmp_path / "in.tum", _head(3))
    source = good if command == "smooth" else "synthetic:2"
    rc, out, err = run_cli(capsys, [command, source, "-o", tmp_path / "out.tum",
                                 "--measurement-noise", value])
    assert_one_line_error(rc, out, err, f"phjax {command}: error: argument "
                           f"--measurement-noise: stds must be positive and finite, got "
                           f"'{value}'")
    assert not (tmp_path / "out.tum").exists()


def test_real_options_still_read_as_options(tmp_path, capsys):
    """A word starting with '-' and a letter is still an option: an unknown one is named."""
    good = _tum(tmp_path / "in.tum", _head(3))
    rc, out, err = run_cli(capsys, ["smooth", good, "-o", tmp_path / "o.tum", "-x5"])
    assert_one_line_error(rc, out, err, "unrecognized arguments: -x5")


# ------------------------------------------------------- 2: poses:FILE of absurd values
@pytest.mark.parametrize("scale", [1e150, 1e30, 1e6])
def test_a_pose_file_of_absurd_positions_is_refused_in_one_line(tmp_path, capsys, scale):
    """Positions of 1e150 m made the stream non-finite: phjax live sent nothing and said
    nothing (exit 0); 1e30 m were sent to opentrack as they were. A position coordinate beyond
    10 m (udp://'s bound) is not a head pose: the file is refused before the tracker starts,
    in one line (the reader's unit warning, which it repeated, is left out)."""
    poses = _tum(tmp_path / "big.tum", _head() + [scale, 0, 0])
    log = tmp_path / "sent.tum"
    rc, out, err = run_cli(capsys, ["live", f"poses:{poses}", "--duration", "0.5", "--log", log])
    assert_one_line_error(rc, out, err, "phjax live: error: ", str(poses),
                           "60 of 60 rows hold a position beyond +-10 m", "0 usable pose(s)")
    assert not log.exists()


def test_a_pose_file_of_lost_frames_only_is_refused(tmp_path, capsys):
    poses = tmp_path / "lost.tum"
    poses.write_text("".join(f"{i / 30} nan nan nan nan nan nan nan\n" for i in range(5)))
    rc, out, err = run_cli(capsys, ["live", f"poses:{poses}", "--duration", "0.5"])
    assert_one_line_error(rc, out, err, str(poses), "5 lost frame(s)", "0 usable pose(s)")


class _Clock:
    def sleep_until(self, t, stop=None):
        pass


def test_absurd_rows_of_a_pose_file_are_replayed_as_lost_frames(tmp_path):
    """Some rows beyond the bound: the others are replayed; those reach the tracker as lost
    frames with their own status (the status line's 'lost N (OUT_OF_RANGE N)'), never as
    values."""
    from phjax.live import PoseReplaySource
    from phjax.live._sources import MAX_POSITION_M
    from phjax.live._udp import MAX_POSITION_CM

    assert MAX_POSITION_CM == 100 * MAX_POSITION_M  # one bound for both replays
    p = _head()
    bad = [10, 11, 30]
    p[bad, 0] = 1e150
    source = PoseReplaySource.from_file(_tum(tmp_path / "some.tum", p))
    assert "3 of 60 rows hold a position beyond +-10 m" in source.out_of_range_text()
    got = []
    source.run(_Clock(), 0.0, threading.Event(), got.append)
    assert len(got) == 60
    status = np.array([m.status for m in got])
    assert (status[bad] == "OUT_OF_RANGE").all() and (np.delete(status, bad) == "OK").all()
    for i, m in enumerate(got):
        if i in bad:
            assert not m.ok and np.isnan(m.position).all() and np.isnan(m.quaternion).all()
        else:
            np.testing.assert_allclose(m.position, p[i], rtol=1e-12)
    # arrays given directly: an infinite position is out of range too
    inf = PoseReplaySource([0.0, 1.0], [[0, 0, np.inf], [0, 0, 0.6]], [[1.0, 0, 0, 0]] * 2)
    assert inf.out_of_range.tolist() == [True, False]


def test_live_names_the_dropped_rows_at_the_start(tmp_path, capsys, monkeypatch):
    """The start of phjax live says how many rows are dropped and why (a stand-in for the
    tracker: the real one compiles for seconds)."""
    import phjax.live

    class Tracker:
        def __init__(self, source, outputs, **kwargs):
            self.source, self.outputs = source, []

        def start(self):
            pass

        def run(self, status, status_interval):
            pass

        def stop(self, timeout=None):
            pass

        def stats(self):
            return {"sent": 0, "elapsed": 0.0, "sent_hz": float("nan"), "frames": 0,
                    "send_errors": {}, "out_of_range": {}, "status": {}}

    monkeypatch.setattr(phjax.live, "LiveTracker", Tracker)
    p = _head()
    p[5, 2] = -1e150
    poses = _tum(tmp_path / "some.tum", p)
    rc, out, err = run_cli(capsys, ["live", f"poses:{poses}", "--quiet"])
    assert rc == 0, err
    lines = err.strip().splitlines()
    assert lines[0].startswith(f"phjax live: poses {poses} -> none"), err
    assert lines[1] == (f"phjax live: warning: {poses}: 1 of 60 rows hold a position beyond "
                        "+-10 m, not a head pose (largest |coordinate| 1e+150 m; positions are "
                        "read in metres): replayed as lost frames (OUT_OF_RANGE in the status "
                        "line)"), err


# ----------------------------------------------------------------- 3: 8-bit depth images
def _pairs(folder, depth_dtype=np.uint16, size=(48, 64)):
    """A color/ + depth/ folder of three frames."""
    import cv2

    (folder / "color").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i in range(1, 4):
        cv2.imwrite(str(folder / "color" / f"{i}.png"), np.full((*size, 3), 90, np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{i}.png"), np.full(size, 200, depth_dtype))
    return folder


def _tum_rgbd(folder, depth_dtype=np.uint16):
    import cv2

    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    rgb, dep = [], []
    for i in range(3):
        t = 100 + i / 30
        cv2.imwrite(str(folder / "rgb" / f"{t:.6f}.png"), np.full((48, 64, 3), 90, np.uint8))
        cv2.imwrite(str(folder / "depth" / f"{t:.6f}.png"), np.full((48, 64), 200, depth_dtype))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t:.6f} depth/{t:.6f}.png")
    (folder / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (folder / "depth.txt").write_text("\n".join(dep) + "\n")
    return folder


@pytest.mark.parametrize("layout", ["pairs", "tum"])
def test_an_8_bit_depth_folder_is_refused_when_opened(tmp_path, layout):
    """8-bit depth PNGs were read as depth (at most 255 units: 0.05-0.26 m): every frame
    ended as NO_DEPTH, after the face detector had run on all of them."""
    from phjax.vision.rgbd_io import RGBDFormatError, open_rgbd

    make = _pairs if layout == "pairs" else _tum_rgbd
    folder = make(tmp_path / "eight", np.uint8)
    first = folder / "depth" / ("1.png" if layout == "pairs" else "100.000000.png")
    with pytest.raises(RGBDFormatError, match="an 8-bit depth image; depth must be 16-bit") as e:
        open_rgbd(folder)
    assert str(e.value).startswith(f"{first}: ")
    # 16-bit opens; a damaged first depth image is left to its frame (lost), as before
    sixteen = make(tmp_path / "sixteen")
    assert len(open_rgbd(sixteen)) == 3
    (sixteen / "depth" / first.name).write_text("not an image")
    seq = open_rgbd(sixteen)
    with pytest.raises(RGBDFormatError, match="not a readable image"):
        seq[0]
    assert seq[1].depth.dtype == np.float32


def test_track_rgbd_names_the_8_bit_depth_file(tmp_path, capsys):
    folder = _pairs(tmp_path / "eight", np.uint8)
    rc, out, err = run_cli(capsys, ["track-rgbd", folder, "-o", tmp_path / "o.tum"])
    assert_one_line_error(rc, out, err, "phjax track-rgbd: error: ",
                           str(folder / "depth" / "1.png"), "depth must be 16-bit")


# ---------------------------------------------------------------------- 4: --intrinsics
@pytest.mark.parametrize("value, message", [
    ("0,500,320,240", "focal lengths FX, FY must be > 0 pixels, got '0,500,320,240'"),
    ("-500,500,320,240", "focal lengths FX, FY must be > 0 pixels, got '-500,500,320,240'"),
    ("500,500,-1,240", "the principal point CX, CY must lie in the image (pixels >= 0)"),
    ("500,500,nan,240", "expected FX,FY,CX,CY (four finite numbers, pixels)"),
    ("500,500,320", "expected FX,FY,CX,CY"),
])
def test_bad_intrinsics_are_refused_when_parsed(tmp_path, capsys, value, message):
    folder = _pairs(tmp_path / "rgbd")
    rc, out, err = run_cli(capsys, ["track-rgbd", folder, "-o", tmp_path / "o.tum",
                                 "--intrinsics", value])
    assert_one_line_error(rc, out, err, "argument --intrinsics: " + message)


@pytest.mark.parametrize("layout", ["pairs", "tum"])
@pytest.mark.parametrize("value, centre", [("50,50,320,240", "CX 320, CY 240"),
                                           ("50,50,20,48", "CX 20, CY 48")])
def test_a_principal_point_outside_the_first_image_is_refused(tmp_path, capsys, layout, value,
                                                              centre):
    """A centre for another resolution (320,240 for 64 x 48 images) gave garbage poses."""
    folder = (_pairs if layout == "pairs" else _tum_rgbd)(tmp_path / "rgbd")
    rc, out, err = run_cli(capsys, ["track-rgbd", folder, "-o", tmp_path / "o.tum",
                                 "--intrinsics", value])
    assert_one_line_error(rc, out, err, f"phjax track-rgbd: error: --intrinsics {value}: the "
                           f"principal point ({centre}) lies outside the 64 x 48 images of "
                           f"{folder} (CX 0-63, CY 0-47 pixels)")
    assert not (tmp_path / "o.tum").exists()


def test_a_principal_point_within_the_image_is_accepted():
    from phjax.cli._rgbd import _check_principal_point
    from phjax.vision.rgbd_io import CameraIntrinsics

    for cx, cy in ((0, 0), (63, 47), (31.5, 23.5)):
        _check_principal_point(CameraIntrinsics(50.0, 50.0, cx, cy, width=64, height=48),
                               (50, 50, cx, cy), "folder")
