"""Sensitivity of phjax to the sensor and the render rate, relative to the Kalman CV baseline.

    python experiments/sensitivity.py            # 100 windows per benchmark, 16 conditions
    python experiments/sensitivity.py --quick    # 10 windows per benchmark (< 2 min)
    python experiments/sensitivity.py --smoke    # 1 window per benchmark (tests)

One factor at a time around the default sensor (30 Hz, 5 mm, 1 deg, 5 % dropouts, no jitter;
120 Hz render): camera rate 15/30/60 Hz; noise (sigma_p, sigma_r) from (2 mm, 0.5 deg) to
(20 mm, 3 deg); dropouts 0-30 %; timestamp jitter 0-30 % of the period (irregular sampling
as of a Kinect-class camera such as Biwi's); render rate 60-144 Hz.

The same windows (``experiments/common.py``, excerpt protocol) and the same sensor key per window
are used in every condition (common random numbers), so conditions differ only by the factor.
Per window the ratio ``phjax / Kalman CV`` of position and rotation RMSE and of position and
rotation RMS jerk is formed; the summary is the geometric mean of the ratios over windows with a
95 % cluster-bootstrap CI (bootstrap of the mean log ratio). Writes ``per_window.csv``,
``meta.json``, ``summary_stats.csv``, ``summary.md`` and ``sensitivity.png`` into ``--out``
(default ``results/sensitivity``); ``--from-csv DIR`` redoes the statistics and the figure.
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

REFERENCE = "kalman-cv extrapolation"
#: the default tracker with the online measurement-noise floor (``TrackerConfig.noise_window``),
#: selectable with ``--methods``
NOISE_FLOOR = "phjax (causal + noise floor 60)"
METRICS = {
    "position_rmse": "position RMSE",
    "rotation_rmse_deg": "rotation RMSE",
    "jerk_position": "RMS jerk (position)",
    "jerk_rotation": "RMS angular jerk",
}
DEFAULT = dict(rate=30.0, sigma_p=0.005, sigma_r_deg=1.0, dropout=0.05, jitter=0.0, render=120.0)


@dataclasses.dataclass(frozen=True)
class Factor:
    name: str
    label: str
    levels: tuple  # tuples of overrides of DEFAULT
    ticks: tuple  # tick labels


FACTORS = (
    Factor("rate", "camera rate [Hz]", tuple(dict(rate=r) for r in (15.0, 30.0, 60.0)),
           ("15", "30", "60")),
    Factor("noise", "noise sigma_p [mm] / sigma_r [deg]",
           tuple(dict(sigma_p=p, sigma_r_deg=r) for p, r in
                 ((0.002, 0.5), (0.005, 1.0), (0.010, 2.0), (0.020, 3.0))),
           ("2/0.5", "5/1", "10/2", "20/3")),
    Factor("dropout", "dropouts [%]", tuple(dict(dropout=d) for d in (0.0, 0.05, 0.1, 0.2, 0.3)),
           ("0", "5", "10", "20", "30")),
    Factor("jitter", "timestamp jitter [% of period]",
           tuple(dict(jitter=j) for j in (0.0, 0.1, 0.2, 0.3)), ("0", "10", "20", "30")),
    Factor("render", "render rate [Hz]", tuple(dict(render=r) for r in (60.0, 90.0, 120.0, 144.0)),
           ("60", "90", "120", "144")),
)


def condition_key(c: dict) -> tuple:
    return tuple(sorted(c.items()))


def conditions() -> list[dict]:
    """Unique conditions (the default is shared by every factor)."""
    seen, out = set(), []
    for f in FACTORS:
        for lv in f.levels:
            c = dict(DEFAULT, **lv)
            if condition_key(c) not in seen:
                seen.add(condition_key(c))
                out.append(c)
    return out


def parse_args(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help="10 windows per benchmark")
    mode.add_argument("--smoke", action="store_true", help="1 window per benchmark (tests)")
    ap.add_argument("--windows", type=int, default=None, help="windows per benchmark (default 100)")
    ap.add_argument("--out", default=None, help="output folder (default results/sensitivity[_quick])")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--methods", default="phjax (causal)",
                    help="comma-separated methods compared with the Kalman CV reference "
                    f"(those of common.study_methods, and {NOISE_FLOOR!r}: the default tracker "
                    "with TrackerConfig(noise_window=60))")
    ap.add_argument("--n-boot", type=int, default=2000)
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--from-csv", default=None, metavar="DIR",
                    help="redo statistics, tables and figures from DIR/per_window.csv and "
                         "DIR/meta.json of an earlier run")
    args = ap.parse_args(argv)
    if args.windows is None:
        args.windows = 1 if args.smoke else 10 if args.quick else 100
    if args.out is None:
        args.out = "results/sensitivity" + ("_smoke" if args.smoke else "_quick" if args.quick else "")
    return args


def study_methods(names):
    """``common.study_methods`` plus :data:`NOISE_FLOOR`."""
    from phjax.evaluation.report import Method
    from phjax.tracking import TrackerConfig, track

    def floor(t, p, q, r):
        return track(t, p, q, r, config=TrackerConfig(noise_window=60))

    known = [n for n in names if n != NOISE_FLOOR]
    by_name = {m.name: m for m in C.study_methods(known)}
    by_name[NOISE_FLOOR] = Method(NOISE_FLOOR, floor, True, False)
    return [by_name[n] for n in names]


def run_study(args):
    t_start = time.perf_counter()
    protocol = C.Protocol()
    shapes = C.Shapes.for_protocol(protocol)
    names = [s.strip() for s in args.methods.split(",") if s.strip()]
    methods = study_methods([n for n in names if n != REFERENCE] + [REFERENCE])
    recs = C.load_recordings()
    windows = C.draw_windows(recs, args.windows, args.seed + 1, protocol)
    conds = conditions()
    rows = []
    jobs = [(c, w) for c in conds for w in windows]
    for c, w in C.progress(jobs, not args.no_progress, desc="sensitivity (condition x window)"):
        sensor = SensorModel(rate=c["rate"], sigma_p=c["sigma_p"],
                             sigma_r=float(np.deg2rad(c["sigma_r_deg"])), dropout=c["dropout"],
                             jitter=c["jitter"])
        rec = recs[w.dataset][w.recording]
        ex = C.make_excerpt(rec, w, sensor=sensor, render_rate=c["render"], seed=args.seed,
                            protocol=protocol, shapes=shapes)
        streams = C.run_methods(ex, methods)
        for m in methods:
            met = C.window_metrics(ex, *streams[m.name], full=False)
            rows.append(dict(**c, dataset=w.dataset, source=w.source, recording=w.name,
                             window=w.uid, block=w.block, method=m.name, **met))
    meta = dict(wall=time.perf_counter() - t_start, windows=len(windows), conditions=len(conds),
                methods=[m.name for m in methods], environment=C.environment_line())
    return rows, meta


def ratio_stats(rows, method, n_boot, seed):
    """``{(factor, level_index, dataset, metric): (geo_mean, lo, hi, n)}`` of method/reference."""
    index = {}
    for r in rows:
        index[condition_key({k: r[k] for k in DEFAULT}), r["window"], r["method"]] = r
    out = {}
    for fi, f in enumerate(FACTORS):
        for li, lv in enumerate(f.levels):
            ck = condition_key(dict(DEFAULT, **lv))
            for di, d in enumerate(C.DATASETS):
                wins = sorted({r["window"] for r in rows if r["dataset"] == d})
                for ki, k in enumerate(METRICS):
                    lr, g = [], []
                    for w in wins:
                        a, b = index.get((ck, w, method)), index.get((ck, w, REFERENCE))
                        if a is None or b is None:
                            continue
                        x, y = float(a[k]), float(b[k])
                        lr.append(np.log(x / y) if x > 0 and y > 0 else np.nan)
                        g.append(a["block"])
                    lr = np.asarray(lr, float)
                    mean, lo, hi = C.bootstrap_ci(lr, groups=np.asarray(g), n_boot=n_boot,
                                                  seed=seed + 100 * fi + 20 * li + 5 * di + ki)
                    out[f.name, li, d, k] = (np.exp(mean), np.exp(lo), np.exp(hi),
                                             int(np.isfinite(lr).sum()))
    return out


def summary_markdown(args, meta, stats_by_method) -> str:
    lines = ["# Sensitivity: phjax relative to the Kalman CV extrapolation", "",
             f"- {meta['windows']} windows ({args.windows} per benchmark, seed {args.seed + 1}), "
             f"{meta['conditions']} conditions, wall time {meta['wall']:.0f} s; "
             f"{meta['environment']}",
             "- cells: geometric mean over windows of the per-window ratio method / Kalman CV, "
             f"95 % cluster-bootstrap CI ({args.n_boot} replicates, 10-s blocks); < 1 = lower "
             "than Kalman CV", ""]
    for method, stats in stats_by_method.items():
        lines += [f"## {method} / Kalman CV", ""]
        for f in FACTORS:
            lines += [f"### {f.label}", ""]
            head = ["level", "benchmark"] + list(METRICS.values())
            lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
            for li, tick in enumerate(f.ticks):
                for d in C.DATASETS:
                    cells = [tick, d]
                    for k in METRICS:
                        g, lo, hi, n = stats[f.name, li, d, k]
                        cells.append("-" if n == 0 else f"{g:.3f} [{lo:.3f}, {hi:.3f}]")
                    lines.append("| " + " | ".join(cells) + " |")
            lines.append("")
    return "\n".join(lines)


def plot(stats, method, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    colors = {"head": "#d62728", "object": "#2ca02c", "camera": "#1f77b4"}
    fig, axes = plt.subplots(len(METRICS), len(FACTORS), figsize=(18, 11), sharey="row")
    for j, f in enumerate(FACTORS):
        x = np.arange(len(f.levels))
        for i, k in enumerate(METRICS):
            ax = axes[i, j]
            for d in C.DATASETS:
                v = np.array([stats[f.name, li, d, k][:3] for li in range(len(f.levels))])
                if not np.isfinite(v).any():
                    continue
                ax.plot(x, v[:, 0], "o-", color=colors[d], label=d, ms=4)
                ax.fill_between(x, v[:, 1], v[:, 2], color=colors[d], alpha=0.15, lw=0)
            ax.axhline(1.0, color="k", lw=0.7)
            ax.set_xticks(x)
            ax.set_xticklabels(f.ticks)
            ax.grid(alpha=0.3, which="both", lw=0.4)
            if j == 0:
                ax.set_ylabel(f"{METRICS[k]}\n{method} / Kalman CV")
            if i == len(METRICS) - 1:
                ax.set_xlabel(f.label)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(f"{method} relative to the Kalman CV extrapolation (geometric mean ratio, "
                 "95 % CI); one factor varied at a time", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.from_csv:
        src = Path(args.from_csv)
        rows = C.read_csv(src / "per_window.csv")
        for r in rows:
            r["window"] = int(r["window"])
            for k in list(DEFAULT) + list(METRICS):
                r[k] = float(r[k])
        meta = json.loads((src / "meta.json").read_text())
        args.windows = meta["windows"] // len(C.DATASETS)
        args.seed = meta.get("seed", args.seed)
    else:
        rows, meta = run_study(args)
        meta["seed"] = args.seed
        C.write_csv(out / "per_window.csv", rows)
        (out / "meta.json").write_text(json.dumps(meta, indent=1))
    compared = [m for m in meta["methods"] if m != REFERENCE]
    stats_by_method = {m: ratio_stats(rows, m, args.n_boot, args.seed) for m in compared}
    C.write_csv(out / "summary_stats.csv", [
        dict(method=m, factor=f, level=next(ff for ff in FACTORS if ff.name == f).ticks[li],
             dataset=d, metric=k, geo_mean_ratio=v[0], ci_low=v[1], ci_high=v[2], n=v[3])
        for m, st in stats_by_method.items() for (f, li, d, k), v in st.items()])
    for i, m in enumerate(compared):
        plot(stats_by_method[m], m, out / ("sensitivity.png" if i == 0 else f"sensitivity_{i}.png"))
    text = summary_markdown(args, meta, stats_by_method)
    (out / "summary.md").write_text(text)
    print(text[:3000])
    print(f"wrote {out}/summary.md, per_window.csv, summary_stats.csv, sensitivity.png "
          f"({meta['wall']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
