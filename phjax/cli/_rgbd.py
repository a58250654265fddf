"""RGB-D commands of the ``phjax`` CLI: ``track-rgbd``."""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from ._common import (
    add_output_argument,
    BYTES_PER_CAMERA_FRAME,
    BYTES_PER_RENDER_SAMPLE,
    add_rate_argument,
    check_fits,
    check_trajectory_output,
    FPS_RANGE,
    float_between,
    model_not_found,
    positive_float,
    positive_int,
    replaced_note,
)
from ._tune import add_noise_argument, with_noise_from_args


def _relative_rotation_errors(est_q: np.ndarray, gt_q: np.ndarray) -> np.ndarray:
    """Angle (deg) between the estimated and true head rotations relative to the first frame
    (camera-frame motions ``q_i q_0^-1``), which does not depend on the head-frame convention."""
    from .._np_quat import np_qconj, np_qmul, np_rotvec

    rel_e = np_qmul(est_q, np_qconj(est_q[:1]))
    rel_g = np_qmul(gt_q, np_qconj(gt_q[:1]))
    return np.degrees(np.linalg.norm(np_rotvec(np_qmul(np_qconj(rel_g), rel_e)), axis=-1))


def _intrinsics(text: str) -> tuple[float, ...]:
    """argparse type: ``FX,FY,CX,CY`` in pixels: four finite numbers, focal lengths > 0, the
    principal point ``CX, CY >= 0`` (checked against the image's size by
    :func:`_check_principal_point` once the first frame is read)."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 4 or not all(np.isfinite(vals)):
        raise argparse.ArgumentTypeError(
            f"expected FX,FY,CX,CY (four finite numbers, pixels), got {text!r}")
    if min(vals[:2]) <= 0:
        raise argparse.ArgumentTypeError(
            f"focal lengths FX, FY must be > 0 pixels, got {text!r}")
    if min(vals[2:]) < 0:
        raise argparse.ArgumentTypeError(
            f"the principal point CX, CY must lie in the image (pixels >= 0), got {text!r}")
    return vals


def _check_principal_point(intrinsics, given, source) -> None:
    """``--intrinsics``' principal point against the size of the first image (the readers set
    ``intrinsics.width`` / ``height`` from it): a ``ValueError`` naming the option when it lies
    outside the image (pixel centres ``0 .. W-1``, ``0 .. H-1``), as a centre given for
    another resolution or the focal lengths and centre swapped."""
    w, h = intrinsics.width, intrinsics.height
    cx, cy = float(intrinsics.cx), float(intrinsics.cy)
    if not (0 <= cx <= w - 1 and 0 <= cy <= h - 1):
        text = ",".join(f"{v:g}" for v in given)
        raise ValueError(f"--intrinsics {text}: the principal point (CX {cx:g}, CY {cy:g}) lies "
                         f"outside the {w} x {h} images of {source} (CX 0-{w - 1}, CY "
                         f"0-{h - 1} pixels)")


def _reader_options(args) -> dict:
    """``--depth-scale`` / ``--intrinsics`` / ``--fps`` as reader keywords, for the layouts
    that take them."""
    from ..vision.rgbd_io import UNTIMED_LAYOUTS, rgbd_layout

    given = {k: v for k, v in (("depth_scale", args.depth_scale),
                               ("intrinsics", args.intrinsics)) if v is not None}
    if given:
        layout = rgbd_layout(args.source)
        if layout not in ("tum", "pairs"):
            names = " and ".join("--" + k.replace("_", "-") for k in given)
            raise ValueError(f"{names}: only for TUM RGB-D and color/ + depth/ folders; "
                             f"{args.source} is {LAYOUT_NAMES[layout]} with its own calibration")
    if args.fps is not None:
        layout = rgbd_layout(args.source)
        if layout not in UNTIMED_LAYOUTS:
            what = LAYOUT_NAMES.get(layout, "a TUM RGB-D folder")
            raise ValueError(f"--fps: only for folders whose frames carry no timestamps (Biwi, "
                             f"color/ + depth/); {args.source} is {what} with its own times")
        given["fps"] = args.fps
    return given


LAYOUT_NAMES = {"biwi": "a Biwi folder", "synthetic": "the synthetic head"}


#: the lists, poses and calibrations that the RGB-D readers read in a source folder (Biwi,
#: TUM RGB-D, color/ + depth/ with pose.txt), and its image subfolders
_RECORDING_NAMES = ("rgb.txt", "depth.txt", "groundtruth.txt", "accelerometer.txt",
                    "pose.txt", "rgb.cal", "depth.cal")
_RECORDING_FOLDERS = ("rgb", "depth", "color")


def _recording_files(source) -> set[Path]:
    """The files of an RGB-D source folder that an output must not replace (resolved paths;
    empty for a synthetic source). Other files in the folder, such as an earlier run's
    output, may be written again."""
    folder = Path(source)
    if not folder.is_dir():
        return set()
    files = {folder / name for name in _RECORDING_NAMES}
    files.update(folder.glob("frame_*_pose.txt"))
    for sub in _RECORDING_FOLDERS:
        files.update((folder / sub).rglob("*"))
    return {f.resolve() for f in files}


def cmd_track_rgbd(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from ..vision.head_pose import HeadPoseConfig, HeadPoseEstimator, HeadPoseStatus
    from ..io import Trajectory, write_trajectory
    from ..vision.rgbd_io import RGBDFormatError, open_rgbd
    from ..tracking.tracker import track

    check_trajectory_output(args.output)
    if args.raw:
        check_trajectory_output(args.raw)
        if Path(args.raw).resolve() == Path(args.output).resolve():
            raise ValueError(f"--raw {args.raw}: the same file as -o; name another file")
    for option, out in (("-o", args.output), ("--raw", args.raw)):
        if out and Path(out).resolve() in _recording_files(args.source):
            raise ValueError(f"{option} {out}: a file of the recording {args.source}; "
                             "writing it would destroy it: name another file")
    source = args.source
    if str(source) == "synthetic" or str(source).startswith("synthetic:"):
        from ..live._sources import synthetic_spec

        frames, seed = synthetic_spec(source)  # N >= 1, 0 <= SEED < 2**32: as phjax live's
        if args.max_frames is not None:  # only those are simulated
            frames = min(frames, args.max_frames)
            source = f"synthetic:{frames}:{seed}"
        check_fits({f"{source} ({frames} frames)": (frames, BYTES_PER_CAMERA_FRAME)},
                   "give fewer frames (N, or --max-frames)")
    seq = open_rgbd(source, **_reader_options(args))
    if args.intrinsics is not None:
        _check_principal_point(seq.intrinsics, args.intrinsics, args.source)
    n = len(seq) if args.max_frames is None else min(len(seq), args.max_frames)
    if n == 0:
        raise ValueError(f"{args.source}: no frames")
    span = float(np.ptp(seq.timestamps[:n])) if n > 1 else 0.0
    check_fits({f"--rate {args.rate:g} Hz over {span:.3g} s":
                (span * args.rate, BYTES_PER_RENDER_SAMPLE["smooth"])})
    cfg = HeadPoseConfig(backend=args.backend, detect_interval=args.detect_interval,
                         feature_method=args.features, icp=args.icp)
    reference = None
    if args.gt_reference:
        gt = seq.ground_truth
        if gt is None or seq.ground_truth_kind != "head":
            raise ValueError("--gt-reference needs a source with head-pose ground truth "
                             "(Biwi, synthetic)")
        if not (np.isfinite(gt.quaternions[0]).all() and np.isfinite(gt.positions[0]).all()):
            raise ValueError(f"--gt-reference: the first frame of {args.source} has no "
                             "ground-truth pose")
        reference = (gt.quaternions[0], gt.positions[0])
    from ..vision.face_detection import FaceDetector, ModelNotFoundError

    try:
        detector = FaceDetector(args.backend, model_dir=args.model_dir,
                                download=args.download_models, detect_width=cfg.detect_width,
                                score_threshold=cfg.min_face_score)
    except ModelNotFoundError as e:  # the command line's own ways first
        raise model_not_found(e, "../shared/data/yunet_face_detection") from None
    est = HeadPoseEstimator(seq.intrinsics, cfg, detector=detector, model_dir=args.model_dir,
                            reference_pose=reference)
    indices = range(n)
    if not args.no_progress:
        try:
            from tqdm.auto import tqdm

            indices = tqdm(indices, total=n, unit="frame", desc="head pose")
        except ImportError:
            pass
    times = np.asarray(seq.timestamps[:n], np.float64).copy()
    pos = np.full((n, 3), np.nan)
    quat = np.full((n, 4), np.nan)
    status = []
    detected = 0  # frames whose face the detector found (not the depth fallback or tracking)
    per_frame = np.full(n, np.nan)
    t_all = time.perf_counter()
    for i in indices:
        t0 = time.perf_counter()
        try:
            frame = seq[i]
        except (OSError, RGBDFormatError) as e:  # a missing or damaged file: that frame lost
            print(f"phjax: warning: frame {i}: {e}", file=sys.stderr)
            status.append(HeadPoseStatus.INVALID_INPUT.name)
            continue
        r = est.process_frame(frame)
        per_frame[i] = time.perf_counter() - t0
        times[i] = r.timestamp
        status.append(HeadPoseStatus(r.status).name)
        detected += r.face_source == "detector"
        if r.ok:
            pos[i], quat[i] = r.position, r.quaternion
    wall = time.perf_counter() - t_all
    ok = np.isfinite(quat).all(-1)
    counts = Counter(status)
    print(f"source: {seq.name}: {n} frames, backend {args.backend}")
    print("status: " + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    steady = per_frame[min(2, n - 1):]
    if np.isfinite(steady).any():
        print(f"front-end: median {1e3 * np.nanmedian(steady):.1f} ms/frame "
              f"({1 / np.nanmedian(steady):.1f} frames/s) after the first frames (those include "
              f"the compilation: {np.nansum(per_frame[:2]):.1f} s); {wall:.1f} s in all with "
              "frame loading")
    if not ok.any():
        hint = ""
        if counts.most_common(1)[0][0] == "NO_DEPTH":
            hint = (f" (most frames had too little depth within {cfg.min_depth:g}-"
                    f"{cfg.max_depth:g} m: check the depth's units; --depth-scale sets them "
                    "for TUM RGB-D and color/ + depth/ folders)")
        raise ValueError(f"no frame produced a head pose; nothing to track{hint}")
    if not detected:  # a reference the detector never confirmed: possibly furniture
        raise ValueError(f"the face detector found no face in any of the {n} frames; the poses "
                         "of the depth fallback alone are not trusted (is a face in the colour "
                         "images?)")
    if args.raw:
        note = replaced_note(args.raw)
        write_trajectory(args.raw, Trajectory(times[ok], pos[ok], quat[ok]))
        print(f"per-frame poses written to {args.raw}{note}")
    gt = seq.ground_truth
    if gt is not None and seq.ground_truth_kind == "head" and ok.sum() > 1:
        gq = np.asarray(gt.quaternions[:n])
        sel = ok & np.isfinite(gq).all(-1)
        if sel.sum() > 1:
            err = _relative_rotation_errors(quat[sel], gq[sel])
            print(f"rotation relative to the first good frame vs ground truth: median "
                  f"{np.median(err):.2f} deg, max {err.max():.2f} deg over {sel.sum()} frames")
    # render-rate stream from the measured poses
    render = np.arange(times[ok].min(), times.max() + 1e-9, 1.0 / args.rate)
    config, noise = with_noise_from_args(args, None, times, pos, quat)
    if noise:
        print(noise)
    p_r, q_r = track(times, pos, quat, render, config=config)
    p_r, q_r = np.asarray(p_r, np.float64), np.asarray(q_r, np.float64)
    good = np.isfinite(q_r).all(-1) & np.isfinite(p_r).all(-1)
    note = replaced_note(args.output)
    write_trajectory(args.output, Trajectory(render[good], p_r[good], q_r[good]))
    print(f"causal stream: {good.sum()} poses at {args.rate:g} Hz written to {args.output}{note}")
    return 0


def add_commands(sub) -> None:
    p = sub.add_parser(
        "track-rgbd", help="head pose from RGB-D frames, then the smooth render-rate stream",
        description="Run the RGB-D head-pose front-end (YuNet face detection, keypoints and "
        "landmarks lifted through depth, RANSAC alignment, point-to-plane ICP) on every frame "
        "of SOURCE and feed the poses to the causal tracker (phjax.track), written at --rate "
        "as a TUM trajectory (head pose in the colour camera frame). SOURCE: a Biwi Kinect "
        "folder, a TUM RGB-D folder, a color/ + depth/ folder, or 'synthetic[:N[:SEED]]' "
        "(N >= 1 frames, 0 <= SEED < 2**32).")
    p.add_argument("source", help="RGB-D source (folder or synthetic[:N[:SEED]], N >= 1, "
                   "0 <= SEED < 2**32)")
    add_output_argument(p, "output: the render-rate trajectory (.tum/.txt = TUM, .csv = CSV)")
    add_rate_argument(p)
    p.add_argument("--backend", choices=("opencv", "kornia"), default="opencv",
                   help="face detector backend (default opencv)")
    p.add_argument("--model-dir", default=None,
                   help="model cache folder (default $PHJAX_MODEL_DIR or ~/.cache/phjax/models)")
    p.add_argument("--download-models", action="store_true",
                   help="download a missing YuNet model file into the model folder (urllib; "
                   "checked against its sha256)")
    p.add_argument("--features", choices=("orb", "sift"), default="orb",
                   help="keypoint type (default orb)")
    p.add_argument("--icp", choices=("projective", "nearest", "none"), default="projective",
                   help="ICP refinement (default projective)")
    p.add_argument("--detect-interval", type=positive_int, default=1,
                   help="run the face detector every n-th frame (default 1)")
    p.add_argument("--max-frames", type=positive_int, default=None, help="process at most N frames")
    p.add_argument("--raw", default=None,
                   help="output: also write the per-frame poses to this file (TUM/CSV by "
                   "extension; replaced when it exists)")
    p.add_argument("--gt-reference", action="store_true",
                   help="use the ground-truth pose of the first frame as the reference")
    p.add_argument("--fps", type=float_between(*FPS_RANGE, "Hz"), default=None, metavar="FPS",
                   help="frame rate of a folder whose frames carry no timestamps (Biwi, color/ "
                   "+ depth/; default 30; slambook's keyframes: 1); TUM RGB-D folders have "
                   "their own timestamps")
    p.add_argument("--depth-scale", type=positive_float, default=None, metavar="UNITS",
                   help="depth image units per metre, for TUM RGB-D and color/ + depth/ folders "
                   "(default: the layout's own, TUM 5000, color/ + depth/ 1000; e.g. 1000 for "
                   "millimetre PNGs in a TUM-layout folder). Depth images must be 16-bit "
                   "(uint16) or float: an 8-bit one is an error naming the file")
    p.add_argument("--intrinsics", type=_intrinsics, default=None, metavar="FX,FY,CX,CY",
                   help="colour camera intrinsics in pixels, for TUM RGB-D and color/ + depth/ "
                   "folders: focal lengths > 0, the principal point within the images "
                   "(checked against the first one's size) (default: TUM Freiburg 1/2/3 from "
                   "the folder name, else the ROS defaults 525,525,319.5,239.5; color/ + "
                   "depth/: slambook's)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_noise_argument(p, has_config=False)
    p.set_defaults(func=cmd_track_rgbd)
