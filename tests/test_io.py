"""Trajectory I/O: round trips, every reader on the real shared files (checked against the SOURCE.md
tables and independent NumPy/scipy parses), VR frame conventions, and malformed input."""

from __future__ import annotations

import csv
import json
import warnings

import jax
import numpy as np
import pytest
from conftest import shared_path
from hypothesis import given, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

import phjax as pj
from phjax import io
from phjax.io import Trajectory, TrajectoryFormatError, TrajectoryWarning

S = np.diag([1.0, 1.0, -1.0])  # Unity -> right-handed (flip z)
GAZE = np.array([0.0, 0.0, -1.0])  # head-frame gaze direction in phjax's VR convention


# ------------------------------------------------------------------------------------------------
# helpers (independent of phjax.io)
# ------------------------------------------------------------------------------------------------


def continuous_reference(q):
    """Normalise and flip signs with a plain loop (reference for the vectorised reader code);
    rows with a NaN are lost frames: all NaN, skipped by the continuity."""
    q = np.array(q, dtype=np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    prev = None
    for k in range(len(q)):
        if np.isnan(q[k]).any():
            q[k] = np.nan
            continue
        if prev is not None and np.dot(q[k], q[prev]) < 0:
            q[k] = -q[k]
        prev = k
    return q


def assert_canonical(traj: Trajectory):
    t, p, q = traj
    assert t.dtype == p.dtype == q.dtype == np.float64
    assert t.shape == (len(t),) and p.shape == (len(t), 3) and q.shape == (len(t), 4)
    assert np.all(np.diff(t) > 0), "times must be strictly increasing"
    lost = np.isnan(q).any(axis=1)  # lost frames: whole rows NaN
    assert np.all(np.isnan(q[lost])) and np.all(np.isfinite(q[~lost]))
    assert np.all(np.isnan(p).any(axis=1) == np.isnan(p).all(axis=1))
    qv = q[~lost]
    np.testing.assert_allclose(np.linalg.norm(qv, axis=1), 1.0, atol=1e-12)
    assert np.all(np.sum(qv[1:] * qv[:-1], axis=1) >= 0), "hemisphere continuity violated"
    assert np.all(np.isfinite(t)) and not np.any(np.isinf(p))


def same_rotation_rows(a, b, atol):
    """Row-wise equality up to the q / -q sign (NaN rows must match)."""
    lost = np.isnan(a).any(axis=1)
    if not np.array_equal(lost, np.isnan(b).any(axis=1)):
        return False
    a = a[~lost] / np.linalg.norm(a[~lost], axis=1, keepdims=True)
    b = b[~lost] / np.linalg.norm(b[~lost], axis=1, keepdims=True)
    return np.all(np.abs(np.abs(np.sum(a * b, axis=1)) - 1) < atol)


def q_to_matrix(q):
    """Rotation matrix of wxyz quaternions via scipy (xyzw), an independent reference."""
    q = np.asarray(q, dtype=np.float64)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]]).as_matrix()


