"""The CLI's one error path: every bad input of issue 18 (missing / folder / empty / malformed /
too short / binary / undetectable files, rates <= 0 or non-finite, unknown formats, unusable
output names) ends with exit status 2 and ONE line on stderr naming the file (and the line), no
traceback, no output file -- for every command that reads a trajectory. Called in-process
(``main([...])``), nothing is computed, so the file runs in seconds."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli

from phjax.cli import main

TUM_ROW = "1.0 0 0 0 0 0 0 1\n"

#: (name, file content or None for "no such file", expected message part); "DIR": a folder
BAD_FILES = [
    ("missing", None, "No such file or directory"),
    ("folder", "DIR", "Is a directory"),
    ("empty", "", "empty file"),
    ("blank", "\n\n   \n", "empty file"),
    ("malformed", TUM_ROW + "2.0 0 0 0 0 0 1\n", "line 2: expected 8 columns"),
    ("non-numeric", TUM_ROW + "2.0 0 0 x 0 0 0 1\n", "line 2: non-numeric value 'x'"),
    ("one pose", TUM_ROW, "1 pose(s); at least 2 are needed"),
    ("only lost frames", "1 nan nan nan nan nan nan nan\n2 nan nan nan nan nan nan nan\n",
     "0 pose(s) (2 lost frame(s)); at least 2"),
    ("binary", b"\x89PNG\r\n\x1a\n\xff\xfe\x00", "not a UTF-8 text file"),
    # the command line's own option, not the library's keyword
    ("undetectable", "1 2 3\n", "first lines; pass --format, one of"),
]

#: commands reading one trajectory file FILE (OUT: an output path in the temporary folder)
READERS = {
    "smooth": ["smooth", "FILE", "-o", "OUT.txt"],
    "evaluate": ["evaluate", "FILE", "--plot", "OUT.png", "--no-progress"],
    "demo": ["demo", "FILE", "--plot", "OUT.png", "--no-progress"],
    "demo-curve": ["demo-curve", "FILE"],
    "tune": ["tune", "FILE", "--lambda", "1", "-o", "OUT.json"],
}


def _materialise(tmp_path, argv, content):
    path = tmp_path / "input.txt"
    if content == "DIR":
        path = tmp_path / "a_folder"
        path.mkdir()
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        path.write_text(content)
    out = tmp_path / "result"
    return [str(path) if a == "FILE" else a.replace("OUT", str(out)) for a in argv], path, out


@pytest.mark.parametrize("command", sorted(READERS))
@pytest.mark.parametrize("name, content, message", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_bad_input_file_gives_one_line_and_status_2(tmp_path, capsys, command, name, content,
                                                    message):
    argv, path, out = _materialise(tmp_path, READERS[command], content)
    rc, stdout, err = run_cli(capsys, argv)
    assert_one_line_error(rc, stdout, err, str(path), message, f"phjax {command}: error:")
    assert not any(out.parent.glob(out.name + "*")), "no output for bad input"


BAD_ARGUMENTS = [
    # (argv with FILE = a valid two-pose TUM file, expected message part)
    (["smooth", "FILE", "-o", "OUT.txt", "--rate", "0"], "argument --rate: must be a positive"),
    (["smooth", "FILE", "-o", "OUT.txt", "--lookahead", "300"],
     "--lookahead must be between 0 and 200 ms, got 300"),
    (["smooth", "FILE", "-o", "OUT.txt", "--lookahead", "20", "--offline"],
     "the offline reconstruction (--offline) has no lookahead"),
    (["smooth", "FILE", "-o", "OUT.txt", "--rate", "-5"], "argument --rate: must be a positive"),
    (["smooth", "FILE", "-o", "OUT.txt", "--rate", "nan"], "argument --rate: must be a positive"),
    (["smooth", "FILE", "-o", "OUT.txt", "--rate", "inf"], "argument --rate: must be a positive"),
    (["smooth", "FILE", "-o", "OUT.txt", "--rate", "fast"], "argument --rate: not a number"),
    (["demo", "--rate", "0"], "argument --rate: must be a positive"),
    (["demo", "--camera-rate", "-30"], "argument --camera-rate: must be a positive"),
    (["demo", "--duration", "0"], "argument --duration: must be a positive"),
    (["demo", "--dropout", "1"], "argument --dropout: must be in [0, 1)"),
    (["evaluate", "FILE", "--rate", "-1"], "argument --rate: must be a positive"),
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--rate", "0"], "argument --rate"),
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--parameters", "horizon,pos_process_noise"],
     "unknown tracker parameter(s) ['pos_process_noise']"),  # the single-model filter's, not the IMM's
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--measured", "FILE", "FILE"],
     "--measured: give one measurement file per ground-truth file, got 2 for 1"),
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--align"], "--align needs --measured"),
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--measured", "FILE"],
     "overlap for too short a time"),  # a two-pose file: no render samples
    (["track-rgbd", "synthetic:2", "-o", "OUT.tum", "--rate", "0"], "argument --rate"),
    (["demo-curve", "FILE", "--stride", "0"], "argument --stride: must be an integer >= 1"),
    # were tracebacks (OverflowError, XLA's RESOURCE_EXHAUSTED) or accepted and failing late
    (["demo", "--seed", "9223372036854775808"],
     "argument --seed: must be an integer between 0 and 2^32 - 1"),
    (["evaluate", "FILE", "--seed", "-1"], "argument --seed: must be an integer between 0"),
    (["demo", "--rgbd", "-1"], "argument --rgbd: must be an integer >= 0"),
    (["demo", "--lookahead", "1e6"], "argument --lookahead: must be between 0 and 200 ms"),
    (["tune", "FILE", "--lambda", "inf", "-o", "OUT.json"], "argument --lambda: must be a finite"),
    (["demo-curve", "FILE", "--samples", "1000000000000"],
     "--samples 1000000000000 x 1 segments makes 1e+12 samples"),
    (["live", "poses:FILE", "--log="], "argument --log: needs a file name"),
    (["live", "poses:FILE", "--bogus"], "phjax live: error: unrecognized arguments: --bogus"),
    (["smooth", "FILE", "-o", "OUT.txt", "--format", "kitti"], "argument --format: invalid choice"),
    (["smooth", "FILE", "-o", "OUT.txt", "--out-format", "kitti"], "argument --out-format"),
    (["evaluate", "FILE", "--format", "kitti"], "argument --format: invalid choice"),
    (["demo-curve", "FILE", "--format", "kitti"], "argument --format: invalid choice"),
    (["smooth", "FILE", "-o", "OUT.xyz"], "cannot choose a format from the extension '.xyz'; "
     "pass --out-format tum, euroc or csv, or name the file .tum, .txt or .csv"),
    (["track-rgbd", "synthetic:2", "-o", "OUT.xyz"], "extension '.xyz'; name the file .tum"),
    (["track-rgbd", "synthetic:2", "-o", "OUT.tum", "--raw", "OUT"], "extension ''; name the"),
    (["smooth", "FILE", "-o", "NOFOLDER/o.txt"], "No such folder for the output file"),
    (["evaluate", "FILE", "--plot", "NOFOLDER/p.png"], "No such folder for the plot file"),
    (["evaluate", "FILE", "--plot", "OUT.xyz", "--no-progress"],
     "cannot write a figure as '.xyz'; use one of .png"),
    (["smooth", "FILE", "-o", "OUT.txt", "--config", "NOFOLDER/c.json"], "c.json"),
    (["track-rgbd", "NOFOLDER", "-o", "OUT.tum"], "RGB-D source not found"),
    # the same check as phjax live's (was an OverflowError traceback / a seedless message)
    (["track-rgbd", "synthetic:3:99999999999999999999", "-o", "OUT.tum"],
     "bad synthetic source 'synthetic:3:99999999999999999999': SEED 99999999999999999999 out "
     "of range; use synthetic[:N[:SEED]] (N >= 1 frames, 0 <= SEED < 2**32)"),
    (["track-rgbd", "synthetic:3:-1", "-o", "OUT.tum"], "SEED -1 out of range"),
    (["track-rgbd", "synthetic:0", "-o", "OUT.tum"], "bad synthetic source 'synthetic:0': N 0"),
    # a billion frames ran out of memory simulating the motion (or ran on for minutes)
    (["track-rgbd", "synthetic:1000000000", "-o", "OUT.tum"], "give fewer frames (N, or"),
    (["track-rgbd", "synthetic:2", "-o", "OUT.tum", "--model-dir", "NOFOLDER"],
     "not found in NOFOLDER: pass --model-dir FOLDER (a folder holding the model files"),
    # named the library's field in SI / the library's keyword, or ran out of memory, or was
    # ignored without a word, or wrote a TUM file under a .csv name
    (["smooth", "FILE", "-o", "OUT.txt", "--measurement-noise", "1e9,1e9"],
     "argument --measurement-noise: orientation std 1e+09 deg is out of range [5.73e-11, "
     "5.73e+07] deg"),
    (["smooth", "FILE", "-o", "OUT.txt", "--measurement-noise", "1e-12,1"],
     "argument --measurement-noise: position std 1e-12 mm is out of range [1e-09, 1e+09] mm"),
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--position-weight", "-1"],
     "argument --position-weight: must be a finite number >= 0, got '-1'"),
    (["tune", "FILE", "--lambda", "1", "-o", "OUT.json", "--rotation-weight", "nan"],
     "argument --rotation-weight: must be a finite number >= 0"),
    (["demo", "--duration", "1e9", "--no-progress"],
     "--duration 1e+09 s of synthetic motion (240 Hz) makes 2.4e+11 samples"),
    (["demo", "FILE", "--duration", "5"], "--duration sets the length of the synthetic motion; "
     "with an input file the whole file is used (leave out --duration)"),
    (["demo", "--rgbd", "2", "--duration", "5"], "--rgbd N sets the number of frames"),
    (["evaluate", "FILE", "--plot", ".", "--no-progress"],
     "Is a directory (expected a plot file name)"),
    (["live", "poses:FILE", "--log", "OUT.csv"], "the log is a TUM file (t x y z qx qy qz qw, "
     "space-separated); name it .tum or .txt"),
    (["smooth", "FILE"], "the following arguments are required: -o/--output"),
    (["smooth", "FILE", "-o", "OUT.txt", "--measurement-noise", "3,x"],
     "argument --measurement-noise: expected 'config', 'auto', 'floor' or 'MM,DEG'"),
    (["smooth", "FILE", "-o", "OUT.txt", "--measurement-noise", "0,1"],
     "argument --measurement-noise: stds must be positive and finite"),
    (["smooth", "FILE", "-o", "OUT.txt", "--measurement-noise", "5"],
     "argument --measurement-noise: expected"),
    (["track-rgbd", "synthetic:2", "-o", "OUT.tum", "--measurement-noise", "nan,1"],
     "argument --measurement-noise: stds must be positive and finite"),
    (["smooth", "FILE", "-o", "OUT.txt", "--measurement-noise", "auto"],
     "--measurement-noise auto: cannot estimate the noise from this input"),  # 2 poses
    # an output that names an input would destroy it
    (["smooth", "FILE", "-o", "FILE"], "good.txt: is the input file; writing the output would"),
    (["tune", "FILE", "--lambda", "1", "-o", "FILE"], "good.txt: is the input file; writing"),
    (["track-rgbd", "synthetic:2", "-o", "OUT.tum", "--raw", "OUT.tum"], "the same file as -o"),
    ([], "the following arguments are required: command"),
    (["frobnicate"], "invalid choice: 'frobnicate'"),
]


@pytest.mark.parametrize("field, value, message", [
    ("horizon", float("nan"), "TrackerConfig.horizon must be a finite number > 0, got nan"),
    ("horizon", "0.03", "tracker.horizon has an invalid value '0.03'"),  # a string: named as such
    ("horizon", -1.0, "TrackerConfig.horizon must be a finite number > 0, got -1.0"),
    ("stop_time", 0.0, "TrackerConfig.stop_time must be a finite number > 0, got 0.0"),
    ("lookahead", 5.0, "tracker.lookahead must be between 0 and 0.2 s, got 5"),
])
def test_config_file_values_are_checked(tmp_path, capsys, field, value, message):
    """A --config file with a value the stream cannot use ends in one line naming the field
    (a NaN horizon wrote an empty trajectory with status 0; a lookahead of 5 s went round
    --lookahead's bound)."""
    import json

    from phjax.tracking.tuning import config_to_dict

    good = tmp_path / "good.txt"
    good.write_text(TUM_ROW + "2.0 0 0 0 0 0 0 1\n")
    d = config_to_dict(pj_config())
    d["tracker"][field] = value
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps(d))
    rc, stdout, err = run_cli(capsys, ["smooth", str(good), "-o", str(tmp_path / "out.txt"),
                                    "--config", str(cfg)])
    assert_one_line_error(rc, stdout, err, message)
    assert not (tmp_path / "out.txt").exists()


