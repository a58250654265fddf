"""``phjax head-pose``: head pose from photos (colour only), one row per image."""

from __future__ import annotations

import contextlib
import csv
import sys
from pathlib import Path

import numpy as np

from .._face_sizes import HEAD_SIZE_RANGE, IPD_RANGE
from ._common import check_output, float_between, model_not_found, replaced_note
from ._live import FOV_RANGE

#: file name endings read as images when a folder is named
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp")
#: the columns of the table and of ``--output``
COLUMNS = ("image", "status", "pitch_deg", "yaw_deg", "roll_deg", "x_m", "y_m", "z_m",
           "confidence")


def _images(paths: list[str]) -> list[Path]:
    """The image files named, a folder's images (sorted by name) in its place; a path that does
    not exist or a folder without images is an error."""
    out: list[Path] = []
    for name in paths:
        p = Path(name)
        if p.is_dir():
            found = sorted(f for f in p.iterdir()
                           if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                sub = any(f.is_dir() for f in p.iterdir())
                raise ValueError(f"{name}: no images in this folder "
                                 f"({', '.join(IMAGE_SUFFIXES)})"
                                 + ("; its subfolders are not searched: name them" if sub
                                    else ""))
            out += found
        elif p.is_file():
            out.append(p)
        else:
            raise FileNotFoundError(2, "No such file or directory", name)
    return out


def _row(image: Path, result) -> dict:
    from ..vision.monocular import pitch_yaw_roll

    angles = pitch_yaw_roll(result.crop_quaternion) if result.ok else np.full(3, np.nan)
    pos = result.position if result.ok else np.full(3, np.nan)
    return dict(zip(COLUMNS, (str(image), result.status.name, *angles, *pos,
                              result.confidence)))


def cmd_head_pose(args) -> int:
    from ..vision.face_detection import (
        HEAD_POSE_ONNX,
        YUNET_ONNX,
        FaceDetector,
        ModelNotFoundError,
        model_path,
    )
    from ..vision.features import _require
    from ..vision.head_pose import HeadPoseStatus
    from ..vision.monocular import MonocularHeadPose, MonocularResult, intrinsics_from_fov
    from ..vision.rgbd_io import RGBDFormatError, read_image

    images = _images(args.images)
    if args.output:
        if Path(args.output).suffix.lower() in IMAGE_SUFFIXES:  # "-o photos/*.jpg": a photo
            raise ValueError(f"-o {args.output}: the output is a CSV table, not an image "
                             f"(did the shell expand a pattern after -o?)")
        check_output(args.output, inputs=images)
    _require("cv2")
    needed = [(YUNET_ONNX, "yunet_face_detection")]  # (model, its folder in ../shared/data)
    if args.method == "net":
        needed.append((HEAD_POSE_ONNX, "head_pose_models"))
    for model, shared in needed:
        try:  # every model before the first image (downloading the missing ones if asked)
            model_path(model, args.model_dir, download=args.download_models)
        except ModelNotFoundError as e:
            raise model_not_found(e, f"../shared/data/{shared}") from None
    detector = FaceDetector("opencv", model_dir=args.model_dir)
    estimators: dict[tuple[int, int], MonocularHeadPose] = {}  # one per image size
    width = max(len(str(image)) for image in images)
    print(f"{'image':<{width}}  {'status':<16} pitch    yaw   roll [deg]   x      y      z [m]")
    rows = []
    note = replaced_note(args.output) if args.output else ""
    # each row printed, and written to -o, as it is done: a folder may hold thousands, and an
    # interrupted run keeps the rows it has
    with (open(args.output, "w", newline="", encoding="utf-8") if args.output
          else contextlib.nullcontext()) as table:
        writer = csv.DictWriter(table, COLUMNS, lineterminator="\n") if table else None
        if writer:
            writer.writeheader()
        for image in images:
            try:
                color = read_image(image)
            except (OSError, RGBDFormatError) as e:  # a missing, truncated or unreadable file
                print(f"phjax: warning: {e}", file=sys.stderr)
                result = MonocularResult(0.0, np.full(3, np.nan), np.full(4, np.nan),
                                         HeadPoseStatus.INVALID_INPUT)
            else:
                shape = color.shape[:2]
                if shape not in estimators:  # the models are loaded once, for the first image
                    intrinsics = intrinsics_from_fov(shape[1], shape[0], args.fov)
                    estimators[shape] = (
                        next(iter(estimators.values())).with_intrinsics(intrinsics)
                        if estimators
                        else MonocularHeadPose(intrinsics, args.ipd, method=args.method,
                                               head_size=args.head_size, detector=detector,
                                               model_dir=args.model_dir, track=False))
                estimator = estimators[shape]
                estimator.reset()  # each image on its own (the landmark method's PnP start)
                result = estimator.process(color)
            r = _row(image, result)
            rows.append(r)
            angles = " ".join(f"{r[k]:6.1f}" for k in COLUMNS[2:5])
            pos = " ".join(f"{r[k]:6.3f}" for k in COLUMNS[5:8])
            print(f"{r['image']:<{width}}  {r['status']:<16}{angles}   {pos}", flush=True)
            if writer:
                writer.writerow({k: (repr(float(v)) if isinstance(v, (float, np.floating))
                                     else v) for k, v in r.items()})
                table.flush()
    ok = sum(r["status"] == "OK" for r in rows)
    assumed = (f"--head-size {args.head_size:g} m" if args.method == "net"
               else f"--ipd {args.ipd:g} m")
    print(f"{ok} of {len(rows)} images with a head pose (angles: AFLW2000-3D convention, "
          f"relative to the viewing ray; position: camera frame at --fov {args.fov:g} deg, "
          f"distance from {assumed})")
    if args.output:
        print(f"wrote {args.output}{note}")
    return 0


def add_commands(sub) -> None:
    from ..vision.monocular import DEFAULT_HEAD_SIZE, DEFAULT_IPD, METHODS

    p = sub.add_parser(
        "head-pose", help="head pose from photos (colour only), one row per image",
        description="Run the monocular head-pose front-end of 'phjax live webcam' on each image "
        "on its own: YuNet face detection and opentrack's head-pose network (default; its "
        "weights are for research / non-commercial use) or five landmarks and PnP "
        "(--method landmarks). Prints, per image, the status, the head's pitch, yaw and roll "
        "in degrees in the AFLW2000-3D / 300W-LP convention of single-image head-pose "
        "benchmarks (relative to the viewing ray; phjax.vision.pitch_yaw_roll), and the head "
        "centre in the camera frame (x right, y down, z forward, m; the distance comes from "
        "an assumed head size and field of view). An image without a detectable face gets "
        "status NO_FACE and NaN values; one OpenCV cannot read, INVALID_INPUT and a warning.")
    p.add_argument("images", nargs="+", help="image files, or folders of images (" +
                   ", ".join(IMAGE_SUFFIXES) + ")")
    p.add_argument("-o", "--output", default=None,
                   help="also write the table as CSV (" + ",".join(COLUMNS) + "); an existing "
                   "file is replaced (the output says so)")
    p.add_argument("--method", choices=METHODS, default="net",
                   help="net: the head-pose network (default); landmarks: YuNet's five "
                   "landmarks and PnP")
    p.add_argument("--fov", type=float_between(*FOV_RANGE, "degrees"), default=60.0,
                   help="horizontal field of view of the camera, degrees (default 60); sets "
                   "the position only")
    p.add_argument("--head-size", type=float_between(*HEAD_SIZE_RANGE, "m"),
                   default=DEFAULT_HEAD_SIZE,
                   help=f"assumed vertical head size, m (default {DEFAULT_HEAD_SIZE:g}; net "
                   "method); sets the distance only")
    p.add_argument("--ipd", type=float_between(*IPD_RANGE, "m"), default=DEFAULT_IPD,
                   help=f"assumed inter-pupillary distance, m (default {DEFAULT_IPD:g}; "
                   "landmarks method); sets the distance only")
    p.add_argument("--model-dir", default=None,
                   help="model cache folder (default $PHJAX_MODEL_DIR or ~/.cache/phjax/models)")
    p.add_argument("--download-models", action="store_true",
                   help="download the missing model files (YuNet; the network) into the model "
                   "folder (urllib; checked against their sha256)")
    p.set_defaults(func=cmd_head_pose)