def no_warnings(fn, *args, **kw):
    """``fn(*args, **kw)`` with every warning an error, except the unit check's (the drawn
    trajectories have arbitrary times and positions; it has its own tests below)."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.simplefilter("ignore", io.TrajectoryUnitWarning)
        return fn(*args, **kw)


# ------------------------------------------------------------------------------------------------
# hypothesis strategies
# ------------------------------------------------------------------------------------------------

unit_box = st.floats(-1.0, 1.0, allow_nan=False, width=64)


@st.composite
def trajectories(draw, times="any"):
    if times == "any":  # arbitrary distinct finite floats (exact-repr formats)
        raw = draw(
            st.lists(
                st.floats(-1e15, 1e15, allow_nan=False, allow_infinity=False), min_size=1,
                max_size=25,
            )
        )
        t = np.unique(np.asarray(raw, dtype=np.float64))
    else:  # distinct by > 1 ns, |t| < 9.2e9 (EuRoC integer nanoseconds)
        n = draw(st.integers(1, 25))
        t0 = draw(st.floats(-1e9, 2e9, allow_nan=False))
        gaps = draw(arrays(np.float64, (n,), elements=st.floats(1e-6, 100.0)))
        t = t0 + np.cumsum(gaps)
    n = len(t)
    q = draw(arrays(np.float64, (n, 4), elements=unit_box))
    q[np.linalg.norm(q, axis=1) < 1e-3] = [1.0, 0.0, 0.0, 0.0]
    kind = draw(st.sampled_from(["full", "none", "some"]))
    p = draw(arrays(np.float64, (n, 3), elements=st.floats(-1e4, 1e4, allow_nan=False)))
    if kind == "none":
        p[:] = np.nan
    elif kind == "some":
        p[draw(arrays(np.bool_, (n,)))] = np.nan
    if draw(st.booleans()):  # lost frames: NaN quaternion rows (with or without a position)
        q[draw(arrays(np.bool_, (n,)))] = np.nan
    return Trajectory(t, p, q)


def check_roundtrip(src: Trajectory, back: Trajectory, time_atol: float):
    assert_canonical(back)
    assert back.num_samples == src.num_samples
    assert np.all(np.abs(back.times - src.times) <= time_atol + np.spacing(np.abs(src.times)))
    np.testing.assert_array_equal(back.positions, src.positions)  # exact, NaN == NaN
    # same rotations, continuous signs (checked above), first sign kept; the loop reference fixes
    # every sign except after an exactly orthogonal pair (dot == 0), where both choices are valid
    ref = continuous_reference(src.quaternions)
    assert same_rotation_rows(back.quaternions, ref, 1e-12)
    np.testing.assert_allclose(back.quaternions[0], ref[0], atol=1e-15)  # NaN == NaN here
    valid = ref[~np.isnan(ref).any(axis=1)]
    dots = np.sum(valid[1:] * valid[:-1], axis=1)
    if np.all(dots != 0):
        np.testing.assert_allclose(back.quaternions, ref, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# round trips
# ------------------------------------------------------------------------------------------------


@given(trajectories())
def test_roundtrip_tum(tmp_path_factory, traj):
    path = tmp_path_factory.mktemp("rt") / "traj.txt"
    io.write_tum(path, traj)
    assert io.detect_format(path) == "tum"
    check_roundtrip(traj, no_warnings(io.read_tum, path), time_atol=0.0)


@given(trajectories())
def test_roundtrip_csv(tmp_path_factory, traj):
    path = tmp_path_factory.mktemp("rt") / "traj.csv"
    io.write_csv(path, traj)
    assert io.detect_format(path) == "csv"
    check_roundtrip(traj, no_warnings(io.read_csv, path), time_atol=0.0)


@given(trajectories(times="ns"))
def test_roundtrip_euroc(tmp_path_factory, traj):
    path = tmp_path_factory.mktemp("rt") / "traj.csv"
    io.write_euroc(path, traj)
    assert io.detect_format(path) == "euroc"
    check_roundtrip(traj, no_warnings(io.read_euroc, path), time_atol=1e-9)


@pytest.mark.filterwarnings("ignore::phjax.io.TrajectoryUnitWarning")  # drawn times
@given(trajectories(times="ns"), st.sampled_from(["tum", "csv", "euroc"]))
def test_a_read_trajectory_written_and_read_again_is_bit_identical(tmp_path_factory, traj, fmt):
    """What phjax read (canonical: unit quaternions) survives a write and read exactly, as the
    module docs promise: quaternions were renormalised on every read and moved by up to 2e-16
    (found by probing)."""
    d = tmp_path_factory.mktemp("rt")
    suffix = ".txt" if fmt == "tum" else ".csv"
    io.write_trajectory(d / f"a{suffix}", traj, format=fmt)
    first = io.read_trajectory(d / f"a{suffix}", format=fmt)
    io.write_trajectory(d / f"b{suffix}", first, format=fmt)
    again = io.read_trajectory(d / f"b{suffix}", format=fmt)
    np.testing.assert_array_equal(again.times, first.times)
    np.testing.assert_array_equal(again.positions, first.positions)
    np.testing.assert_array_equal(again.quaternions, first.quaternions)


@pytest.mark.filterwarnings("ignore::phjax.io.TrajectoryUnitWarning")  # drawn times
@given(trajectories(times="ns"), st.sampled_from([".txt", ".tum", ".csv", "euroc"]))
def test_write_trajectory_dispatch_roundtrip(tmp_path_factory, traj, kind):
    d = tmp_path_factory.mktemp("rt")
    if kind == "euroc":
        path, expected = d / "x.csv", "euroc"
        io.write_trajectory(path, traj, format="euroc")
    else:
        path, expected = d / f"x{kind}", {".csv": "csv"}.get(kind, "tum")
        io.write_trajectory(path, traj)
    assert io.detect_format(path) == expected
    check_roundtrip(traj, io.read_trajectory(path), time_atol=1e-9)


def test_write_trajectory_rejects_bad_input(tmp_path):
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(ValueError, match="extension"):
        io.write_trajectory(tmp_path / "x.dat", traj)
    with pytest.raises(ValueError, match="unknown format"):
        io.write_trajectory(tmp_path / "x.csv", traj, format="kitti")
    with pytest.raises(ValueError, match="shape"):
        io.write_tum(tmp_path / "x.txt", traj._replace(quaternions=np.ones((3, 4))))
    with pytest.raises(ValueError, match="infinite"):
        io.write_csv(tmp_path / "x.csv", traj._replace(positions=np.full((2, 3), np.inf)))
    with pytest.raises(ValueError, match="9.2e9"):
        io.write_euroc(tmp_path / "x.csv", traj._replace(times=np.array([0.0, 1e10])))


# ------------------------------------------------------------------------------------------------
# Trajectory container
# ------------------------------------------------------------------------------------------------


def test_trajectory_is_pytree_and_helpers():
    q = np.array([[1.0, 0, 0, 0], [-2.0, 0, 0, 0.1], [0.0, 0, 3, 0]])
    with pytest.warns(TrajectoryWarning, match="1 timestamp"):
        tr = Trajectory.from_arrays([0.2, 0.1, 0.3], q)
    np.testing.assert_array_equal(tr.times, [0.1, 0.2, 0.3])
    assert_canonical(tr)
    assert not tr.has_positions() and tr.num_samples == 3 and len(tr) == 3
    tr2 = tr._replace(positions=np.where(np.arange(3)[:, None] == 1, 1.0, np.nan) * np.ones((3, 3)))
    assert tr2.has_positions()
    leaves = jax.tree_util.tree_leaves(tr2)
    assert len(leaves) == 3
    out = jax.jit(lambda t: t._replace(times=t.times * 2))(tr2)
    assert isinstance(out, Trajectory)
    np.testing.assert_allclose(out.times, 2 * tr2.times)
    with pytest.raises(ValueError, match="non-zero"):
        Trajectory.from_arrays([0.0], [[0.0, 0, 0, 0]])


# ------------------------------------------------------------------------------------------------
# real data: TUM RGB-D
# ------------------------------------------------------------------------------------------------

TUM_TABLE = {  # file: (poses, duration s, median step ms) from SOURCE.md
    "fr1_xyz-groundtruth.txt": (3000, 30.09, 10.0),
    "fr1_desk-groundtruth.txt": (2335, 23.40, 10.0),
    "fr1_room-groundtruth.txt": (4887, 48.90, 10.0),
    "fr2_pioneer_360-groundtruth.txt": (21823, 72.75, 3.3),
    "fr3_long_office_household-groundtruth.txt": (8710, 87.09, 10.0),
    "fr3_structure_texture_far-groundtruth.txt": (3156, 31.55, 10.0),
    "fr3_nostructure_notexture_far-groundtruth.txt": (1580, 15.79, 10.0),
    "estimates/fr1_xyz-rgbdslam_estimate.txt": (788, None, 32.6),
}


@pytest.mark.parametrize("name", sorted(TUM_TABLE))
def test_read_tum_real(name):
    path = shared_path("tum_rgbd_groundtruth", name)
    raw = np.loadtxt(path)  # independent parse
    _, first = np.unique(raw[:, 0], return_index=True)  # first occurrence of each time
    n_dup = len(raw) - len(first)
    if n_dup:
        with pytest.warns(TrajectoryWarning, match=f"dropped {n_dup} sample"):
            tr = io.read_tum(path)
    else:
        tr = no_warnings(io.read_tum, path)
    poses, duration, step_ms = TUM_TABLE[name]
    assert len(raw) == poses
    assert tr.num_samples == poses - n_dup
    assert_canonical(tr)
    if duration is not None:
        assert abs(tr.times[-1] - tr.times[0] - duration) < 0.01
    assert abs(np.median(np.diff(tr.times)) * 1e3 - step_ms) < 0.1
    ref = raw[np.sort(first)]
    np.testing.assert_array_equal(tr.times, ref[:, 0])
    np.testing.assert_array_equal(tr.positions, ref[:, 1:4])
    assert same_rotation_rows(tr.quaternions, ref[:, [7, 4, 5, 6]], 1e-12)  # xyzw -> wxyz
    assert tr.has_positions() and np.all(np.linalg.norm(tr.positions, axis=1) < 5.0)
    assert 1.3e9 < tr.times[0] < 1.4e9  # Unix seconds (2011)


def test_read_tum_pioneer_duplicates_keep_first():
    path = shared_path("tum_rgbd_groundtruth", "fr2_pioneer_360-groundtruth.txt")
    with pytest.warns(TrajectoryWarning, match="dropped 3 sample"):
        tr = io.read_tum(path)
    # file line 4308 (pose 4305) repeats the time of line 4307: the earlier pose must be kept
    raw = np.loadtxt(path)
    k = int(np.flatnonzero(np.diff(raw[:, 0]) == 0)[0])
    i = int(np.searchsorted(tr.times, raw[k, 0]))
    np.testing.assert_array_equal(tr.positions[i], raw[k, 1:4])


# ------------------------------------------------------------------------------------------------
# real data: TUM VI (EuRoC CSV) and the TUM <-> EuRoC cross-check
# ------------------------------------------------------------------------------------------------

TUMVI_TABLE = {"room1": (16541, 141.0), "room2": (15477, 144.1), "room3": (15200, 141.0)}


@pytest.mark.parametrize("room", sorted(TUMVI_TABLE))
def test_read_euroc_real(room):
    path = shared_path("tum_vi_room_groundtruth", f"{room}_mocap_groundtruth.csv")
    tr = no_warnings(io.read_euroc, path)
    n, duration = TUMVI_TABLE[room]
    assert tr.num_samples == n
    assert_canonical(tr)
    assert abs(tr.times[-1] - tr.times[0] - duration) < 0.1
    assert abs(np.median(np.diff(tr.times)) - 1 / 120) < 1e-4
    ns = np.loadtxt(path, delimiter=",", usecols=0, dtype=np.int64)
    vals = np.loadtxt(path, delimiter=",", usecols=range(1, 8))
    # integer-exact differences vs float seconds (float64 resolution at 1.5e9 s is 2.4e-7 s)
    np.testing.assert_allclose(tr.times - tr.times[0], (ns - ns[0]) * 1e-9, rtol=0, atol=5e-7)
    assert abs(tr.times[0] - 1.52e9) < 1e7
    np.testing.assert_array_equal(tr.positions, vals[:, :3])
    assert same_rotation_rows(tr.quaternions, vals[:, 3:7], 1e-9)  # already wxyz in the file
    assert np.all(np.linalg.norm(tr.positions, axis=1) < 5.0)


def test_tum_and_euroc_agree_on_the_same_trajectory(tmp_path):
    src = io.read_euroc(shared_path("tum_vi_room_groundtruth", "room1_mocap_groundtruth.csv"))
    io.write_tum(tmp_path / "r.txt", src)
    io.write_euroc(tmp_path / "r.csv", src)
    a = no_warnings(io.read_tum, tmp_path / "r.txt")
    b = no_warnings(io.read_euroc, tmp_path / "r.csv")
    np.testing.assert_array_equal(a.times, src.times)
    assert np.all(np.abs(a.times - b.times) <= np.spacing(a.times))
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_allclose(a.quaternions, b.quaternions, atol=1e-15)
    # and the other way round, starting from a TUM file (4-decimal times survive ns exactly)
    src = io.read_tum(shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"))
    io.write_euroc(tmp_path / "x.csv", src)
    back = io.read_euroc(tmp_path / "x.csv")
    np.testing.assert_array_equal(back.times, src.times)
    np.testing.assert_allclose(back.quaternions, src.quaternions, atol=1e-15)


def test_euroc_state_estimate_with_17_columns(tmp_path):
    """EuRoC's state_groundtruth_estimate0/data.csv has velocity and IMU biases after the pose
    (17 columns): it was 'cannot detect', and 'expected 8 columns' with format='euroc'."""
    src = io.read_euroc(shared_path("tum_vi_room_groundtruth", "room1_mocap_groundtruth.csv"))
    io.write_euroc(tmp_path / "pose.csv", src)
    lines = (tmp_path / "pose.csv").read_text().splitlines()
    extra = ",0.1,0.2,0.3,-0.003,0.02,0.07,-0.02,0.13,0.07"
    state = [lines[0] + ", v_x, v_y, v_z, bw_x, bw_y, bw_z, ba_x, ba_y, ba_z"]
    state += [ln + extra for ln in lines[1:] if not ln.startswith("#")]
    (tmp_path / "data.csv").write_text("\n".join(state) + "\n")
    for fmt in ("auto", "euroc"):
        got = io.read_trajectory(tmp_path / "data.csv", format=fmt)
        want = io.read_euroc(tmp_path / "pose.csv")
        np.testing.assert_array_equal(got.times, want.times)
        np.testing.assert_array_equal(got.positions, want.positions)
        np.testing.assert_array_equal(got.quaternions, want.quaternions)
    # other widths are still refused with the line
    bad = state[:3] + [state[3] + ",1.0"]
    (tmp_path / "bad.csv").write_text("\n".join(bad) + "\n")
    with pytest.raises(io.TrajectoryFormatError, match="line 4"):
        io.read_euroc(tmp_path / "bad.csv")


# ------------------------------------------------------------------------------------------------
# real data: Corbillon, Hachaj
# ------------------------------------------------------------------------------------------------

CORBILLON_TABLE = {"user1": (16053, 272.1, 248), "user2": (17379, 296.9, 336)}


@pytest.mark.parametrize("user", sorted(CORBILLON_TABLE))
def test_read_corbillon_real_removes_flips(user):
    path = shared_path("vr_corbillon_multiviewpoint360", f"{user}_quaternion.txt")
    tr = no_warnings(io.read_corbillon, path)
    n, duration, flips = CORBILLON_TABLE[user]
    raw = np.loadtxt(path, skiprows=1)
    assert np.count_nonzero(np.sum(raw[1:, 2:] * raw[:-1, 2:], axis=1) < 0) == flips  # raw file
    assert tr.num_samples == n
    assert_canonical(tr)  # includes: no flips left
    assert abs(tr.times[-1] - tr.times[0] - duration) < 0.1
    assert same_rotation_rows(tr.quaternions, raw[:, 2:6], 1e-12)
    np.testing.assert_array_equal(tr.times, raw[:, 0])
    assert not tr.has_positions() and np.all(np.isnan(tr.positions))


HACHAJ_FILES = [
    "right/1-01.log",
    "clockwise/1-04.log",
    "left/2-05.log",
    "omega_right/2-11.log",
    "node_head/2-01.log",
    "segment_continuous.log",
]


@pytest.mark.parametrize("name", HACHAJ_FILES)
def test_read_hachaj_real(name):
    path = shared_path("vr_hachaj_head_gestures", *name.split("/"))
    tr = no_warnings(io.read_hachaj, path)
    rows = [ln.strip().split(";") for ln in open(path) if ln.startswith("q;")]
    t_ms = np.array([int(r[1]) for r in rows])
    q_xyzw = np.array([[float(v) for v in r[2].split(",") if v] for r in rows])
    assert tr.num_samples == len(rows)
    assert_canonical(tr)
    np.testing.assert_allclose(tr.times, t_ms / 1e3, rtol=0, atol=1e-6)
    assert same_rotation_rows(tr.quaternions, q_xyzw[:, [3, 0, 1, 2]], 1e-9)
    assert 0.01 < np.median(np.diff(tr.times)) < 0.05  # ~40 Hz, seconds
    assert not tr.has_positions()
    assert io.detect_format(path) == "hachaj"


# ------------------------------------------------------------------------------------------------
# real data: CWI (Unity) and the Unity convention
# ------------------------------------------------------------------------------------------------

CWI_TABLE = {"H1_longdress_nav.csv": (9516, 132, 885), "H2_loot_nav.csv": (10458, 160, 1459)}


def unity_reference_matrix(rx, ry, rz):
    """Unity's R = Ry Rx Rz (z applied first, fixed axes) == scipy intrinsic 'YXZ'."""
    return Rotation.from_euler("YXZ", np.stack([ry, rx, rz], -1), degrees=True).as_matrix()