def pj_config():
    from phjax import TrackerConfig

    return TrackerConfig()


@pytest.mark.parametrize("argv, message", BAD_ARGUMENTS, ids=lambda x: " ".join(x)
                         if isinstance(x, list) else None)
def test_bad_arguments_give_one_line_and_status_2(tmp_path, capsys, argv, message):
    good = tmp_path / "good.txt"
    good.write_text(TUM_ROW + "2.0 0 0 0 0 0 0 1\n")
    out = tmp_path / "result"
    argv = [a.replace("FILE", str(good)).replace("OUT", str(out))
            .replace("NOFOLDER", str(tmp_path / "no_such_folder")) for a in argv]
    rc, stdout, err = run_cli(capsys, argv)
    assert_one_line_error(rc, stdout, err, message.replace("NOFOLDER",
                                                            str(tmp_path / "no_such_folder")))
    assert not any(tmp_path.glob("result*"))


def test_a_noise_floor_over_too_few_poses_keeps_the_configured_noise(tmp_path, capsys):
    """``--measurement-noise floor`` (documented as safe for a source of unknown noise) failed
    on a file too short to estimate from; it now keeps the configured noise and says so
    (``auto``, which has nothing else to use, still fails: BAD_ARGUMENTS)."""
    good = tmp_path / "good.txt"
    good.write_text(TUM_ROW + "2.0 0 0 0 0 0 0 1\n")
    rc, out, err = run_cli(capsys, ["smooth", str(good), "-o", str(tmp_path / "out.txt"),
                                 "--measurement-noise", "floor"])
    assert rc == 0, err
    assert "measurement noise: the configured (" in out + err
    assert (tmp_path / "out.txt").exists()


