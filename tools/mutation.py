"""Mutation testing of the core modules with Cosmic Ray (slow: run by hand, not in CI).

Each mutant is one small change of a library module (an operator, a comparison, a constant,
a boolean ...) made by Cosmic Ray's operators; the module's own test files then run against
it. A mutant is *killed* when a test fails (or the run times out), and *survives* when every
test passes: either a hole in the tests or an equivalent mutant (same behaviour).

The work happens in a scratch copy of the repository (``--out``, default
``build/mutation``): the checkout is never modified, even when the run is interrupted.
The shared data stays where it is (``$PHJAX_SHARED_DATA`` is pointed at it).

Modules and the tests run against them (``--modules``, default all):

=============  ===========================================  ===============================
name           module                                       tests
=============  ===========================================  ===============================
quaternion     phjax/quaternion.py                          tests/test_quaternion.py
ph_quintic     phjax/curves/ph_quintic.py                   tests/curves/test_ph_quintic.py,
                                                            tests/curves/test_ph_reference.py
kalman         phjax/tracking/kalman.py                     tests/tracking/test_kalman.py
tracker        phjax/tracking/tracker.py                    tests/tracking/test_tracker.py,
                                                            tests/tracking/test_stream.py
metrics        phjax/evaluation/metrics.py                  tests/evaluation/test_metrics.py
=============  ===========================================  ===============================

A full run has thousands of mutants and takes many hours on a laptop; ``--sample N`` draws
``N`` mutants per module with a fixed ``--seed`` (the same mutants for the same code),
``--functions`` keeps the mutants inside the named functions, and ``-k`` narrows the tests of a
module (e.g. to its fast tests; a survivor is then only a survivor of those tests).

Before / after a change of the tests: ``--tests-from REF`` runs the tests as they were at the
git revision ``REF`` (the library stays the working tree's), and ``--rerun-survivors DIR``
runs only the mutants that survived a previous run in ``DIR`` against the current tests
(the tests only grow, so a mutant killed before is still killed)::

    nice -n 10 python tools/mutation.py --modules quaternion metrics --sample 15 --seed 0 \\
        --tests-from HEAD~1 --out build/mutation-before
    nice -n 10 python tools/mutation.py --rerun-survivors build/mutation-before \\
        --out build/mutation-after

Output: one line per mutant while running, then per module the kill rate and every
surviving mutant as a diff; ``summary.json`` and one Cosmic Ray session per module
(``<name>.sqlite``, readable with ``cr-report``) in ``--out``.

Requires ``cosmic-ray`` (the ``mutation`` extra). Exit status 0 when the run completed (whatever
the kill rate), 2 on bad arguments.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import subprocess
import sys
import tarfile
import time
from io import BytesIO
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

MODULES = {
    "quaternion": ("phjax/quaternion.py", ("tests/test_quaternion.py",)),
    "ph_quintic": ("phjax/curves/ph_quintic.py",
                   ("tests/curves/test_ph_quintic.py", "tests/curves/test_ph_reference.py")),
    "kalman": ("phjax/tracking/kalman.py", ("tests/tracking/test_kalman.py",)),
    "tracker": ("phjax/tracking/tracker.py",
                ("tests/tracking/test_tracker.py", "tests/tracking/test_stream.py")),
    "metrics": ("phjax/evaluation/metrics.py", ("tests/evaluation/test_metrics.py",)),
}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python tools/mutation.py",
        description="Mutation testing of phjax's core modules with Cosmic Ray (see the module "
                    "docstring).")
    p.add_argument("--modules", nargs="+", choices=sorted(MODULES), default=None,
                   help="modules to mutate (default: all five)")
    p.add_argument("--sample", type=int, default=None, metavar="N",
                   help="mutants per module, drawn with --seed (default: all of them)")
    p.add_argument("--seed", type=int, default=0, help="seed of the sample (default 0)")
    p.add_argument("--functions", nargs="+", default=None, metavar="NAME",
                   help="only mutants inside these functions / classes (Cosmic Ray's "
                        "definition name), e.g. _data_frame _make_frame")
    p.add_argument("-k", dest="keyword", default=None,
                   help="pytest -k expression narrowing the tests of every module")
    p.add_argument("--timeout", type=float, default=600.0,
                   help="seconds per test run; a run that takes longer counts as killed "
                        "(default 600)")
    p.add_argument("--tests-from", default=None, metavar="REF",
                   help="run the tests as they were at git revision REF (a 'before' run)")
    p.add_argument("--rerun-survivors", type=Path, default=None, metavar="DIR",
                   help="only the mutants that survived the run in DIR (its modules, same "
                        "library code), against the current tests")
    p.add_argument("--out", type=Path, default=REPO / "build" / "mutation",
                   help="scratch copy and results (default build/mutation; replaced)")
    return p


def _copy_tree(dest: Path, tests_from: str | None) -> None:
    """The library, the tests and the project files of the working tree, in ``dest``."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for name in ("phjax", "tests", "pyproject.toml"):
        src = REPO / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(src, dest / name)
    if tests_from is not None:
        shutil.rmtree(dest / "tests")
        data = subprocess.run(["git", "archive", tests_from, "tests"], cwd=REPO, check=True,
                              capture_output=True).stdout
        with tarfile.open(fileobj=BytesIO(data)) as tar:
            tar.extractall(dest, filter="data")