@given(arrays(np.float64, (3,), elements=st.floats(-720.0, 720.0, allow_nan=False)))
def test_unity_conversion_against_scipy(angles):
    rx, ry, rz = angles
    q = io.unity_euler_to_quaternion(rx, ry, rz)
    r = q_to_matrix(q)
    np.testing.assert_allclose(r, S @ unity_reference_matrix(rx, ry, rz) @ S, atol=1e-12)
    assert abs(np.linalg.det(r) - 1) < 1e-12
    # gaze: Unity's forward +z rotated by R_u, mapped to the right-handed frame
    np.testing.assert_allclose(
        r @ GAZE, S @ unity_reference_matrix(rx, ry, rz) @ [0, 0, 1.0], atol=1e-12
    )


def test_unity_convention_semantics():
    gaze = lambda *a: q_to_matrix(io.unity_euler_to_quaternion(*a)) @ GAZE  # noqa: E731
    up = lambda *a: q_to_matrix(io.unity_euler_to_quaternion(*a)) @ [0, 1.0, 0]  # noqa: E731
    np.testing.assert_allclose(gaze(0, 0, 0), [0, 0, -1], atol=1e-15)  # Unity +z -> -z
    np.testing.assert_allclose(gaze(0, 90, 0), [1, 0, 0], atol=1e-15)  # yaw +90: turn right
    np.testing.assert_allclose(gaze(30, 0, 0), [0, -0.5, -np.sqrt(0.75)], atol=1e-15)  # look down
    np.testing.assert_allclose(gaze(0, 0, 40), [0, 0, -1], atol=1e-15)  # roll keeps the gaze
    np.testing.assert_allclose(up(0, 0, 90), [-1, 0, 0], atol=1e-15)  # +z roll: up towards left
    # z first, then x, then y: pitch down then yaw right gives a right-and-down gaze
    np.testing.assert_allclose(
        gaze(30, 90, 0), [np.sqrt(0.75), -0.5, 0], atol=1e-15
    )


@pytest.mark.parametrize("name", sorted(CWI_TABLE))
def test_read_cwi_real(name):
    path = shared_path("vr_cwi_6dof_navigation", name)
    trajs = no_warnings(io.read_cwi, path)
    rows, lo, hi = CWI_TABLE[name]
    counts = [t.num_samples for t in trajs.values()]
    assert len(trajs) == 27 and sum(counts) == rows and min(counts) == lo and max(counts) == hi
    assert list(trajs)[0] == "P01_V1"
    for tr in trajs.values():
        assert_canonical(tr)
        assert np.all((tr.positions[:, 1] > 1.3) & (tr.positions[:, 1] < 2.1))  # head height
        np.testing.assert_allclose(np.diff(tr.times), 1 / 30, atol=1e-12)  # ViewFrame / 30
    # independent parse of the raw rows: positions flipped in z, rotations S R_u S
    with open(path) as f:
        raw = [r for r in csv.DictReader(f) if r["Participant"] == "P05_V1"]
    num = lambda k: np.array([float(r[k]) for r in raw])  # noqa: E731
    tr = trajs["P05_V1"]
    np.testing.assert_array_equal(tr.times, num("ViewFrame") / 30.0)
    p_rh = np.stack([num("HMDPX"), num("HMDPY"), -num("HMDPZ")], axis=1)
    np.testing.assert_array_equal(tr.positions, p_rh)
    ref = S @ unity_reference_matrix(num("HMDRX"), num("HMDRY"), num("HMDRZ")) @ S
    np.testing.assert_allclose(q_to_matrix(tr.quaternions), ref, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(q_to_matrix(tr.quaternions)), 1.0, atol=1e-12)


