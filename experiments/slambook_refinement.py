"""Relative camera poses on the slambook2 chapter-5 RGB-D frames: feature RANSAC alone
(``refine=None``), with the dense ICP refinement (``refine="icp"``), with the joint dense +
feature refinement (``refine="joint"``, the RANSAC inliers as 3-D point pairs weighted by their
noise model) and with the default joint dense + reprojection refinement (``refine="reproj"``:
all descriptor matches as 2-D reprojection residuals with a gated Tukey loss, re-selected every
iteration, the dense information corrected for the sensor's 9 x 7 depth correlation window),
against the given (approximate) poses, per RANSAC seed; sensitivity tables over the depth
correlation window (``--windows``), the relative feature weight (``--weights``, of
``--variant``) and the Tukey scale of the reprojection refinement; optionally ``cv2.Odometry``
(OpenCV 5, DEPTH / RGB / RGB_DEPTH) as an independent reference.

``cv2.Odometry.compute`` takes no initial guess and fails on these wide baselines (0.2-0.7 m,
up to 25 degrees) when started from the identity, so frame ``a`` (depth + grey) is first
forward-warped into ``b``'s view with the initial motion (z-buffered 2x2 splats) and the
odometry's correction is composed with that motion.

    python experiments/slambook_refinement.py            # seeds 0..7, with cv2.Odometry
    python experiments/slambook_refinement.py --seeds 2 --no-cv2 --weights 1 100 --variant joint

Writes ``results/slambook_refinement/summary.md`` (and prints it).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from phjax.vision import head_pose as H
from phjax.vision import rgbd_io as R
from phjax.datasets import shared_data_dir


REPROJ = H._REFINE_PRESETS["reproj"]  # the default refinement


def _rot_deg(ra: np.ndarray, rb: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(ra.T @ rb) - 1) / 2, -1, 1))))


def _given(seq, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Given motion camera i -> camera i+1 (pose.txt is T_wc)."""
    gt = seq.ground_truth
    ri, rj = H._np_qmatrix(gt.quaternions[i]), H._np_qmatrix(gt.quaternions[i + 1])
    return rj.T @ ri, rj.T @ (gt.positions[i] - gt.positions[i + 1])


def _errors(seq, i, rot, trans) -> tuple[float, float]:
    r, t = _given(seq, i)
    return _rot_deg(r, rot), 100 * float(np.linalg.norm(t - trans))


def _warp(depth, gray, rot, trans, k):
    """Forward-warp a depth + grey image by ``p -> R p + t`` (z-buffer, 2x2 splats)."""
    h, w = depth.shape
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    p = np.stack([(u - k[0, 2]) * z / k[0, 0], (v - k[1, 2]) * z / k[1, 1], z], -1)
    q = p @ rot.T + trans
    keep = q[:, 2] > 0.1
    q, g = q[keep], gray[v[keep], u[keep]]
    uu = k[0, 0] * q[:, 0] / q[:, 2] + k[0, 2]
    vv = k[1, 1] * q[:, 1] / q[:, 2] + k[1, 2]
    out_d = np.zeros((h, w), np.float32)
    out_g = np.zeros((h, w), np.uint8)
    for du in (0, 1):
        for dv in (0, 1):
            ui = np.floor(uu).astype(int) + du
            vi = np.floor(vv).astype(int) + dv
            idx = np.nonzero((ui >= 0) & (ui < w) & (vi >= 0) & (vi < h))[0]
            idx = idx[np.argsort(-q[idx, 2])]  # far first: the nearest point is written last
            cur = out_d[vi[idx], ui[idx]]
            idx = idx[(cur == 0) | (q[idx, 2] < cur)]
            out_d[vi[idx], ui[idx]] = q[idx, 2]
            out_g[vi[idx], ui[idx]] = g[idx]
    return out_d, out_g