def _test_command(tests, keyword: str | None) -> str:
    cmd = f"{sys.executable} -m pytest -x -q -p no:cacheprovider {' '.join(tests)}"
    return cmd + (f" -k '{keyword}'" if keyword else "")


def _session(work: Path, name: str, out: Path, sample: int | None, seed: int, survivors_of,
             functions=None):
    """Cosmic Ray session of one module: every mutant enumerated, those not selected marked
    skipped. Returns the open database and the selected work items (stable order)."""
    from cosmic_ray.commands import init
    from cosmic_ray.work_db import WorkDB
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    module = MODULES[name][0]
    db = WorkDB(str(out / f"{name}.sqlite"), WorkDB.Mode.create)
    init([Path(module)], db, {})
    def key(w):
        return (w.mutations[0].operator_name, w.mutations[0].occurrence)

    items = sorted(db.work_items, key=key)
    if functions:
        wanted = set(functions)
        inside = [w for w in items if w.mutations[0].definition_name in wanted]
        db.set_multiple_results([w.job_id for w in items if w not in inside],
                                WorkResult(worker_outcome=WorkerOutcome.SKIPPED))
        items = inside
    if survivors_of is not None:
        chosen = [w for w in items if key(w) in survivors_of]
    elif sample is not None and sample < len(items):
        chosen = sorted(random.Random(f"{seed}:{name}").sample(items, sample), key=key)
    else:
        chosen = items
    keep = {w.job_id for w in chosen}
    db.set_multiple_results([w.job_id for w in items if w.job_id not in keep],
                            WorkResult(worker_outcome=WorkerOutcome.SKIPPED))
    return db, chosen, len(items)


def _previous_survivors(directory: Path) -> dict[str, set]:
    summary = json.loads((directory / "summary.json").read_text())
    return {name: {(s["operator"], s["occurrence"]) for s in m["survivors"]}
            for name, m in summary["modules"].items()}