@pytest.mark.parametrize("name", sorted(CWI_TABLE))
def test_read_cwi_gaze_points_at_the_content(name):
    """Viewers walk around a point-cloud human standing at the origin: the converted gaze must
    point (horizontally) at it and slightly downwards. A wrong handedness / sign convention gives
    a median azimuth error of ~25 deg instead of ~10 deg on these files."""
    trajs = io.read_cwi(shared_path("vr_cwi_6dof_navigation", name))
    errs, down = [], []
    for tr in trajs.values():
        g = q_to_matrix(tr.quaternions) @ GAZE
        to = -tr.positions  # from the head towards the vertical axis through the origin
        err = np.arctan2(to[:, 0], -to[:, 2]) - np.arctan2(g[:, 0], -g[:, 2])
        errs.append(np.abs(np.angle(np.exp(1j * err))))
        down.append(g[:, 1])
    assert np.degrees(np.median(np.concatenate(errs))) < 15.0
    assert np.median(np.concatenate(down)) < 0


def test_read_cwi_participant_and_rate():
    path = shared_path("vr_cwi_6dof_navigation", "H1_longdress_nav.csv")
    one = io.read_cwi(path, participant="P03_V1", rate=60.0)
    allp = io.read_cwi(path)
    np.testing.assert_allclose(one.times * 2, allp["P03_V1"].times)
    np.testing.assert_array_equal(one.quaternions, allp["P03_V1"].quaternions)
    with pytest.raises(ValueError, match="P99"):
        io.read_cwi(path, participant="P99_V1")
    with pytest.raises(ValueError, match="rate"):
        io.read_cwi(path, rate=0.0)
    assert io.detect_format(path) == "cwi"


def test_read_trajectory_names_one_of_several():
    """``read_trajectory(name=...)`` reads one trajectory of a CWI / AVTrack360 file (equal to
    the multi-trajectory readers' entry), lists the names when none or an unknown one is given,
    refuses a name for a one-trajectory file, and shows only the selected trajectory's warnings
    (subject 10's ``4.mp4`` has a duplicate timestamp, ``6.mp4`` none)."""
    import warnings

    cwi = shared_path("vr_cwi_6dof_navigation", "H1_longdress_nav.csv")
    one = io.read_trajectory(cwi, name="P03_V1")
    np.testing.assert_array_equal(one.positions, io.read_cwi(cwi)["P03_V1"].positions)
    with pytest.raises(io.TrajectoryFormatError,
                       match=r"holding 27 trajectories; pass name= one of: P01_V1, P02_V1"):
        io.read_trajectory(cwi)
    with pytest.raises(io.TrajectoryFormatError, match="no trajectory named 'P99'"):
        io.read_trajectory(cwi, name="P99")
    tum = shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt")
    with pytest.raises(io.TrajectoryFormatError, match="this is a tum file holding one"):
        io.read_trajectory(tum, name="x")
    avt = shared_path("vr_avtrack360", "subject10_head_rotation.json")
    with warnings.catch_warnings():
        warnings.simplefilter("error", TrajectoryWarning)
        six = io.read_trajectory(avt, name="6.mp4")
    with pytest.warns(TrajectoryWarning, match=r"4\.mp4.*dropped 1 sample"):
        four = io.read_trajectory(avt, name="4.mp4")
    with pytest.warns(TrajectoryWarning):
        every = io.read_avtrack360(avt)
    np.testing.assert_array_equal(six.quaternions, every["6.mp4"].quaternions)
    np.testing.assert_array_equal(four.times, every["4.mp4"].times)
    assert io.split_trajectory_name(f"{cwi}#P03_V1") == (str(cwi), "P03_V1")
    np.testing.assert_array_equal(io.read_trajectory_spec(f"{cwi}#P03_V1").positions,
                                  one.positions)
    with pytest.raises(io.TrajectoryFormatError, match="name one as FILE#NAME, NAME one of: P01"):
        io.read_trajectory_spec(cwi)
    assert io.split_trajectory_name(tum) == (str(tum), None)


# ------------------------------------------------------------------------------------------------
# real data: AVTrack360 and its convention
# ------------------------------------------------------------------------------------------------


def test_avtrack360_convention_semantics():
    def frame(pitch, yaw, roll):
        return q_to_matrix(io.avtrack360_euler_to_quaternion(pitch, yaw, roll))

    np.testing.assert_allclose(frame(0, 90, 0) @ GAZE, [1, 0, 0], atol=1e-15)  # right = +yaw
    np.testing.assert_allclose(frame(0, -90, 0) @ GAZE, [-1, 0, 0], atol=1e-15)  # left = -yaw
    np.testing.assert_allclose(frame(-30, 0, 0) @ GAZE, [0, 0.5, -np.sqrt(0.75)], atol=1e-15)
    up = frame(0, 0, -20) @ [0, 1.0, 0]  # tilt left = negative roll
    assert up[0] < 0 and abs(up[2]) < 1e-15
    rng = np.random.default_rng(0)
    ang = rng.uniform(-180, 180, size=(50, 3))
    ref = Rotation.from_euler("YXZ", -ang[:, [1, 0, 2]], degrees=True).as_matrix()
    np.testing.assert_allclose(frame(ang[:, 0], ang[:, 1], ang[:, 2]), ref, atol=1e-12)


def test_read_avtrack360_real():
    path = shared_path("vr_avtrack360", "subject10_head_rotation.json")
    with pytest.warns(TrajectoryWarning, match=r"4\.mp4.*dropped 1 sample"):
        trajs = io.read_avtrack360(path)
    doc = json.loads(path.read_text())["data"]
    assert len(trajs) == 20 and set(trajs) == {v["filename"] for v in doc}
    assert sum(t.num_samples for t in trajs.values()) == 5926 - 1
    for video in doc:
        tr = trajs[video["filename"]]
        assert_canonical(tr)
        assert not tr.has_positions()
        assert 25.0 < tr.times[-1] - tr.times[0] < 31.0
        assert 0.09 < np.median(np.diff(tr.times)) < 0.11
        # invert the convention on the real samples: gaze azimuth == yaw, elevation == -pitch
        s = {}
        for e in video["pitch_yaw_roll_data_hmd"]:
            s.setdefault(e["sec"], e)  # first occurrence of each time
        pyr = np.array([[s[t]["pitch"], s[t]["yaw"], s[t]["roll"]] for t in tr.times], float)
        g = q_to_matrix(tr.quaternions) @ GAZE
        az = np.degrees(np.arctan2(g[:, 0], -g[:, 2]))
        np.testing.assert_allclose(np.angle(np.exp(1j * np.radians(az - pyr[:, 1]))), 0, atol=1e-9)
        np.testing.assert_allclose(np.degrees(np.arcsin(g[:, 1])), -pyr[:, 0], atol=1e-7)
    assert io.detect_format(path) == "avtrack360"


# ------------------------------------------------------------------------------------------------
# real data: Biwi poses
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("frame", ["00054", "00427", "unknown"])
def test_read_biwi_pose_real(frame):
    path = shared_path("biwi_kinect_head_pose_samples", f"frame_{frame}_pose.txt")
    r, t = io.read_biwi_pose(path)
    assert r.shape == (3, 3) and t.shape == (3,)
    assert 0.85 < np.linalg.norm(t) < 0.95 and t[2] > 0.85  # metres, in front of the sensor
    assert abs(np.linalg.det(r) - 1) < 1e-3
    q = io.biwi_pose_to_quaternion(r)
    assert q[0] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-15
    np.testing.assert_allclose(q_to_matrix(q), r, atol=1e-5)
    ref = Rotation.from_matrix(r).as_quat()  # xyzw
    assert same_rotation_rows(q[None], ref[None, [3, 0, 1, 2]], 1e-10)
    np.testing.assert_allclose(np.asarray(pj.quat_from_matrix(r)), q, atol=1e-12)


