"""Fig. 1 of the source paper, reproduced and extended: per-window accuracy and smoothness of
phjax and every baseline on the Head, Object and Camera benchmarks, ordered by difficulty.

    python experiments/fig1.py                  # full study: 400 windows per benchmark
    python experiments/fig1.py --quick          # 40 windows per benchmark (< 2 min)
    python experiments/fig1.py --smoke          # 4 windows per benchmark (tests)

Writes into ``--out`` (default ``results/fig1``):

* ``per_window.csv``: one row per (window, method): benchmark, source, recording, start,
  duration, difficulty features and score, difficulty rank, the ground truth's own path
  metrics, and every metric of :func:`phjax.evaluation.metrics.evaluate` used here;
* ``summary.md``: setup, per-benchmark mean and 95 % cluster-bootstrap CI of every metric and
  method, and the paired difference phjax - baseline with its CI (the paper's "advantage");
* ``summary_stats.csv``, ``paired_differences.csv``: the numbers behind the tables;
  ``meta.json``: the run's settings and timings (``--from-csv DIR`` redoes the statistics and
  figures from ``per_window.csv`` and ``meta.json`` without evaluating again);
* ``fig1.png`` (the paper's 4 x 3 figure: metric vs difficulty rank) and ``fig1_advantage.png``
  (paired relative differences with CIs).

Protocol, difficulty and CI definitions: ``experiments/common.py`` and ``experiments/README.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

import common as C  # noqa: E402

from phjax.motion.simulate import SensorModel  # noqa: E402

DATASET_TITLES = {"head": "Head (VR head traces)", "object": "Object (TUM VI hand-held rig)",
                  "camera": "Camera (TUM RGB-D)"}


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="40 windows per benchmark")
    mode.add_argument("--smoke", action="store_true", help="4 windows per benchmark (tests)")
    ap.add_argument("--windows", type=int, default=None, help="windows per benchmark (default 400)")
    ap.add_argument("--out", default=None, help="output folder (default results/fig1[_quick])")
    ap.add_argument("--seed", type=int, default=0, help="seed of windows, sensor and bootstrap")
    ap.add_argument("--methods", default=None,
                    help="comma-separated method names (default: every method; --quick and "
                         "--smoke leave out the slow optimised-angles variant)")
    ap.add_argument("--rate", type=float, default=30.0, help="camera rate, Hz")
    ap.add_argument("--sigma-p", type=float, default=0.005, help="position noise, m")
    ap.add_argument("--sigma-r", type=float, default=1.0, help="orientation noise, deg")
    ap.add_argument("--dropout", type=float, default=0.05, help="frame loss probability")
    ap.add_argument("--render-rate", type=float, default=120.0, help="render rate, Hz")
    ap.add_argument("--n-boot", type=int, default=2000, help="bootstrap replicates")
    ap.add_argument("--no-neck-model", action="store_true",
                    help="orientation-only head traces keep NaN positions")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--from-csv", default=None, metavar="DIR",
                    help="recompute statistics, tables and figures from DIR/per_window.csv and "
                         "DIR/meta.json of an earlier run (no evaluation)")
    args = ap.parse_args(argv)
    if args.windows is None:
        args.windows = 4 if args.smoke else 40 if args.quick else 400
    if args.out is None:
        args.out = "results/fig1" + ("_smoke" if args.smoke else "_quick" if args.quick else "")
    return args


# ----------------------------------------------------------------------------------------------
# running
# ----------------------------------------------------------------------------------------------


def run_study(args):
    """Evaluate every method on every window. Returns ``(rows, meta)``."""
    t_start = time.perf_counter()
    protocol = C.Protocol()
    shapes = C.Shapes.for_protocol(protocol)
    sensor = SensorModel(rate=args.rate, sigma_p=args.sigma_p, sigma_r=float(np.deg2rad(args.sigma_r)),
                         dropout=args.dropout)
    names = None if args.methods is None else [s.strip() for s in args.methods.split(",") if s.strip()]
    methods = C.study_methods(names, include_slow=not (args.quick or args.smoke))
    recs = C.load_recordings(neck_model=not args.no_neck_model)
    windows = C.draw_windows(recs, args.windows, args.seed, protocol)
    t_load = time.perf_counter() - t_start
    rows, feats, timings = [], [], {}
    phase = dict(simulate=0.0, methods=0.0, metrics=0.0)
    for w in C.progress(windows, not args.no_progress, desc="fig1 windows"):
        rec = recs[w.dataset][w.recording]
        t0 = time.perf_counter()
        ex = C.make_excerpt(rec, w, sensor=sensor, render_rate=args.render_rate, seed=args.seed,
                            protocol=protocol, shapes=shapes)
        t1 = time.perf_counter()
        streams = C.run_methods(ex, methods, timings)
        t2 = time.perf_counter()
        n = ex.n_render
        f = C.difficulty_features(ex.render[:n], ex.gt_positions[:n], ex.gt_quaternions[:n])
        feats.append([f[k] for k in C.DIFFICULTY_FEATURES])
        gt = C.ground_truth_metrics(ex)
        base = dict(dataset=w.dataset, source=w.source, recording=w.name, window=w.uid,
                    start_s=round(w.start, 4), duration_s=round(w.duration, 4), block=w.block,
                    position_source=rec.position_source, **f,
                    **{f"gt_{k}": v for k, v in gt.items()})
        for m in methods:
            met = C.window_metrics(ex, *streams[m.name])
            rows.append(dict(base, method=m.name, causal=m.causal,
                             **{k: met[k] for k in C.ALL_METRICS},
                             n_render=met["position_rmse_n"] or met["rotation_rmse_deg_n"]))
        t3 = time.perf_counter()
        phase["simulate"] += t1 - t0
        phase["methods"] += t2 - t1
        phase["metrics"] += t3 - t2
    # difficulty: per benchmark, features normalised by their median
    feats = np.asarray(feats, np.float64)
    score = np.full(len(windows), np.nan)
    rank = np.zeros(len(windows), int)
    for d in C.DATASETS:
        idx = np.array([i for i, w in enumerate(windows) if w.dataset == d])
        if idx.size:
            score[idx] = C.difficulty_scores(feats[idx])
            rank[idx] = C.difficulty_ranks(score[idx])
    pos = {w.uid: i for i, w in enumerate(windows)}
    for r in rows:
        i = pos[r["window"]]
        r["difficulty"] = score[i]
        r["rank"] = int(rank[i])
    meta = dict(
        command="python experiments/fig1.py " + " ".join(args.argv),
        windows=len(windows), windows_per_dataset=args.windows, seed=args.seed,
        methods=[m.name for m in methods], causal={m.name: m.causal for m in methods},
        sensor=dict(rate=float(sensor.rate), sigma_p=float(sensor.sigma_p),
                    sigma_r_deg=float(np.rad2deg(sensor.sigma_r)), dropout=float(sensor.dropout)),
        render_rate=args.render_rate, neck_model=not args.no_neck_model,
        protocol=dataclasses.asdict(protocol), shapes=dataclasses.asdict(shapes),
        wall=time.perf_counter() - t_start, load=t_load, phase=phase,
        method_ms={k: (1e3 * float(np.median(v)), 1e3 * float(v[0])) for k, v in timings.items()},
        recordings={d: len(v) for d, v in recs.items()},
        used={d: len({w.name for w in windows if w.dataset == d}) for d in C.DATASETS},
        environment=C.environment_line(),
    )
    return rows, meta


# ----------------------------------------------------------------------------------------------
# statistics
# ----------------------------------------------------------------------------------------------


def _column(rows, dataset, method, key):
    sel = [r for r in rows if r["dataset"] == dataset and r["method"] == method]
    sel.sort(key=lambda r: int(r["window"]))
    return (np.array([float(r[key]) for r in sel]), np.array([r["block"] for r in sel]),
            np.array([int(r["window"]) for r in sel]))


def summary_stats(rows, methods, n_boot, seed):
    """``{(dataset, method, metric): (mean, lo, hi, n)}`` with the cluster bootstrap."""
    out = {}
    for di, d in enumerate(C.DATASETS):
        for mi, m in enumerate(methods):
            for ki, k in enumerate(C.ALL_METRICS):
                x, g, _ = _column(rows, d, m, k)
                s = seed + 1000 * di + 37 * mi + ki
                out[d, m, k] = C.bootstrap_ci(x, groups=g, n_boot=n_boot, seed=s) + (
                    int(np.isfinite(x).sum()),)
        for ki, k in enumerate(("curvature_path", "torsion_path", "curvature", "torsion",
                                "jerk_position", "jerk_rotation")):
            x, g, _ = _column(rows, d, methods[0], f"gt_{k}")
            out[d, "ground truth", k] = C.bootstrap_ci(x, groups=g, n_boot=n_boot,
                                                       seed=seed + 1000 * di + 999 + ki) + (
                int(np.isfinite(x).sum()),)
    return out


def paired_differences(rows, methods, n_boot, seed):
    """``{(dataset, phjax_method, baseline, metric): dict(mean, lo, hi, rel, win, n)}``.

    ``mean`` is the mean over windows of ``phjax - baseline`` (same windows, same measurements),
    ``lo, hi`` its 95 % cluster-bootstrap CI; ``rel, rel_lo, rel_hi`` the relative difference
    ``mean(phjax) / mean(baseline) - 1`` with its cluster-bootstrap CI (both means resampled
    together; not for latencies); ``win`` the share of windows where phjax is lower.
    """
    out = {}
    ph = [m for m in methods if C.is_phjax(m)]
    base = [m for m in methods if not C.is_phjax(m)]
    for di, d in enumerate(C.DATASETS):
        for pi, p in enumerate(ph):
            for bi, b in enumerate(base):
                for ki, k in enumerate(C.ALL_METRICS):
                    xp, g, wp = _column(rows, d, p, k)
                    xb, _, wb = _column(rows, d, b, k)
                    if not np.array_equal(wp, wb):
                        raise AssertionError("unpaired windows")
                    diff = xp - xb
                    ok = np.isfinite(diff)
                    s = seed + 7 + 1000 * di + 101 * pi + 13 * bi + ki
                    mean, lo, hi = C.bootstrap_ci(diff, groups=g, n_boot=n_boot, seed=s)
                    if k.startswith("latency"):  # signed, near 0: no relative difference
                        ratio = (np.nan,) * 3
                    else:
                        ratio = C.bootstrap_ratio_ci(xp, xb, groups=g, n_boot=n_boot, seed=s)
                    out[d, p, b, k] = dict(
                        mean=mean, lo=lo, hi=hi, n=int(ok.sum()),
                        rel=ratio[0] - 1, rel_lo=ratio[1] - 1, rel_hi=ratio[2] - 1,
                        win=float(np.mean(diff[ok] < 0)) if ok.any() else np.nan)
    return out


# ----------------------------------------------------------------------------------------------
# report
# ----------------------------------------------------------------------------------------------


def _unit(k):
    return C.ALL_METRICS[k][1]


def summary_markdown(meta, stats, diffs, n_boot) -> str:
    methods = meta["methods"]
    s, p = meta["sensor"], meta["protocol"]
    max_excerpt = p["warmup"] + p["max_len"] + p["tail"]
    lines = [
        "# Fig. 1 reproduction: phjax vs baselines on Head, Object, Camera", "",
        f"Command: `{meta['command'].strip()}`", "",
        f"- {meta['windows']} windows ({meta['windows_per_dataset']} per benchmark), lengths "
        f"U({p['min_len']:g}, {p['max_len']:g}) s, seed {meta['seed']}; recordings used (of "
        "available): " + ", ".join(f"{d} {meta['used'][d]} of {meta['recordings'][d]}"
                                    for d in C.DATASETS),
        f"- sensor: {s['rate']:g} Hz, sigma_p {1e3 * s['sigma_p']:g} mm, sigma_r "
        f"{s['sigma_r_deg']:g} deg, dropout {100 * s['dropout']:g} %; render "
        f"{meta['render_rate']:g} Hz",
        f"- excerpt protocol: each method runs on [start - {p['warmup']:g} s, end + {p['tail']:g} s] "
        "of the recording (causal methods restart there; metrics over the window only)",
        "- head positions: " + ("neck model for orientation-only traces (Corbillon, AVTrack360, "
                                "Hachaj); measured for CWI" if meta["neck_model"] else
                                "CWI only (orientation-only traces have no position metrics)"),
        f"- CI: 95 % percentile bootstrap of the mean over windows, {n_boot} replicates, "
        "resampling 10-s blocks of each recording (cluster bootstrap)",
        f"- wall time {meta['wall']:.0f} s (load {meta['load']:.1f} s, simulate "
        f"{meta['phase']['simulate']:.0f} s, methods {meta['phase']['methods']:.0f} s incl. "
        f"compilation, metrics {meta['phase']['metrics']:.0f} s); {meta['environment']}",
        "",
    ]
    for d in C.DATASETS:
        lines += [f"## {DATASET_TITLES[d]}: mean [95 % CI] per window", ""]
        keys = list(C.ALL_METRICS)
        head = ["method", "causal"] + [f"{C.ALL_METRICS[k][0]} [{_unit(k)}]" for k in keys]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for m in methods + ["ground truth"]:
            cells = [m, "" if m == "ground truth" else ("yes" if meta["causal"][m] else "no")]
            for k in keys:
                v = stats.get((d, m, k))
                cells.append("" if v is None else C.fmt_ci(*v[:3]))
            lines.append("| " + " | ".join(cells) + " |")
        n = stats[d, methods[0], "rotation_rmse_deg"][3]
        npos = stats[d, methods[0], "position_rmse"][3]
        lines += ["", f"n = {n} windows ({npos} with positions).", ""]
    lines += ["## Paired differences phjax - baseline (the paper's \"advantage\")", "",
              "Like-for-like pairs (causal phjax vs causal baselines, offline vs offline) on the "
              "same windows and measurements: relative difference mean(phjax) / mean(baseline) "
              "- 1 with its 95 % cluster-bootstrap CI, and the share of windows where phjax is "
              "lower (negative = phjax lower; for RMSE, jerk and latency lower is better). "
              "Latencies: mean difference in ms.", ""]
    keys = [k for k in C.ALL_METRICS if k not in ("curvature", "torsion")]
    head = ["benchmark", "phjax", "baseline"] + [C.ALL_METRICS[k][0] for k in keys]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for d in C.DATASETS:
        for pm, b in comparison_pairs(methods, meta["causal"]):
            cells = [d, pm, b]
            for kk in keys:
                x = diffs[d, pm, b, kk]
                if x["n"] == 0:
                    cells.append("-")
                    continue
                if kk.startswith("latency"):
                    cells.append(f"{1e3 * x['mean']:+.1f} ms [{1e3 * x['lo']:+.1f}, "
                                 f"{1e3 * x['hi']:+.1f}] (lower in {100 * x['win']:.0f} %)")
                    continue
                rel = (f"{100 * x['rel']:+.0f} %" if np.isfinite(x["rel"]) else "")
                cells.append(f"{rel} [{100 * x['rel_lo']:+.0f}, {100 * x['rel_hi']:+.0f}] "
                             f"(lower in {100 * x['win']:.0f} %)")
            lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "Every pair (also offline phjax vs the causal baselines) and the absolute "
              "differences in SI units are in `paired_differences.csv`.", "",
              f"## Method run time per window (excerpt of up to {max_excerpt:g} s)", "",
              "| method | median ms per window | first call ms (incl. compilation) |",
              "|---|---|---|"]
    for m, (med, first) in meta["method_ms"].items():
        lines.append(f"| {m} | {med:.2f} | {first:.0f} |")
    return "\n".join(lines) + "\n"


def headline_table(stats, methods) -> str:
    """Compact table of the paper's four metrics (mean and CI) for the README."""
    lines = ["| benchmark | method | pos RMSE [mm] | mean curvature (path) [1/m] | mean abs torsion (path) [1/m] "
             "| rot RMSE [deg] |", "|---|---|---|---|---|---|"]
    for d in C.DATASETS:
        for m in methods:
            cells = [d, m]
            for k, scale in (("position_rmse", 1e3), ("curvature_path", 1), ("torsion_path", 1),
                             ("rotation_rmse_deg", 1)):
                mean, lo, hi, _ = stats[d, m, k]
                cells.append(C.fmt_ci(scale * mean, scale * lo, scale * hi))
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------
# figures
# ----------------------------------------------------------------------------------------------