def test_a_long_gap_is_named(tmp_path, capsys):
    """A recording paused for a minute: smooth writes the held pose through the gap (at
    --rate), now with one warning line naming the gap."""
    f = tmp_path / "paused.txt"
    t = np.r_[np.arange(35) / 30, 61 + np.arange(35) / 30]
    f.write_text("".join(f"{x:.6f} {0.01 * k} 0 0 0 0 0 1\n" for k, x in enumerate(t)))
    # 70 poses and 500 rows: the size classes (one compiled program) of the one-part tests
    rc, out, err = run_cli(capsys, ["smooth", str(f), "-o", str(tmp_path / "out.txt"),
                                 "--rate", "8"])
    assert rc == 0, err
    lines = [ln for ln in err.splitlines() if ln.startswith("phjax: warning:")]
    assert lines == [f"phjax: warning: {f}: no pose for 59.87 s after t = 1.133333 s (median "
                     "interval 33.3 ms): the stream comes to rest and holds the last pose "
                     "through the gap, about 479 rows"], err


def test_an_output_naming_the_input_leaves_it_unchanged(tmp_path, capsys):
    good = tmp_path / "good.txt"
    good.write_text(TUM_ROW + "2.0 0 0 0 0 0 0 1\n")
    before = good.read_bytes()
    for argv in (["smooth", str(good), "-o", str(good)],
                 ["smooth", f"{good}", "-o", str(tmp_path / "." / "good.txt")]):
        rc, stdout, err = run_cli(capsys, argv)
        assert_one_line_error(rc, stdout, err, "is the input")
    assert good.read_bytes() == before