@given(arrays(np.float64, (4,), elements=unit_box).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_biwi_pose_to_quaternion_inverts_matrix(q):
    q = q / np.linalg.norm(q)
    back = io.biwi_pose_to_quaternion(q_to_matrix(q))
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-12


def test_biwi_pose_to_quaternion_half_turns_batched():
    axes = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0]])
    rots = Rotation.from_rotvec(np.pi * axes / np.linalg.norm(axes, axis=1, keepdims=True))
    q = io.biwi_pose_to_quaternion(rots.as_matrix())
    assert q.shape == (4, 4)
    np.testing.assert_allclose(q_to_matrix(q), rots.as_matrix(), atol=1e-12)


# ------------------------------------------------------------------------------------------------
# read_trajectory dispatch on real files
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "parts, fmt, reader",
    [
        (("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"), "tum", io.read_tum),
        (("tum_vi_room_groundtruth", "room2_mocap_groundtruth.csv"), "euroc", io.read_euroc),
        (("vr_corbillon_multiviewpoint360", "user2_quaternion.txt"), "corbillon",
         io.read_corbillon),
        (("vr_hachaj_head_gestures", "segment_continuous.log"), "hachaj", io.read_hachaj),
    ],
)
def test_read_trajectory_auto(parts, fmt, reader):
    path = shared_path(*parts)
    assert io.detect_format(path) == fmt
    a, b = io.read_trajectory(path), reader(path)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    with pytest.raises(ValueError, match="unknown format"):
        io.read_trajectory(path, format="kitti")


# ------------------------------------------------------------------------------------------------
# malformed input
# ------------------------------------------------------------------------------------------------

TUM_OK = "1.0 0 0 0 0 0 0 1"
EUROC = "#h\n1000000000,0,0,0,1,0,0,0\n"
CSV = "t,x,y,z,qw,qx,qy,qz\n1,0,0,0,1,0,0,0\n"
CORB = "timestamp viewpoint w x y z\n0.0 0 1 0 0 0\n"
HACH = "q;1000;0,0,0,1,\n"
EYE = "1 0 0\n0 1 0\n"

MALFORMED = [
    # (reader, file name, content, line, message regex)
    (io.read_tum, "a.txt", f"# c\n{TUM_OK}\n2.0 0 0 0 0 0 1\n", 3, "expected 8 columns.*found 7"),
    (io.read_tum, "a.txt", f"{TUM_OK}\n\n2 0 abc 0 0 0 0 1\n", 3, "value 'abc' in column 3"),
    (io.read_tum, "a.txt", f"{TUM_OK}\n2.0 0 0 0 0 0 0 0\n", 2, "zero-norm quaternion"),
    (io.read_tum, "a.txt", f"{TUM_OK}\nnan 0 0 0 0 0 0 1\n", 2, "non-finite timestamp"),
    (io.read_tum, "a.txt", f"{TUM_OK}\n2.0 0 inf 0 0 0 0 1\n", 2, "infinite position"),
    (io.read_tum, "a.txt", f"{TUM_OK}\n2.0 0 0 0 0 -inf 0 1\n", 2, "infinite quaternion"),
    (io.read_tum, "a.txt", "\n", None, "no data"),
    (io.read_tum, "a.txt", "# only comments\n", None, "no data"),
    (io.read_euroc, "a.csv", f"{EUROC}2000000000,0,0,0,1,0,0\n", 3, "expected 8 columns"),
    (io.read_euroc, "a.csv", f"{EUROC}2000000000,0,0,x,1,0,0,0\n", 3, "non-numeric value 'x'"),
    (io.read_euroc, "a.csv", f"{EUROC}2000000000,0,0,0,0,0,0,0\n", 3, "zero-norm"),
    (io.read_csv, "a.csv", "t,x,y,z,qw,qx,qy\n1,0,0,0,1,0,0\n", 1, r"lacks column\(s\) \['qz'\]"),
    (io.read_csv, "a.csv", "t,x,y,qw,qx,qy,qz\n1,0,0,1,0,0,0\n", 1, "all of x,y,z or none"),
    (io.read_csv, "a.csv", "t,Time,qw,qx,qy,qz\n1,1,1,0,0,0\n", 1,
     "columns 't' and 'Time' both name 't'"),
    (io.read_csv, "a.csv", "time_ms,qw,qx,qy,qz\n1,1,0,0,0\n", 1, r"lacks column\(s\) \['t'\]"),
    (io.read_csv, "a.csv", f"{CSV}2,0,0,0,1,0,0\n", 3, "expected 8 columns"),
    (io.read_csv, "a.csv", f"{CSV}2,0,0,0,1,0,0,?\n", 3, r"non-numeric value '\?' in column 8"),
    (io.read_csv, "a.csv", f"{CSV}2,0,0,0,0,0,0,0\n", 3, "zero-norm"),
    (io.read_corbillon, "u.txt", "0.0 0 1 0 0 0\n", 1, "expected the header"),
    (io.read_corbillon, "u.txt", f"{CORB}0.1 0 0 0 0 0\n", 3, "zero-norm"),
    (io.read_corbillon, "u.txt", f"{CORB}0.1 0 1 0 0\n", 3, "expected 6 columns"),
    (io.read_hachaj, "h.log", f"{HACH}v;1000;0,0,0\nq;1010;0,0,1,\n", 3, "4 quaternion components"),
    (io.read_hachaj, "h.log", f"{HACH}x;1010;0,0,0,1\n", 2, "unknown record type 'x'"),
    (io.read_hachaj, "h.log", f"{HACH}q;10a0;0,0,0,1,\n", 2, "non-numeric value '10a0'"),
    (io.read_hachaj, "h.log", f"{HACH}q;1010;0,0,0,0,\n", 2, "zero-norm"),
    (io.read_biwi_pose, "p.txt", f"{EYE}0 0 1\n\n1 2\n", 5, "expected 3 columns"),
    (io.read_biwi_pose, "p.txt", f"{EYE}\n1 2 3\n", None, "expected 4 non-blank lines"),
    (io.read_biwi_pose, "p.txt", f"{EYE}0 0 -1\n\n1 2 3\n", 1, "not a rotation matrix"),
    (io.read_biwi_pose, "p.txt", f"{EYE}0 0 1.1\n\n1 2 3\n", 1, "not a rotation matrix"),
]


@pytest.mark.parametrize("reader, fname, content, line, match", MALFORMED)
def test_malformed_files_raise_with_location(tmp_path, reader, fname, content, line, match):
    path = tmp_path / fname
    path.write_text(content)
    with pytest.raises(TrajectoryFormatError, match=match) as info:
        reader(path)
    msg = str(info.value)
    assert fname in msg and str(path) in msg
    assert info.value.line == line
    if line is not None:
        assert f"line {line}:" in msg
    assert isinstance(info.value, ValueError)


