"""Does the phjax stream want a filter of its own? The IMM model set chosen *with* the horizon.

    python experiments/stream_filter_choice.py [--lookaheads 20 50] [--draws 3] [--draw K]
                                               [--seconds 15] [--render-phase 0.5]
                                               [--out results/stream_filter_choice]

``display_frontier.py`` runs the stream on the IMM model set tuned for the IMM *extrapolation*
(lowest train RMSE, per channel) and chooses only the horizon by the stream's rule (lowest train
RMSE among the horizons with train jerk <= 1/3 of the tuned Kalman CV's). A filter that jumps
less at each frame might let the stream settle faster at the same jerk, so here the model set
is chosen with the horizon: every IMM grid point of ``frontier.py`` (18) at every horizon of
``display_frontier.py`` (10), and per channel the pair with the lowest train RMSE at train
jerk <= 1/3 of the Kalman CV's (the stream's channels are independent with ``adapt`` 0, so one
sweep serves both). Everything else is ``display_frontier.py``'s protocol (data, sensor draws,
split, baselines tuned on train at each lookahead, ratios against the strongest external
baseline, medians over the test recordings; ``--render-phase`` as there).

Output: a table per lookahead and draw (the choice of each rule, the test ratio against the
strongest external baseline, median and mean over recordings, and the test jerk / Kalman CV),
printed and written to ``--out``/``stream_filter_choice.md``. About 150 s per lookahead and
draw on one core.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))
import display_frontier as D  # noqa: E402
import frontier as F  # noqa: E402
from devset import add_sensor_arguments  # noqa: E402

from phjax.tracking.kalman import KalmanConfig  # noqa: E402
from phjax.tracking.tracker import TrackerConfig, track  # noqa: E402

KF = "kalman-cv extrapolation"
JOINT = "stream, IMM chosen with the horizon"
CHANNELS = (("p", "pos", "jp"), ("r", "rot", "jr"))


def joint_sweep(data, res, L: float) -> dict:
    """``{(grid point, horizon): rows}``: the stream on every IMM grid point and horizon, with
    the Kalman CV noise tuned at ``L`` (as ``display_frontier.measure``)."""
    kf = res["tuned"][KF]
    kf_cfg = KalmanConfig(pos_process_noise=0.03 * kf[0], rot_process_noise=0.3 * kf[1])
    out = {}
    for g in F.IMM_GRID:
        imm = F._imm_config(0.03 * g[0], 0.3 * g[0], g[1], g[2])
        for h in D.HORIZONS:
            cfg = TrackerConfig(kalman=kf_cfg, imm=imm, horizon=h, lookahead=L)
            out[(g, h)] = D.run(data, lambda t, p, q, r, c=cfg: track(t, p, q, r, config=c), L)
    return out


def choose(sweep: dict, res, train: list[int], ch: str):
    """The ``(grid point, horizon)`` of channel ``ch`` by the stream's rule on train."""
    _, key, jkey = next(c for c in CHANNELS if c[0] == ch)
    kf_rows = D.rows_of(res, KF, ch)
    ok = [k for k in sweep if F.rel_mean(sweep[k], kf_rows, jkey, train) <= 1 / 3]
    if not ok:  # as frontier.horizon_rule: the smoothest when none meets the rule
        return max(sweep, key=lambda k: k[1])
    return min(ok, key=lambda k: F.rel_mean(sweep[k], res["hold"], key, train))


def rows(data, res, sweep, train, test, L, draw) -> list[str]:
    """The table rows of one lookahead and draw."""
    out = []
    for ch, key, jkey in CHANNELS:
        k = choose(sweep, res, train, ch)
        runs = dict(res["runs"])
        runs[(JOINT, k)] = sweep[k]
        both = dict(res, runs=runs, tuned=dict(res["tuned"], **{JOINT: (k, k)}))
        imm = res["tuned"][D.IMM][0 if ch == "p" else 1]
        for name, choice in ((D.STREAM, f"{imm}, {res['tuned'][D.STREAM][0] * 1e3:g} ms"),
                             (JOINT, f"{k[0]}, {k[1] * 1e3:g} ms")):
            med, base = D.strongest(both, name, key, test)
            mean, _ = D.strongest(both, name, key, test, stat="mean")
            jerk = F.med_ratio(D.rows_of(both, name, ch), D.rows_of(both, KF, ch), jkey, test)
            out.append(f"| {L * 1e3:g} | {draw} | {key} | {name} | {choice} | {med:.3f} ({base}) "
                       f"| {mean:.3f} | {jerk:.3f} |")
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--lookaheads", type=float, nargs="+", default=[20.0, 50.0],
                    help="display-time lookaheads, ms")
    ap.add_argument("--seconds", type=float, default=15.0, help="window per recording, s")
    ap.add_argument("--draws", type=int, default=3, help="sensor draws (--draw, --draw + 1, ...)")
    ap.add_argument("--render-phase", type=float, default=0.0,
                    help="offset of the render clock from the camera clock, render periods")
    ap.add_argument("--out", default="results/stream_filter_choice", help="output folder")
    add_sensor_arguments(ap)
    args = ap.parse_args(argv)
    if args.seconds < 3.5:
        ap.error("--seconds must be at least 3.5 (1 s warm-up, 1 s cut)")
    if any(not 0 <= L <= 200 for L in args.lookaheads):
        ap.error("--lookaheads must lie in 0-200 ms")
    if not 0 <= args.render_phase < 1:
        ap.error("--render-phase must lie in [0, 1) render periods")
    if not 1 <= args.draws <= 20:
        ap.error("--draws must lie in 1-20")
    t0 = time.time()
    lookaheads = [L / 1e3 for L in args.lookaheads]
    seqs = D.load_recordings(args.seconds)
    lines = ["| lookahead (ms) | draw | channel | stream | IMM grid point (centre, spread, "
             "rate), horizon | test ratio, median (strongest baseline) | mean | jerk / KF |",
             "|---|---|---|---|---|---|---|---|"]
    for draw in range(args.draw, args.draw + args.draws):
        recs = D.simulate(seqs, args.seconds, seeding=args.noise_seed, draw=draw)
        data = D.prepare(recs, args.seconds, lookaheads, args.render_phase)
        train, splits = D._split(data, False)
        for L in lookaheads:
            res = D.measure(data, L, train, log=lambda s: None)
            sweep = joint_sweep(data, res, L)
            lines += rows(data, res, sweep, train, splits["test"], L, draw)
            print(f"draw {draw}, {L * 1e3:g} ms done ({time.time() - t0:.0f} s)", flush=True)
    head = (f"Test split, {args.seconds:g} s per recording, render phase {args.render_phase:g}, "
            f"draws {args.draw}-{args.draw + args.draws - 1} ({time.time() - t0:.0f} s). "
            f"'{D.STREAM}': display_frontier.py's stream (IMM tuned for the extrapolation, "
            f"horizon by the rule); '{JOINT}': both chosen by the rule, per channel.")
    text = "\n".join([head, ""] + lines) + "\n"
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "stream_filter_choice.md").write_text(text)


if __name__ == "__main__":
    main()