def _one_part_rows(n=120, leading=None):
    """A 30 Hz TUM recording whose rows alternate a position only and an orientation only (a
    log merged from two sensors), or, with ``leading``, whose first ``leading`` rows hold only a
    position and the rest whole poses."""
    t = 1.0 + np.arange(n) / 30
    rows = []
    for i, ti in enumerate(t):
        p, q = f"{0.01 * np.sin(ti):.6f} 0 0", f"0 0 {0.1 * np.sin(ti):.6f} 1"
        if leading is None:
            part = (p, "nan nan nan nan") if i % 2 == 0 else ("nan nan nan", q)
        else:
            part = (p, "nan nan nan nan") if i < leading else (p, q)
        rows.append(f"{ti:.6f} {part[0]} {part[1]}\n")
    return "".join(rows)


def test_measurements_never_holding_a_whole_pose_are_refused(tmp_path, capsys):
    """The filters start from a whole pose: a file whose rows each hold one part would give an
    empty output (it wrote a header and exit 0); as measurements it is one line, exit 2. The
    same file as ground truth (sampled by the simulated sensor) is not refused."""
    f = tmp_path / "merged.txt"
    f.write_text(_one_part_rows())
    out = tmp_path / "out.txt"
    for argv in (["smooth", str(f), "-o", str(out)],
                 ["tune", str(f), "--measured", str(f), "--lambda", "1",
                  "-o", str(tmp_path / "c.json")]):
        rc, stdout, err = run_cli(capsys, argv)
        assert_one_line_error(rc, stdout, err, str(f), "no row holds both a position and an "
                               "orientation (60 position-only, 60 orientation-only rows)")
    assert not out.exists()