def test_malformed_cwi_and_avtrack(tmp_path):
    head = "FrameNumber,HMDPX,HMDPY,HMDPZ,HMDRX,HMDRY,HMDRZ,Participant,Dataset,ViewFrame\n"
    p = tmp_path / "c.csv"
    p.write_text(head + "1,0,1.7,0,0,0,0,P01_V1,H1,1\n1,0,1.7,0,0,0,P01_V1,H1,2\n")
    with pytest.raises(TrajectoryFormatError, match="c.csv, line 3: expected 10 columns"):
        io.read_cwi(p)
    p.write_text(head.replace("HMDRZ,", "") + "1,0,1.7,0,0,0,P01_V1,H1,1\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 1: header lacks.*HMDRZ"):
        io.read_cwi(p)
    p.write_text(head + "1,0,1.7,0,0,0,inf,P01_V1,H1,1\n")
    with pytest.raises(TrajectoryFormatError, match="line 2: non-finite ViewFrame or infinite"):
        io.read_cwi(p)
    p.write_text(head + "1,0,1.7,0,0,0,0,P01_V1,H1,nan\n")
    with pytest.raises(TrajectoryFormatError, match="line 2: non-finite ViewFrame"):
        io.read_cwi(p)
    p.write_text(head + "1,0,1.7,0,0,0,0,P01_V1,H1,1\n")  # zero angles are fine (identity)
    tr = io.read_cwi(p, participant="P01_V1")
    np.testing.assert_allclose(tr.quaternions, [[1.0, 0, 0, 0]])

    j = tmp_path / "a.json"
    j.write_text('{"data": [\n  {"filename": "1.mp4",\n  }\n]}')
    with pytest.raises(TrajectoryFormatError, match="line 3: invalid JSON"):
        io.read_avtrack360(j)
    sample = {"pitch": 1, "yaw": 2, "roll": 3, "sec": 0.1}
    bad = dict(sample)
    del bad["yaw"]
    video = {"filename": "1.mp4", "pitch_yaw_roll_data_hmd": [sample, bad]}
    j.write_text(json.dumps({"data": [video]}))
    where = r"data\[0\]\.pitch_yaw_roll_data_hmd\[1\]: .*'yaw'"
    with pytest.raises(TrajectoryFormatError, match=where):
        io.read_avtrack360(j)
    video = {"filename": "1.mp4", "pitch_yaw_roll_data_hmd": [sample]}
    j.write_text(json.dumps({"data": [video, video]}))
    with pytest.raises(TrajectoryFormatError, match="duplicate filename"):
        io.read_avtrack360(j)


UNSORTED = [  # times 3, 1, 2, 1 (second t=1 sample has x=9 and must be dropped)
    (io.read_tum, "u.txt", "3 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n2 2 0 0 0 0 0 1\n1 9 0 0 0 0 0 1\n"),
    (io.read_euroc, "u.csv", "#\n3,0,0,0,1,0,0,0\n1,1,0,0,1,0,0,0\n"
                             "2,2,0,0,1,0,0,0\n1,9,0,0,1,0,0,0\n"),
    (io.read_csv, "u.csv", "qw,qx,qy,qz,x,y,z,t\n1,0,0,0,0,0,0,3\n1,0,0,0,1,0,0,1\n"
                           "1,0,0,0,2,0,0,2\n1,0,0,0,9,0,0,1\n"),
    (io.read_hachaj, "u.log", "q;3;0,0,0,1,\nq;1;0,0,0,1,\nq;2;0,0,0,1,\nq;1;0,0,0,1,\n"),
    (io.read_corbillon, "u.txt", "timestamp viewpoint w x y z\n3 0 1 0 0 0\n1 0 1 0 0 0\n"
                                 "2 0 1 0 0 0\n1 0 -1 0 0 0\n"),
]


@pytest.mark.parametrize("reader, fname, content", UNSORTED)
def test_unsorted_and_duplicate_times_are_fixed_with_warnings(tmp_path, reader, fname, content):
    path = tmp_path / fname
    path.write_text(content)
    with pytest.warns(TrajectoryWarning) as rec:
        tr = reader(path)
    msgs = " | ".join(str(w.message) for w in rec)
    assert "2 timestamp(s) out of order" in msgs and "dropped 1 sample(s)" in msgs
    assert str(path) in msgs
    assert_canonical(tr)
    scale = {io.read_euroc: 1e-9, io.read_hachaj: 1e-3}.get(reader, 1.0)
    np.testing.assert_allclose(tr.times, np.array([1.0, 2.0, 3.0]) * scale)
    if tr.has_positions():  # the first of the two t=1 samples (x=1, not x=9) is kept
        np.testing.assert_array_equal(tr.positions[:, 0], [1.0, 2.0, 0.0])


#: (what is rescaled, factor, expected words of the warning): fr1_xyz as a file of another unit
UNIT_MISTAKES = [
    ("times", 1e3, "median interval between poses is 10 s (0.1 Hz); times are read in seconds: "
                   "are they in milliseconds, microseconds or nanoseconds?"),
    ("times", 1e9, "1e+07 s"),
    ("times", 1e-3, "1e-05 s (1e+05 Hz); times are read in seconds: are they in another unit?"),
    ("positions", 1e3, "positions are read in metres: are they in millimetres or centimetres?"),
    ("positions", 1e2, "the median speed is 3"),
]


@pytest.mark.parametrize("what, factor, words", UNIT_MISTAKES,
                         ids=["ms", "ns", "10 us", "mm", "cm"])
def test_times_or_positions_in_another_unit_warn_once(tmp_path, what, factor, words):
    """fr1_xyz (100 Hz, median speed 0.33 m/s) written with its times in ms / ns / 10 us or
    its positions in mm / cm: one TrajectoryUnitWarning naming the file and the suspect unit,
    and the values are used as read."""
    src = io.read_tum(shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"))
    t, p = src.times - src.times[0], src.positions
    t, p = (t * factor, p) if what == "times" else (t, p * factor)
    path = tmp_path / "unit.txt"
    io.write_tum(path, Trajectory(t, p, src.quaternions))
    with pytest.warns(io.TrajectoryUnitWarning) as rec:
        tr = io.read_tum(path)
    assert len(rec) == 1, [str(w.message) for w in rec]
    assert str(rec[0].message).startswith(f"{path}: ") and words in str(rec[0].message)
    np.testing.assert_allclose(tr.times, t, rtol=1e-12, atol=1e-9 * abs(factor))
    np.testing.assert_allclose(tr.positions, p, rtol=1e-12)
    short = tmp_path / "short.txt"  # nine poses: not checked (frames picked from a sequence)
    io.write_tum(short, Trajectory(t[:9], p[:9], src.quaternions[:9]))
    with warnings.catch_warnings():
        warnings.simplefilter("error", io.TrajectoryUnitWarning)
        io.read_tum(short)


@pytest.mark.parametrize("folder, pattern", [
    ("tum_rgbd_groundtruth", "**/*.txt"), ("tum_vi_room_groundtruth", "*.csv"),
    ("vr_corbillon_multiviewpoint360", "*.txt"), ("vr_hachaj_head_gestures", "**/*.log"),
    ("vr_cwi_6dof_navigation", "*.csv"), ("vr_avtrack360", "*.json")])
def test_no_real_recording_is_taken_for_another_unit(folder, pattern):
    """Every recording of ../shared/data (median intervals 3.3-101 ms, median speeds
    0.03-1.2 m/s) reads without a unit warning."""
    read = {"vr_cwi_6dof_navigation": io.read_cwi,
            "vr_avtrack360": io.read_avtrack360}.get(folder, io.read_trajectory)
    files = sorted(shared_path(folder).glob(pattern))
    assert files
    for f in files:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TrajectoryWarning)  # duplicates in two of them
            warnings.simplefilter("error", io.TrajectoryUnitWarning)
            read(f)