def run(args) -> dict:
    from cosmic_ray.mutating import mutate_and_test
    from cosmic_ray.work_item import TestOutcome, WorkerOutcome

    out = args.out.resolve()
    work = out / "work"
    survivors = _previous_survivors(args.rerun_survivors) if args.rerun_survivors else None
    modules = args.modules or (sorted(survivors) if survivors is not None else list(MODULES))
    _copy_tree(work, args.tests_from)
    os.environ.setdefault("PHJAX_SHARED_DATA", str(REPO.parent / "shared" / "data"))
    os.environ["PYTHONPATH"] = str(work)
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    os.chdir(work)
    summary = {"tests_from": args.tests_from or "working tree", "seed": args.seed,
               "sample": args.sample, "keyword": args.keyword, "functions": args.functions,
               "rerun_survivors_of": str(args.rerun_survivors) if survivors is not None else None,
               "modules": {}}
    for name in modules:
        module, tests = MODULES[name]
        cmd = _test_command(tests, args.keyword)
        db, chosen, total = _session(work, name, out, args.sample, args.seed,
                                     None if survivors is None else survivors.get(name, set()),
                                     args.functions)
        print(f"== {name}: {len(chosen)} of {total} mutants; tests: {cmd}", flush=True)
        counts = {"killed": 0, "survived": 0, "timeout": 0, "incompetent": 0, "no_mutation": 0}
        surv = []
        t_start = time.perf_counter()
        for w in chosen:
            spec = w.mutations[0]
            t0 = time.perf_counter()
            res = mutate_and_test([spec], cmd, args.timeout)
            db.set_result(w.job_id, res)
            if res.worker_outcome == WorkerOutcome.NO_TEST:
                outcome = "no_mutation"
            elif res.test_outcome == TestOutcome.SURVIVED:
                outcome = "survived"
                surv.append({"operator": spec.operator_name, "occurrence": spec.occurrence,
                             "line": spec.start_pos[0], "definition": spec.definition_name,
                             "diff": res.diff})
            elif res.test_outcome == TestOutcome.INCOMPETENT:
                outcome = "incompetent"
            elif res.output == "timeout":
                outcome = "timeout"
            else:
                outcome = "killed"
            counts[outcome] += 1
            print(f"  {outcome:11s} {module}:{spec.start_pos[0]} {spec.operator_name} "
                  f"#{spec.occurrence} ({time.perf_counter() - t0:.0f} s)", flush=True)
        db.close()
        tested = counts["killed"] + counts["survived"] + counts["timeout"]
        rate = (counts["killed"] + counts["timeout"]) / tested if tested else float("nan")
        summary["modules"][name] = {"module": module, "tests": list(tests), "total_mutants": total,
                                    "selected": len(chosen), **counts, "kill_rate": rate,
                                    "seconds": round(time.perf_counter() - t_start),
                                    "survivors": surv}
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def report(summary: dict) -> str:
    lines = [f"tests: {summary['tests_from']}"]
    killed = tested = 0
    for name, m in summary["modules"].items():
        k = m["killed"] + m["timeout"]
        n = k + m["survived"]
        killed, tested = killed + k, tested + n
        lines.append(f"{name:11s} {k:3d} / {n:3d} killed ({100 * m['kill_rate']:.0f} %), "
                     f"{m['selected']} of {m['total_mutants']} mutants, {m['seconds']} s")
        for s in m["survivors"]:
            lines.append(f"  survived: {m['module']}:{s['line']} ({s['definition']}) "
                         f"{s['operator']} #{s['occurrence']}")
            lines += ["    " + ln for ln in s["diff"].splitlines()[2:] if ln[:1] in "+-@"]
    if tested:
        lines.append(f"all: {killed} / {tested} killed ({100 * killed / tested:.0f} %)")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        import cosmic_ray  # noqa: F401
    except ImportError:
        parser.error("cosmic-ray is not installed (pip install -e '.[dev]')")
    if args.sample is not None and args.sample < 1:
        parser.error("--sample must be at least 1")
    if args.rerun_survivors is not None and not (args.rerun_survivors / "summary.json").is_file():
        parser.error(f"no summary.json in {args.rerun_survivors}")
    if args.out.resolve() == REPO or REPO.is_relative_to(args.out.resolve()):
        parser.error("--out must not contain the repository (it is replaced)")
    summary = run(args)
    print(report(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
