"""All metrics for phjax (causal, offline) and every baseline on each development sequence.

    python experiments/evaluate_devset.py [--seconds 30] [--out results/devset]

Each sequence of ``experiments/devset.py`` is sampled by the default sensor model (30 Hz, 5 mm,
1 deg, 5 % dropouts, seed 0) and rendered at 120 Hz by every method of
:func:`phjax.evaluation.default_methods` (baselines with their tuned parameters). Writes
``per_sequence.csv`` and ``summary.md`` (per-sequence tables, and the mean over sequences of each
metric relative to the tuned Kalman CV extrapolation) into ``--out``. ``--variants`` adds the
causal stream with the two non-default options of :class:`phjax.TrackerConfig`,
``reacquire=True`` and ``noise_window=60``.
"""

from __future__ import annotations

import argparse
import csv
import sys
import warnings
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))
from devset import load_devset  # noqa: E402

from phjax.evaluation import evaluate_recording, format_table  # noqa: E402
from phjax.evaluation.report import Method, default_methods  # noqa: E402
from phjax.tracking import TrackerConfig, track  # noqa: E402

KEYS = ["position_rmse", "rotation_rmse_deg", "jerk_position", "jerk_rotation", "curvature",
        "torsion", "velocity_jump", "angular_velocity_jump", "latency_position", "latency_rotation"]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=30.0, help="length of each sequence used")
    ap.add_argument("--out", default="results/devset")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variants", action="store_true",
                    help="also the causal stream with TrackerConfig(reacquire=True) and with "
                    "TrackerConfig(noise_window=60)")
    args = ap.parse_args(argv)
    methods = default_methods()
    if args.variants:
        for name, cfg in (("phjax (causal, reacquire)", TrackerConfig(reacquire=True)),
                          ("phjax (causal + noise floor 60)", TrackerConfig(noise_window=60))):
            methods.insert(1, Method(name, lambda t, p, q, r, c=cfg: track(t, p, q, r, config=c),
                                     True, False))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        seqs = load_devset(max_seconds=args.seconds)
    from tqdm.auto import tqdm

    rows, md = [], ["# Development-set evaluation", ""]
    ratios: dict[str, dict[str, list]] = {}
    for name, kind, t, p, q in tqdm(seqs, desc="sequences"):
        res = evaluate_recording(t, p, q, seed=args.seed, methods=methods)
        md += [f"## {name} ({kind})", "", format_table(res.metrics, res.causal), ""]
        ref = res.metrics["kalman-cv extrapolation"]
        for method, m in res.metrics.items():
            rows.append({"sequence": name, "kind": kind, "method": method, **{k: m.get(k, np.nan) for k in KEYS}})
            r = ratios.setdefault(method, {k: [] for k in KEYS[:4]})
            for k in KEYS[:4]:
                if np.isfinite(m.get(k, np.nan)) and np.isfinite(ref.get(k, np.nan)) and ref[k] > 0:
                    r[k].append(m[k] / ref[k])
    with open(out / "per_sequence.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    summary = ["## Overall: mean over sequences of the ratio to the tuned Kalman CV extrapolation", "",
               "| method | pos RMSE | rot RMSE | pos jerk | rot jerk |", "|---|---|---|---|---|"]
    for method, r in ratios.items():
        summary.append(f"| {method} | " + " | ".join(
            f"{np.mean(r[k]):.3f} (n={len(r[k])})" if r[k] else "-" for k in KEYS[:4]) + " |")
    text = "\n".join(summary + [""] + md)
    (out / "summary.md").write_text(text)
    print("\n".join(summary))
    print(f"\nwrote {out / 'summary.md'} and {out / 'per_sequence.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