@pytest.mark.parametrize("header, order, sep", [
    ("timestamp,tx,ty,tz,qx,qy,qz,qw", "tum", ","),  # TUM's columns, comma-separated
    ("Time, Pos_X, pos.y, POSITION Z, quat_w, quat_x, quat_y, quat_z", "wxyz", ","),
    ("# a comment\nstamp,qw,qx,qy,qz,px,py,pz,frame", "wxyz", ","),
    ("t;x;y;z;qw;qx;qy;qz", "wxyz", ";"),
    ("timestamp\ttx\tty\ttz\tqx\tqy\tqz\tqw", "tum", "\t"),
])
def test_csv_column_names_in_common_spellings(tmp_path, header, order, sep):
    """A CSV whose header spells the columns as other tools do (scalar-last quaternion, other
    names and order, an extra column, semicolons or tabs between them) is detected as CSV and
    reads exactly as the same poses from a TUM file."""
    ref = io.read_tum(shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"))
    t, p, q = ref.times[:50], ref.positions[:50], ref.quaternions[:50]
    names = header.splitlines()[-1].split(sep)
    cols = {"tum": [t[:, None], p, q[:, [1, 2, 3, 0]]], "wxyz": [t[:, None], p, q]}[order]
    table = np.concatenate(cols, axis=1)
    if names[0].strip() == "stamp":  # stamp,q,p,frame
        table = np.concatenate([t[:, None], q, p, np.arange(50)[:, None]], axis=1)
    path = tmp_path / "poses.csv"
    path.write_text(header + "\n" + "\n".join(sep.join(repr(float(v)) for v in row)
                                             for row in table) + "\n")
    assert io.detect_format(path) == "csv"
    got = no_warnings(io.read_trajectory, path)
    np.testing.assert_array_equal(got.times, t)
    np.testing.assert_array_equal(got.positions, p)
    np.testing.assert_allclose(got.quaternions, q, rtol=0, atol=1e-15)


def test_a_csv_of_numbers_without_a_header_says_what_to_add(tmp_path):
    path = tmp_path / "poses.csv"
    path.write_text("0.0,0,0,0,0,0,0,1\n0.033,0.001,0,0,0,0,0,1\n")
    with pytest.raises(TrajectoryFormatError, match=r"poses\.csv: comma-separated numbers "
                       r"without a header: name the columns in a first line"):
        io.read_trajectory(path)


def _fr1_xyz(n=50):
    ref = io.read_tum(shared_path("tum_rgbd_groundtruth", "fr1_xyz-groundtruth.txt"))
    return ref.times[:n], ref.positions[:n], ref.quaternions[:n]


def test_csv_units_in_brackets_are_converted(tmp_path):
    """``t [ms]``, ``x (mm)``, ``qw []``: real poses written in milliseconds and millimetres
    read back in seconds and metres (without a unit warning); a unit phjax does not convert is
    a one-line error naming the column."""
    t, p, q = _fr1_xyz()
    path = tmp_path / "units.csv"
    table = np.concatenate([1e3 * t[:, None], 1e3 * p, q], axis=1)
    path.write_text("t [ms],x (mm),y (mm),z (mm),qw [],qx [],qy [],qz []\n" + "\n".join(
        ",".join(repr(float(v)) for v in row) for row in table) + "\n")
    assert io.detect_format(path) == "csv"
    got = no_warnings(io.read_trajectory, path)
    np.testing.assert_allclose(got.times, t, rtol=1e-15)
    np.testing.assert_allclose(got.positions, p, rtol=1e-12)
    np.testing.assert_allclose(got.quaternions, q, atol=1e-15)
    path.write_text("t [s],x [ft],y [ft],z [ft],qw,qx,qy,qz\n0,0,0,0,1,0,0,0\n")
    with pytest.raises(TrajectoryFormatError, match=r"units\.csv, line 1: column 'x \[ft\]': "
                       r"unit 'ft' is not one of \['cm', 'm', 'mm'\]"):
        io.read_csv(path)


def test_csv_header_in_a_comment_is_read_by_name(tmp_path):
    """``#timestamp,tx,ty,tz,qx,qy,qz,qw`` (scalar-last, as a ``#`` comment like EuRoC's):
    read as CSV by its names, not as EuRoC's scalar-first columns; EuRoC's own header (names
    phjax does not know) still means EuRoC."""
    t, p, q = _fr1_xyz()
    path = tmp_path / "commented.csv"
    table = np.concatenate([t[:, None], p, q[:, [1, 2, 3, 0]]], axis=1)
    path.write_text("# exported by another tool\n#timestamp,tx,ty,tz,qx,qy,qz,qw\n" + "\n".join(
        ",".join(repr(float(v)) for v in row) for row in table) + "\n")
    assert io.detect_format(path) == "csv"
    got = no_warnings(io.read_trajectory, path)
    np.testing.assert_array_equal(got.times, t)
    np.testing.assert_allclose(got.quaternions, q, atol=1e-15)
    euroc = sorted(shared_path("tum_vi_room_groundtruth").glob("*.csv"))[0]
    assert io.detect_format(euroc) == "euroc"


def test_csv_missing_values_trailing_separators_and_second_pairs(tmp_path):
    """pandas' empty field, ``NA``, ``null``: a lost frame; trailing commas (unnamed empty
    columns) are ignored; a whole-seconds column beside a nanoseconds one is refused."""
    path = tmp_path / "p.csv"
    path.write_text("t,x,y,z,qw,qx,qy,qz,,\n0.0,,,,NA,null,None,,,\n"
                    "0.1,1,2,3,1,0,0,0,,\n")
    tr = io.read_csv(path)
    assert np.isnan(tr.positions[0]).all() and np.isnan(tr.quaternions[0]).all()
    np.testing.assert_array_equal(tr.positions[1], [1, 2, 3])
    path.write_text("seconds,nanoseconds,x,y,z,qw,qx,qy,qz\n1,5,0,0,0,1,0,0,0\n")
    with pytest.raises(TrajectoryFormatError, match=r"'seconds' beside 'nanoseconds' looks like "
                       r"whole seconds and nanoseconds: combine them"):
        io.read_trajectory(path)
    path.write_text("0.0,0,0,0,1,0,0,0\n0.1,0,0,0,1,0,0,0\n")
    with pytest.raises(TrajectoryFormatError, match=r"line 1: the first line is numbers, not a "
                       r"header"):
        io.read_csv(path)


def test_csv_header_any_order_and_orientation_only(tmp_path):
    p = tmp_path / "o.csv"
    p.write_text("# comment\nqz, QY ,qx,qw,t,label\n0,0,1,1,0.25,b\n0,0,0,2,0.5,a\n")
    tr = no_warnings(io.read_csv, p)
    np.testing.assert_array_equal(tr.times, [0.25, 0.5])
    expected = [[np.sqrt(0.5), np.sqrt(0.5), 0, 0], [1, 0, 0, 0]]
    np.testing.assert_allclose(tr.quaternions, expected, atol=1e-15)
    assert not tr.has_positions()
    assert io.detect_format(p) == "csv"


def test_detect_format_rejects_unknown(tmp_path):
    p = tmp_path / "x.txt"
    p.write_text("1 2 3\n")
    with pytest.raises(ValueError, match="cannot detect"):
        io.detect_format(p)
    p.write_text("")
    with pytest.raises(ValueError, match="empty"):
        io.read_trajectory(p)


def test_binary_file_is_a_format_error(tmp_path):
    path = tmp_path / "x.txt"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00\x00")
    for fn in (io.read_tum, io.detect_format, io.read_trajectory):
        with pytest.raises(TrajectoryFormatError, match=r"x\.txt: not a UTF-8 text file"):
            fn(path)


# ------------------------------------------------------------------------------------------------
# lost frames: NaN rows (position, quaternion or both) in every reader and writer
# ------------------------------------------------------------------------------------------------

# rows: (t, position or None for NaN, xyzw quaternion or None for NaN); row 4 has a partial NaN in
# both parts; the last quaternion is -(first), so continuity must look past the lost frames
_ROWS = [
    (1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
    (2.0, None, (0.0, 0.0, 0.0, 1.0)),
    (3.0, (1.0, 2.0, 3.0), None),
    (4.0, None, None),
    (5.0, (1.0, np.nan, 3.0), (0.0, 0.0, 0.5, np.nan)),
    (6.0, (0.5, 0.0, 0.0), (0.0, 0.0, 0.0, -1.0)),
]
_POS_LOST = [False, True, False, True, True, False]
_Q_LOST = [False, False, True, True, True, False]


def _fmt(x):
    return repr(float(x))


def _lost_frame_files():
    nan3, nan4 = (np.nan,) * 3, (np.nan,) * 4
    rows = [(t, nan3 if p is None else p, nan4 if q is None else q) for t, p, q in _ROWS]
    tum = "".join(" ".join(map(_fmt, (t, *p, *q))) + "\n" for t, p, q in rows)
    euroc = "#t,px,py,pz,qw,qx,qy,qz\n" + "".join(
        ",".join([str(int(t * 1e9))] + [_fmt(v) for v in (*p, q[3], *q[:3])]) + "\n"
        for t, p, q in rows)
    csv_ = "t,x,y,z,qw,qx,qy,qz\n" + "".join(
        ",".join(map(_fmt, (t, *p, q[3], *q[:3]))) + "\n" for t, p, q in rows)
    corb = "timestamp viewpoint w x y z\n" + "".join(
        " ".join(map(_fmt, (t, 0, q[3], *q[:3]))) + "\n" for t, p, q in rows)
    hach = "".join(f"q;{int(t * 1000)};" + ",".join(map(_fmt, q)) + ",\n" for t, p, q in rows)
    return [(io.read_tum, "l.txt", tum, True), (io.read_euroc, "l.csv", euroc, True),
            (io.read_csv, "l.csv", csv_, True), (io.read_corbillon, "l.txt", corb, False),
            (io.read_hachaj, "l.log", hach, False)]


@pytest.mark.parametrize("reader, fname, content, has_pos", _lost_frame_files(),
                         ids=["tum", "euroc", "csv", "corbillon", "hachaj"])
def test_nan_rows_are_lost_frames_in_every_reader(tmp_path, reader, fname, content, has_pos):
    path = tmp_path / fname
    path.write_text(content)
    tr = no_warnings(reader, path)
    assert_canonical(tr)
    np.testing.assert_allclose(tr.times, np.arange(1.0, 7.0))  # every row kept
    np.testing.assert_array_equal(np.isnan(tr.quaternions).all(axis=1), _Q_LOST)
    if has_pos:
        np.testing.assert_array_equal(np.isnan(tr.positions).all(axis=1), _POS_LOST)
        np.testing.assert_array_equal(tr.positions[2], [1.0, 2.0, 3.0])
    else:
        assert not tr.has_positions()
    # continuity across the lost frames: the last row is flipped to the first one's sign
    np.testing.assert_array_equal(tr.quaternions[[0, 1, 5]], np.tile([1.0, 0, 0, 0], (3, 1)))
    if reader in (io.read_tum, io.read_euroc, io.read_csv):  # auto-detected as well
        np.testing.assert_array_equal(io.read_trajectory(path).quaternions, tr.quaternions)


def test_nan_angles_are_lost_frames_in_vr_readers(tmp_path):
    head = "FrameNumber,HMDPX,HMDPY,HMDPZ,HMDRX,HMDRY,HMDRZ,Participant,Dataset,ViewFrame\n"
    p = tmp_path / "c.csv"
    p.write_text(head + "1,0,1.7,0,0,0,0,P,H1,1\n2,nan,nan,nan,0,0,0,P,H1,2\n"
                 "3,0,1.7,0,nan,0,0,P,H1,3\n4,0,1.7,0,0,10,0,P,H1,4\n")
    tr = io.read_cwi(p, participant="P")
    np.testing.assert_array_equal(np.isnan(tr.positions).all(axis=1), [0, 1, 0, 0])
    np.testing.assert_array_equal(np.isnan(tr.quaternions).all(axis=1), [0, 0, 1, 0])
    assert_canonical(tr)
    samples = [{"pitch": 0, "yaw": 0, "roll": 0, "sec": 0.0},
               {"pitch": float("nan"), "yaw": 3, "roll": 0, "sec": 0.1},
               {"pitch": 0, "yaw": 5, "roll": 0, "sec": 0.2}]
    j = tmp_path / "a.json"
    j.write_text(json.dumps({"data": [{"filename": "1.mp4", "pitch_yaw_roll_data_hmd": samples}]}))
    tr = io.read_avtrack360(j)["1.mp4"]
    np.testing.assert_array_equal(np.isnan(tr.quaternions).all(axis=1), [0, 1, 0])
    assert_canonical(tr)
    samples[1]["sec"] = float("nan")  # a time is never missing
    j.write_text(json.dumps({"data": [{"filename": "1.mp4", "pitch_yaw_roll_data_hmd": samples}]}))
    with pytest.raises(TrajectoryFormatError, match=r"\[1\]: missing or non-finite 'sec'"):
        io.read_avtrack360(j)


@pytest.mark.parametrize("writer, fname", [(io.write_tum, "w.txt"), (io.write_csv, "w.csv"),
                                           (io.write_euroc, "w.csv")])
def test_writers_keep_lost_frames(tmp_path, writer, fname):
    t = np.arange(1.0, 5.0)
    p = np.array([[0.0, 0, 0], [np.nan] * 3, [1.0, 2, 3], [np.nan] * 3])
    q = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, 0], [np.nan] * 4, [np.nan] * 4])
    tr = Trajectory.from_arrays(t, q, p)
    path = tmp_path / fname
    writer(path, tr)
    back = io.read_trajectory(path)
    np.testing.assert_allclose(back.times, t, atol=1e-9)
    np.testing.assert_array_equal(back.positions, p)
    np.testing.assert_array_equal(back.quaternions, q)
    with pytest.raises(ValueError, match="infinite"):
        writer(path, tr._replace(quaternions=np.where(np.isnan(q), np.inf, q)))