def _rolling_median(x, k):
    x = np.asarray(x, float)
    out = np.full(x.size, np.nan)
    h = k // 2
    for i in range(x.size):
        seg = x[max(0, i - h): i + h + 1]
        seg = seg[np.isfinite(seg)]
        if seg.size >= max(3, k // 4):
            out[i] = np.median(seg)
    return out


def plot_fig1(rows, methods, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = list(C.FIG1_METRICS)
    fig, axes = plt.subplots(len(keys), 3, figsize=(15, 13), sharex="col")
    scatter = [m for m in ("phjax (causal)", "kalman-cv extrapolation") if m in methods]
    for j, d in enumerate(C.DATASETS):
        n_win = len({r["window"] for r in rows if r["dataset"] == d})
        k_roll = max(5, (n_win // 12) | 1)
        for i, k in enumerate(keys):
            ax = axes[i, j]
            series = [(m, k) for m in methods]
            if k in ("curvature_path", "torsion_path"):
                series.append(("ground truth", f"gt_{k}"))
            for mi, (m, key) in enumerate(series):
                src = methods[0] if m == "ground truth" else m
                sel = sorted((r for r in rows if r["dataset"] == d and r["method"] == src),
                             key=lambda r: int(r["rank"]))
                x = np.array([int(r["rank"]) for r in sel])
                y = np.array([float(r[key]) for r in sel])
                st = C.method_style(m, mi)
                if m in scatter:
                    ax.scatter(x, y, s=5, color=st["color"], alpha=0.3, lw=0)
                ax.plot(x, _rolling_median(y, k_roll), label=m, **st)
            ax.set_yscale("log")
            if j == 0:
                ax.set_ylabel(f"{C.FIG1_METRICS[k][0]} [{C.FIG1_METRICS[k][1]}]")
            if i == 0:
                ax.set_title(DATASET_TITLES[d])
            if i == len(keys) - 1:
                ax.set_xlabel("window, ordered by difficulty (rank)")
            ax.grid(alpha=0.3, which="both", lw=0.4)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    h2, l2 = axes[1, 0].get_legend_handles_labels()
    for h, lab in zip(h2, l2):
        if lab not in labels:
            handles.append(h)
            labels.append(lab)
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 4), fontsize=9)
    fig.suptitle("Per-window metrics vs difficulty (dots: phjax causal in red, Kalman CV in blue; "
                 f"lines: rolling median over {k_roll} windows)", fontsize=11)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def comparison_pairs(methods, causal) -> list[tuple[str, str]]:
    """Like-for-like pairs of the advantage figure: causal phjax vs the causal baselines,
    offline phjax variants vs the offline baselines."""
    out = []
    for p in (m for m in methods if C.is_phjax(m)):
        out += [(p, b) for b in methods if not C.is_phjax(b) and causal[b] == causal[p]]
    return out


def plot_advantage(diffs, methods, causal, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [k for k in C.ALL_METRICS if k not in ("curvature", "torsion")]
    pairs = comparison_pairs(methods, causal)
    fig, axes = plt.subplots(len(keys), 3, figsize=(15, 1.1 * len(keys) * max(len(pairs), 4) / 4 + 1),
                             sharey=True)
    y = np.arange(len(pairs))
    for j, d in enumerate(C.DATASETS):
        for i, k in enumerate(keys):
            ax = axes[i, j]
            lat = k.startswith("latency")
            for yi, (p, b) in enumerate(pairs):
                v = diffs[d, p, b, k]
                if v["n"] == 0 or not np.isfinite(v["mean"]):
                    continue
                m, lo, hi = ((1e3 * v["mean"], 1e3 * v["lo"], 1e3 * v["hi"]) if lat else
                             (100 * v["rel"], 100 * v["rel_lo"], 100 * v["rel_hi"]))
                ax.errorbar(m, yi, xerr=[[m - lo], [hi - m]], fmt="o", ms=3.5, capsize=2,
                            color=C.method_style(p)["color"])
            ax.axvline(0, color="k", lw=0.6)
            ax.set_yticks(y)
            ax.set_yticklabels([f"{p} - {b}" for p, b in pairs], fontsize=7)
            ax.tick_params(axis="x", labelsize=7)
            ax.grid(alpha=0.3, lw=0.4)
            ax.set_xlabel("phjax - baseline, ms" if lat else "phjax - baseline, % of baseline",
                          fontsize=7)
            if j == 0:
                ax.set_ylabel(C.ALL_METRICS[k][0], fontsize=8)
            if i == 0:
                ax.set_title(DATASET_TITLES[d], fontsize=10)
    fig.suptitle("Paired difference phjax - baseline over the same windows (mean, 95 % cluster-"
                 "bootstrap CI); left of 0: phjax lower", fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.98))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


# ----------------------------------------------------------------------------------------------


def _typed(rows):
    for r in rows:
        r["window"], r["rank"] = int(r["window"]), int(r["rank"])
    return rows


def main(argv=None) -> int:
    args = parse_args(argv)
    args.argv = sys.argv[1:] if argv is None else list(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.from_csv:
        src = Path(args.from_csv)
        rows = _typed(C.read_csv(src / "per_window.csv"))
        meta = json.loads((src / "meta.json").read_text())
    else:
        rows, meta = run_study(args)
        C.write_csv(out / "per_window.csv", rows)
        (out / "meta.json").write_text(json.dumps(meta, indent=1))
    methods = meta["methods"]
    t0 = time.perf_counter()
    stats = summary_stats(rows, methods, args.n_boot, args.seed)
    diffs = paired_differences(rows, methods, args.n_boot, args.seed)
    C.write_csv(out / "summary_stats.csv", [
        dict(dataset=d, method=m, metric=k, mean=v[0], ci_low=v[1], ci_high=v[2], n=v[3])
        for (d, m, k), v in stats.items()])
    C.write_csv(out / "paired_differences.csv", [
        dict(dataset=d, phjax=p, baseline=b, metric=k, **v) for (d, p, b, k), v in diffs.items()])
    plot_fig1(rows, methods, out / "fig1.png")
    plot_advantage(diffs, methods, meta["causal"], out / "fig1_advantage.png")
    report_s = time.perf_counter() - t0
    text = summary_markdown(meta, stats, diffs, args.n_boot)
    text += (f"\nStatistics, tables and figures: {report_s:.0f} s.\n"
             "\n## Headline (paper's four metrics)\n\n" + headline_table(stats, methods) + "\n")
    (out / "summary.md").write_text(text)
    print(headline_table(stats, methods))
    print(f"\nwrote {out}/summary.md, per_window.csv, summary_stats.csv, paired_differences.csv, "
          f"fig1.png, fig1_advantage.png (study {meta['wall']:.0f} s, report {report_s:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