def test_one_part_rows_before_the_first_whole_pose_are_named(tmp_path, capsys):
    f = tmp_path / "late.txt"
    f.write_text(_one_part_rows(leading=45))
    rc, stdout, err = run_cli(capsys, ["smooth", str(f), "-o", str(tmp_path / "out.txt")])
    assert rc == 0, err
    assert "45 one-part measurement(s) before the first whole pose" in err
    assert "1.5 s after the first measurement" in err


@pytest.mark.parametrize("missing", ["position", "orientation"])
def test_a_file_with_one_part_alone_is_read_with_one_warning(tmp_path, capsys, missing):
    """An orientation-only recording (a VR head trace) or a position-only one is valid input,
    but the missing part came out as NaN rows / '-' cells without a word (exit 0); now one
    warning line names it. The written file keeps the measured part finite."""
    t = np.arange(40) / 30
    p, q = np.c_[0.01 * np.sin(t), 0 * t, 0 * t], np.c_[0 * t, 0 * t, 0.1 * np.sin(t), 1 + 0 * t]
    (p if missing == "position" else q)[:] = np.nan
    f, out = tmp_path / "part.txt", tmp_path / "out.txt"
    np.savetxt(f, np.c_[t, p, q])
    rc, stdout, err = run_cli(capsys, ["smooth", str(f), "-o", str(out)])
    assert rc == 0, err
    other = "orientation" if missing == "position" else "position"
    assert err.count("phjax: warning:") == 1, err
    assert (f"phjax: warning: {f}: no row holds a valid {missing} ({other} only); the results "
            f"have no {missing} (NaN in written files, '-' in tables)") in err
    rows = np.loadtxt(out)
    kept, lost = (rows[:, 4:], rows[:, 1:4]) if missing == "position" else (rows[:, 1:4], rows[:, 4:])
    assert len(rows) > 100 and np.isfinite(kept).all() and np.isnan(lost).all()


def test_demo_curve_reads_the_named_file_without_synthetic_fallback(tmp_path, capsys):
    rc, out, err = run_cli(capsys, ["demo-curve", str(tmp_path / "nope.txt")])
    assert_one_line_error(rc, out, err, "nope.txt: No such file or directory")
    assert "synthetic" not in out