def test_huge_components_are_a_direction_and_huge_degrees_a_format_error(tmp_path):
    """A quaternion written with components like 1e200 is a valid direction (its norm
    overflowed to inf: read as the zero quaternion, with a NumPy overflow warning); an
    AVTrack360 angle too large for a float is a format error naming the sample (it was an
    OverflowError traceback)."""
    f = tmp_path / "big.txt"
    f.write_text("1 0 0 0 0 0 0 1\n2 0 0 0 1e200 0 0 1e200\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q = io.read_trajectory(f).quaternions
    np.testing.assert_allclose(q[1], [np.sqrt(0.5), np.sqrt(0.5), 0, 0], atol=1e-15)
    big = {"data": [{"filename": "a.mp4", "pitch_yaw_roll_data_hmd": [
        {"pitch": 0, "yaw": 0, "roll": 0, "sec": 0.0},
        {"pitch": 0, "yaw": 10 ** 400, "roll": 0, "sec": 0.1}]}]}
    j = tmp_path / "av.json"
    j.write_text(json.dumps(big))
    with pytest.raises(TrajectoryFormatError, match=r"\[1\]: missing or non-finite 'yaw'"):
        io.read_avtrack360(j)


def test_a_write_error_names_the_file(tmp_path):
    """A full disk ("No space left on device") said so without naming the file."""
    import os

    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full on this system")
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(OSError) as e:
        io.write_trajectory("/dev/full", traj, format="tum")
    assert e.value.filename == "/dev/full" and "No space left" in e.value.strerror


def test_warnings_point_at_the_callers_line(tmp_path):
    """A unit or duplicate-time warning names the line that called the reader (this file),
    whether through read_trajectory (format detection in between) or a reader directly."""
    ms = tmp_path / "ms.csv"
    ms.write_text("t,x,y,z,qw,qx,qy,qz\n" + "".join(f"{33.0 * i},0,0,0,1,0,0,0\n"
                                                    for i in range(30)))
    dup = tmp_path / "dup.txt"
    dup.write_text("".join(f"{t} 0 0 0 0 0 0 1\n" for t in (0.0, 0.1, 0.1, 0.2)))
    for call in (lambda: io.read_trajectory(ms), lambda: io.read_csv(ms),
                 lambda: io.read_trajectory(dup), lambda: io.read_tum(dup)):
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            call()
        assert len(seen) == 1 and seen[0].filename == __file__, [
            (w.filename, w.lineno) for w in seen]


def test_a_spreadsheet_export_with_sep_line_and_decimal_commas(tmp_path):
    """A European Excel export: ``sep=;`` first, semicolons between the columns, decimal
    commas in the numbers; read as the same poses as the TUM file."""
    t, p, q = _fr1_xyz(20)
    path = tmp_path / "excel.csv"
    table = np.concatenate([t[:, None], p, q], axis=1)
    path.write_text("sep=;\nTime;X;Y;Z;QW;QX;QY;QZ\n" + "".join(
        ";".join(repr(float(v)).replace(".", ",") for v in row) + "\n" for row in table))
    assert io.detect_format(path) == "csv"
    got = no_warnings(io.read_trajectory, path)
    np.testing.assert_array_equal(got.times, t)
    np.testing.assert_array_equal(got.positions, p)
    np.testing.assert_allclose(got.quaternions, q, atol=1e-15)
