"""Bad or unusual trajectory files that phjax.io (and the CLI's report of its errors) handled
wrongly (found in review): a long comment header that made a valid file undetectable, AVTrack360
JSONs that escaped as a raw decoding error, a RecursionError traceback or a message listing no
names, digit-group underscores read as numbers, and form feeds counted as line breaks. Small
files in ``tmp_path``; no JAX program is compiled."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

from phjax import io
from phjax.io import TrajectoryFormatError

TUM_ROWS = "1.0 0.1 0.2 0.3 0 0 0 1\n2.0 0.4 0.5 0.6 0 0 1 0\n"
EUROC_HEADER = ("#timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],"
                "q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []\n")


def _comments(n):
    return "".join(f"# recorded with tool X, note {i}\n" for i in range(n))


# ------------------------------------------------------------------ 1: a long comment header
@pytest.mark.parametrize("n_comments", [19, 20, 45])
def test_a_long_comment_header_does_not_hide_the_format(tmp_path, n_comments):
    """detect_format looked at the first 20 non-blank lines only: a TUM or EuRoC file whose
    comment header was 20 lines or longer was "cannot detect the trajectory format", though
    read_tum / read_euroc read it."""
    tum = tmp_path / "long.txt"
    tum.write_text(_comments(n_comments) + TUM_ROWS)
    assert io.detect_format(tum) == "tum"
    got = io.read_trajectory(tum)
    np.testing.assert_array_equal(got.times, [1.0, 2.0])
    np.testing.assert_array_equal(got.positions, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])
    np.testing.assert_array_equal(got.quaternions, [[1.0, 0, 0, 0], [0, 0, 0, 1.0]])
    euroc = tmp_path / "long.csv"
    euroc.write_text(_comments(n_comments) + EUROC_HEADER
                     + "1000000000,1,2,3,1,0,0,0\n2000000000,1,2,3,0,1,0,0\n")
    assert io.detect_format(euroc) == "euroc"
    np.testing.assert_array_equal(io.read_trajectory(euroc).quaternions,
                                  [[1.0, 0, 0, 0], [0, 1.0, 0, 0]])
    csv_ = tmp_path / "named.csv"  # the header in the last comment line, after a long preamble
    csv_.write_text(_comments(n_comments) + "#timestamp,tx,ty,tz,qx,qy,qz,qw\n"
                    + "1.0,0,0,0,0,0,0,1\n2.0,0,0,0,0,0,1,0\n")
    assert io.detect_format(csv_) == "csv"


# --------------------------------------------------------------------- 2: AVTrack360 JSON
def _av_json(n=30, note="x"):
    samples = [{"sec": i / 10, "pitch": 0, "yaw": i, "roll": 0} for i in range(n)]
    samples[-1]["note"] = note
    return json.dumps({"data": [{"filename": "6.mp4", "pitch_yaw_roll_data_hmd": samples}]},
                      indent=1, ensure_ascii=False)


def test_a_json_with_a_latin1_byte_late_in_the_file_names_the_file(tmp_path, capsys):
    """A Latin-1 byte past what detect_format reads (or with --format avtrack360): a raw
    UnicodeDecodeError, and on the command line "'utf-8' codec can't decode byte 0xe9 ...",
    naming no file."""
    path = tmp_path / "late.json"
    path.write_bytes(_av_json(note="caf\xe9").encode("latin-1"))
    with pytest.raises(TrajectoryFormatError, match=r"late\.json: not a UTF-8 text file"):
        io.read_avtrack360(path)
    rc, out, err = run_cli(capsys, ["smooth", f"{path}#6.mp4", "--format", "avtrack360",
                                    "-o", tmp_path / "o.tum"])
    assert_one_line_error(rc, out, err, f"phjax smooth: error: {path}: not a UTF-8 text file")
    good = tmp_path / "good.json"  # the same file in UTF-8 reads
    good.write_text(_av_json(note="caf\xe9"), encoding="utf-8")
    assert io.read_avtrack360(good)["6.mp4"].num_samples == 30


def test_a_deeply_nested_json_is_a_format_error(tmp_path, capsys):
    """``[[[[...`` nested 100000 deep: json's RecursionError (a RuntimeError, which the CLI
    re-raises) ended the command with a traceback."""
    path = tmp_path / "deep.json"
    path.write_text("[" * 100_000)
    with pytest.raises(TrajectoryFormatError, match=r"deep\.json: invalid JSON: nested too "
                                                    r"deeply"):
        io.read_avtrack360(path)
    rc, out, err = run_cli(capsys, ["smooth", path, "-o", tmp_path / "o.tum"])
    assert_one_line_error(rc, out, err, f"{path}: invalid JSON")


def test_a_json_without_videos_is_a_format_error(tmp_path):
    """``{"data": []}``: read_avtrack360 returned ``{}`` (no error) and read_trajectory said
    "a avtrack360 file holding 0 trajectories; pass name= one of: " (and no name)."""
    path = tmp_path / "none.json"
    path.write_text('{"data": []}')
    for read in (io.read_avtrack360, io.read_trajectory):
        with pytest.raises(TrajectoryFormatError, match=r"none\.json: no videos in 'data'"):
            read(path)


def test_a_json_of_several_videos_names_them_with_an_article_that_fits(tmp_path):
    path = tmp_path / "two.json"
    doc = json.loads(_av_json(3))
    doc["data"].append(dict(doc["data"][0], filename="7.mp4"))
    path.write_text(json.dumps(doc))
    with pytest.raises(TrajectoryFormatError, match=r"an avtrack360 file holding 2 "
                                                    r"trajectories; pass name= one of: 6.mp4, "
                                                    r"7.mp4$"):
        io.read_trajectory(path)


# ------------------------------------------------------------- 3: digit-group underscores
@pytest.mark.parametrize("reader, fname, content, line, token", [
    (io.read_tum, "u.txt", "1.0 0 0 0 0 0 0 1\n2.0 1_5 0 0 0 0 0 1\n", 2, "1_5"),
    (io.read_tum, "u.txt", "1_0 0 0 0 0 0 0 1\n", 1, "1_0"),
    (io.read_euroc, "u.csv", "#h\n1_000_000_000,0,0,0,1,0,0,0\n", 2, "1_000_000_000"),
    (io.read_csv, "u.csv", "t,qw,qx,qy,qz\n0.1_0,1,0,0,0\n", 2, "0.1_0"),
    (io.read_hachaj, "u.log", "q;1000;0,0,0,1,\nq;10_10;0,0,0,1,\n", 2, "10_10"),
])
def test_digit_group_underscores_are_not_numbers(tmp_path, reader, fname, content, line, token):
    """Python's float() reads '1_5' as 15 and '1_000_000_000' as 1e9: such a token (a typo or
    a field joined by '_') was silently read as another number; no trajectory format writes
    numbers so."""
    path = tmp_path / fname
    path.write_text(content)
    with pytest.raises(TrajectoryFormatError, match=f"line {line}: non-numeric value "
                                                    f"'{token}'"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reader(path)


# ----------------------------------------------------------- 4: line numbers with form feeds
def test_a_form_feed_is_not_a_line_break(tmp_path):
    """str.splitlines() also breaks at form feeds (and \\x1c-\\x1e, \\x85, \\u2028): a page
    break shifted every later line number in the messages, and a form feed between two
    numbers split one row into two."""
    path = tmp_path / "ff.txt"
    path.write_text("1 0 0 0 0 0 0 1\n\x0c\n2 0 0 0 0 0 0 1\n3 0 0 x 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 4: non-numeric value 'x'"):
        io.read_tum(path)
    path.write_text("1 0 0 0\x0c0 0 0 1\r\n2 0 0 0 0 0 0 1\r\n")
    np.testing.assert_array_equal(io.read_tum(path).times, [1.0, 2.0])


def test_a_file_of_comments_only_says_it_has_no_data_lines(tmp_path):
    """It said "cannot detect the trajectory format ...; pass --format", and every --format
    then said "no data lines": the first message now says what is wrong."""
    path = tmp_path / "header_only.csv"
    path.write_text(EUROC_HEADER + "# recorded 2026-11-30\n")
    with pytest.raises(TrajectoryFormatError, match="header_only.csv: no data lines"):
        io.detect_format(path)
    with pytest.raises(TrajectoryFormatError, match="no data lines"):
        io.read_trajectory(path)