def cv_odometry(fa, fb, rot0, trans0, kind: str):
    """``cv2.Odometry`` (``kind`` DEPTH / RGB / RGB_DEPTH) started from ``rot0, trans0``."""
    import cv2

    intr = fa.intrinsics
    k = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1]], np.float32)
    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(k)
    odo = cv2.Odometry(getattr(cv2, "OdometryType_" + kind), settings,
                       cv2.OdometryAlgoType_COMMON)
    ga = cv2.cvtColor(fa.color, cv2.COLOR_BGR2GRAY)
    gb = cv2.cvtColor(fb.color, cv2.COLOR_BGR2GRAY)
    wd, wg = _warp(fa.depth, ga, rot0, trans0, k)
    db = np.asarray(fb.depth, np.float32)
    ok, rt = (odo.compute(wd, db) if kind == "DEPTH" else odo.compute(wd, wg, db, gb))
    rt = np.asarray(rt, np.float64)
    return bool(ok), rt[:3, :3] @ rot0, rt[:3, :3] @ trans0 + rt[:3, 3]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=8, help="RANSAC seeds 0..N-1 (default 8)")
    ap.add_argument("--no-cv2", action="store_true", help="skip the cv2.Odometry reference")
    ap.add_argument("--windows", nargs="*", default=["none", "9x7", "9x9"],
                    help="depth correlation windows of the reproj table (WxH or none; none: "
                         "independent dense residuals; empty: no table)")
    ap.add_argument("--weights", type=float, nargs="*", default=[0.1, 10, 100],
                    help="feature weights of the sensitivity table (none: no table)")
    ap.add_argument("--variant", choices=("reproj", "joint"), default="reproj",
                    help="refinement of the weight table: reprojection pairs re-selected from "
                         "all matches (default) or the RANSAC inliers as 3-D pairs")
    ap.add_argument("--scales", type=float, nargs="*", default=[2.0, 4.685],
                    help="Tukey scales (standard deviations) of the reprojection variant's "
                         "table (default 3; none: no table)")
    ap.add_argument("--out", default="results/slambook_refinement")
    args = ap.parse_args(argv)
    base = shared_data_dir()
    if base is None:
        raise SystemExit("shared data not found (set PHJAX_SHARED_DATA)")
    seq = R.open_rgbd(base / "rgbd_frames_slambook2_ch5")
    frames = [seq[i] for i in range(5)]
    seeds = range(args.seeds)
    for refine in ("icp", "joint", "reproj"):  # compile outside the timings
        H.rgbd_relative_pose(frames[3], frames[4], refine=refine)
    head = "| pair | stage | " + " | ".join(f"seed {s}" for s in seeds) + " | time / pair |"
    lines = ["# slambook2 ch5: relative camera pose errors (deg / cm) against pose.txt", "",
             head, "|" + "---|" * (len(seeds) + 3)]
    refined = {}
    for i in range(4):
        for stage, refine in (("RANSAC", None), ("RANSAC + ICP", "icp"),
                              ("RANSAC + joint", "joint"), ("RANSAC + reproj (default)", "reproj")):
            cells, times = [], []
            for s in seeds:
                t0 = time.perf_counter()
                rel = H.rgbd_relative_pose(frames[i], frames[i + 1], seed=s, refine=refine)
                times.append(time.perf_counter() - t0)
                e = _errors(seq, i, rel.rotation, rel.translation)
                cells.append(f"{e[0]:.2f} / {e[1]:.1f}")
                if refine == "icp":
                    refined[i, s] = rel
            lines.append(f"| {i + 1}->{i + 2} | {stage} | " + " | ".join(cells)
                         + f" | {np.median(times):.2f} s |")
            print(lines[-1], flush=True)
    tables = []
    if args.windows:
        def window(text):
            return None if text == "none" else tuple(int(x) for x in text.split("x"))

        tables.append(("reproj refinement, sensitivity to the depth correlation window "
                       "(`depth_window`; none = independent dense residuals):",
                       [(f"window {w}", dataclasses.replace(REPROJ, depth_window=window(w)))
                        for w in args.windows]))
    if args.weights:
        base_cfg = REPROJ if args.variant == "reproj" else H.DenseRefinement(feature_weight=1.0)
        tables.append((f"{args.variant} refinement, sensitivity to the relative feature weight "
                       "(`feature_weight=w`, on top of the depth-window factor; 1 = noise "
                       "models alone):",
                       [(f"w = {w:g}", dataclasses.replace(base_cfg, feature_weight=w))
                        for w in args.weights]))
    if args.scales:
        tables.append(("reproj refinement, sensitivity to the Tukey scale "
                       "(`feature_loss_scale=c`, standard deviations; default 3):",
                       [(f"c = {c:g}", dataclasses.replace(REPROJ, feature_loss_scale=c))
                        for c in args.scales]))
    for title, cfgs in tables:
        lines += ["", title, "", head, "|" + "---|" * (len(seeds) + 3)]
        for label, cfg in cfgs:
            H.rgbd_relative_pose(frames[3], frames[4], refine=cfg)  # compile
            for i in range(4):
                cells, times = [], []
                for s in seeds:
                    t0 = time.perf_counter()
                    rel = H.rgbd_relative_pose(frames[i], frames[i + 1], seed=s, refine=cfg)
                    times.append(time.perf_counter() - t0)
                    e = _errors(seq, i, rel.rotation, rel.translation)
                    cells.append(f"{e[0]:.2f} / {e[1]:.1f}")
                lines.append(f"| {i + 1}->{i + 2} | {label} | " + " | ".join(cells)
                             + f" | {np.median(times):.2f} s |")
                print(lines[-1], flush=True)
    if not args.no_cv2:
        lines += ["", "cv2.Odometry started from the refined pose of each seed:", "", head,
                  "|" + "---|" * (len(seeds) + 3)]
        for kind in ("DEPTH", "RGB", "RGB_DEPTH"):
            for i in range(4):
                cells, times = [], []
                for s in seeds:
                    rel = refined[i, s]
                    t0 = time.perf_counter()
                    ok, rot, trans = cv_odometry(frames[i], frames[i + 1], rel.rotation,
                                                 rel.translation, kind)
                    times.append(time.perf_counter() - t0)
                    e = _errors(seq, i, rot, trans)
                    cells.append(f"{e[0]:.2f} / {e[1]:.1f}" + ("" if ok else " (failed)"))
                lines.append(f"| {i + 1}->{i + 2} | cv2 {kind} | " + " | ".join(cells)
                             + f" | {np.median(times):.2f} s |")
                print(lines[-1], flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'summary.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