@pytest.mark.parametrize("command, outputs", [
    ("demo", ["phjax_evaluation.png", "phjax_evaluation.tum", "replaced"]),
    ("evaluate", ["phjax_evaluation.png", "replaced"]),
    ("smooth", ["--output", "replaced", "lost frame"]),
    ("tune", ["JSON", "replaced"]),
    ("track-rgbd", ["--output", "--raw", "replaced"]),
    ("demo-curve", ["Writes no file"]),
])
def test_help_names_every_output_file(capsys, command, outputs):
    assert main([command, "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for part in outputs:
        assert part in text, (command, part)


def test_top_level_help_documents_the_error_path(capsys):
    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "exit status 2" in text and "error" in text


@pytest.mark.parametrize("argv, names", [
    (["smooth", "FILE", "-o", "OUT.txt", "--rate", "1e9"], "--rate 1e+09 Hz"),
    (["evaluate", "FILE", "--plot", "", "--no-progress", "--rate", "1e9"], "--rate 1e+09 Hz"),
    (["demo", "--plot", "", "--no-progress", "--camera-rate", "1e9"], "--camera-rate 1e+09 Hz"),
    (["demo", "FILE", "--plot", "", "--no-progress", "--rate", "2e8"], "--rate 2e+08 Hz"),
    (["track-rgbd", "synthetic:10", "-o", "OUT.txt", "--rate", "1e9"], "--rate 1e+09 Hz"),
])
def test_work_that_cannot_fit_in_memory_says_so_before_it_starts(tmp_path, capsys, monkeypatch,
                                                                   argv, names):
    """Rates whose arrays would need more than half the machine's memory end in one line and
    status 2 before any array is made (they ended in NumPy's out-of-memory traceback, 74-447
    GiB); the memory is pinned to 24 GiB so that the bound is the same on every machine."""
    import phjax.cli._common as common

    monkeypatch.setattr(common, "_memory_bytes", lambda: 24 * 2**30)
    src = tmp_path / "walk.txt"
    src.write_text("".join(f"{0.1 * k} {0.01 * k} 0 0 0 0 0 1\n" for k in range(300)))  # 29.9 s
    argv = [str(src) if a == "FILE" else str(tmp_path / a) if a.startswith("OUT") else a
            for a in argv]
    rc, out, err = run_cli(capsys, argv)
    assert_one_line_error(rc, out, err, names, "GiB of memory", "24 GiB")
    assert not (tmp_path / "OUT.txt").exists()


def test_work_that_fits_is_not_refused(monkeypatch):
    """The bound sits at half the memory: 120 Hz over an hour passes on 1 GiB."""
    import phjax.cli._common as common

    monkeypatch.setattr(common, "_memory_bytes", lambda: 2**30)
    common.check_fits({"--rate 120 Hz over 3600 s": (120 * 3600, 512)})
    with pytest.raises(ValueError, match="more than half of this machine's 1 GiB"):
        common.check_fits({"--rate 1e5 Hz over 3600 s": (1e5 * 3600, 512)})


def test_several_trajectory_files_are_named_file_hash_name(tmp_path, capsys):
    """A CWI / AVTrack360 file holds several trajectories: ``FILE#NAME`` picks one (the same
    trajectory as ``phjax.io.read_trajectory(name=...)``); ``FILE`` alone, an unknown name, or
    ``#NAME`` on a one-trajectory file is one line naming ``FILE#NAME`` and the choices."""
    from conftest import shared_path

    cwi = shared_path("vr_cwi_6dof_navigation", "H1_longdress_nav.csv")
    out = tmp_path / "out.txt"
    rc, stdout, err = run_cli(capsys, ["smooth", f"{cwi}#P03_V1", "-o", str(out), "--offline"])
    assert rc == 0 and out.exists(), err
    for spec, part in ((str(cwi), "holding 27 trajectories; name one as FILE#NAME, NAME one of: "
                        "P01_V1"), (f"{cwi}#P99", "no trajectory named 'P99'"),
                       (f"{shared_path('tum_rgbd_groundtruth', 'fr1_xyz-groundtruth.txt')}#a",
                        "FILE#NAME selects one of several trajectories")):
        rc, stdout, err = run_cli(capsys, ["smooth", spec, "-o", str(tmp_path / "x.txt")])
        assert_one_line_error(rc, stdout, err, part, "phjax smooth: error:")


@pytest.mark.parametrize("command", ["evaluate", "demo"])
def test_a_recording_too_short_to_score_is_one_line(tmp_path, capsys, command):
    """Two poses 10 ms apart (under one camera period): no render time is scored; this ended
    in an IndexError traceback, and 40 ms in a NaN-to-int error after a plot was written."""
    src = tmp_path / "short.txt"
    src.write_text("".join(f"{0.01 * k:.2f} {0.001 * k} 0 0 0 0 0 1\n" for k in range(5)))
    rc, out, err = run_cli(capsys, [command, str(src), "--plot", str(tmp_path / "p.png"),
                                 "--no-progress"])
    assert_one_line_error(rc, out, err, f"{src}: the recording is too short to evaluate",
                           "jerk and lag need 8")
    assert not (tmp_path / "p.png").exists()


def test_a_still_noise_free_head_evaluates_and_a_plot_name_gets_png(tmp_path, capsys):
    """Every method exact, every jerk 0: the verdict's ratios and the frontier plot's log
    scale divided by zero (ZeroDivisionError); now the run completes. And a plot name without
    extension: matplotlib appends .png to it, and the messages (and the "replaced" note) named
    the file without it. (One run for both: 5 s at 100 Hz, the size classes of the other
    evaluate tests, whose compiled programs it shares.)"""
    src = tmp_path / "still.txt"
    src.write_text("".join(f"{0.01 * k:.2f} 1 2 3 0 0 0 1\n" for k in range(500)))
    rc, out, err = run_cli(capsys, ["evaluate", str(src), "--sigma-p", "0", "--sigma-r", "0",
                                 "--dropout", "0", "--plot", str(tmp_path / "fig"),
                                 "--no-progress"])
    assert rc == 0, err
    assert "Traceback" not in err
    assert f"frontier plot written to {tmp_path / 'fig.png'}" in out
    assert (tmp_path / "fig.png").is_file() and (tmp_path / "fig_methods.png").is_file()
