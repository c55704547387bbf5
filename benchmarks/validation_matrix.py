"""Run (and resume) the dynamics validation matrix of issue 13; print its table.

    python benchmarks/validation_matrix.py run OUT.jsonl [--seeds 200:210] [--cases a,b]
        [--masses 0,1500] [--workers 2] [--posterior nested] [--nlive 100] [--dlogz 0.5]
        [--velocity-law line_of_sight] [--compare-laws free_kurtosis,line_of_sight]
        [--anisotropy general]
    python benchmarks/validation_matrix.py table OUT.jsonl

Each trial (``tests/dynamics_helpers.validation_trial``) is one four-model comparison
on an ``ngc3201-nbody`` catalogue of the cluster generator (luminous stars inside 15",
true motions plus 15 microarcsec/yr errors). Trials run seed by seed over every case
and mass, so a stopped run leaves a balanced partial matrix; rows already in OUT are
skipped (resume). ``table`` prints, per case and mass, the seeds run, ln B (full and
kinematics only), how often ln B < 1 (no IMBH) or the 68/95% M_bh intervals hold
the truth (IMBH), and the CPU per trial. ``--no-kinematic-evidence`` halves the cost
(the criteria use the full ln B only). The criteria of issue 13: without an IMBH
ln B < 1 in >= 9 of 10 seeds per case; with 1500 solMass the 68% interval holds the
truth in 5-9 of 10 and the 95% interval in >= 9 of 10.
"""

from __future__ import annotations

import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from mavispm.dynamics.likelihood import VELOCITY_LAWS
from mavispm.dynamics.settings import ANISOTROPY, WEIGHED, WEIGHED_LAWS, DynamicsSettings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from dynamics_helpers import (  # noqa: E402
    SAME_AS_SEGREGATED,
    VALIDATION_CASES,
    validation_settings,
    validation_trial,
)


def _seeds(text: str) -> list[int]:
    lo, hi = (int(v) for v in text.split(":"))
    return list(range(lo, hi))


def _done(path: Path) -> set:
    if not path.exists():
        return set()
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return {(r["seed"], r["case"], float(r["imbh_mass"])) for r in rows}


def _trial(job):
    seed, case, mass, knobs = job
    return validation_trial(seed, case, mass, validation_settings(**knobs))


def run(args) -> None:
    out = Path(args.out)
    done = _done(out)
    knobs = {
        "posterior": args.posterior,
        "nlive": args.nlive,
        "dlogz": args.dlogz,
        "kinematic_evidence": args.kinematic_evidence,
        "anisotropy": args.anisotropy,
        "velocity_law": args.velocity_law,
        "compare_velocity_laws": (
            tuple(filter(None, args.compare_laws.split(",")))
            if args.velocity_law == WEIGHED
            else ()
        ),
    }
    jobs = [
        (seed, case, mass, knobs)
        for seed in _seeds(args.seeds)
        for case in args.cases.split(",")
        for mass in (float(m) for m in args.masses.split(","))
        if (seed, case, mass) not in done and not (case in SAME_AS_SEGREGATED and mass > 0)
    ]
    print(f"{len(jobs)} trials to run ({len(done)} already in {out})", flush=True)
    with ProcessPoolExecutor(max_workers=args.workers) as ex:
        for row in ex.map(_trial, jobs):
            with out.open("a") as fh:
                fh.write(json.dumps({**row, **knobs}, default=float) + "\n")
            print(
                f"seed {row['seed']} {row['case']} M_bh {row['imbh_mass']:g}: ln B "
                f"{row['ln_b']:.2f} (kin {row['ln_b_kin']:.2f}) {row['verdict']}, M_bh "
                f"{row['q50']:.0f} [{row['q16']:.0f}, {row['q84']:.0f}], {row['cpu_s']:.0f} s",
                flush=True,
            )


def _median(values) -> str:
    finite = values[np.isfinite(values)]
    return f"{np.median(finite):.2f}" if finite.size else "not run"


def table(args) -> None:
    rows = [json.loads(line) for line in Path(args.out).read_text().splitlines() if line.strip()]
    print(
        "| case | M_bh true | seeds | ln B (median, range) | kinematic ln B (median) | "
        "criterion | result | CPU s / trial |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for case in VALIDATION_CASES:
        for mass in sorted({float(r["imbh_mass"]) for r in rows}):
            sel = [r for r in rows if r["case"] == case and float(r["imbh_mass"]) == mass]
            if not sel:
                continue
            lnb = np.array([r["ln_b"] for r in sel])
            kin = np.array([r["ln_b_kin"] for r in sel], dtype=float)
            n = len(sel)
            if mass == 0:
                crit = "ln B < 1 in >= 90%"
                res = f"{int(np.sum(lnb < 1))}/{n}"
            else:
                in68 = sum(r["q16"] <= mass <= r["q84"] for r in sel)
                in95 = sum(r["q2.5"] <= mass <= r["q97.5"] for r in sel)
                crit = "68% holds truth 50-90%, 95% >= 90%"
                med = np.median([r["q50"] for r in sel])
                res = f"68%: {in68}/{n}, 95%: {in95}/{n} (median M_bh {med:.0f})"
            cpu = np.median([r["cpu_s"] for r in sel])
            print(
                f"| {case} | {mass:g} | {n} | {np.median(lnb):.2f} ({lnb.min():.2f} to "
                f"{lnb.max():.2f}) | {_median(kin)} | {crit} | {res} | {cpu:.0f} |"
            )


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("--seeds", default="200:210")
    r.add_argument("--cases", default=",".join(VALIDATION_CASES))
    r.add_argument("--masses", default="0,1500")
    r.add_argument("--workers", type=int, default=2)
    r.add_argument("--posterior", default="nested", choices=("nested", "emcee"))
    r.add_argument("--nlive", type=int, default=100)
    r.add_argument("--dlogz", type=float, default=0.5)
    r.add_argument(
        "--velocity-law",
        default=DynamicsSettings.velocity_law,
        choices=(WEIGHED, *VELOCITY_LAWS),
        help="the dynamics stage's velocity_law (default: the stage's)",
    )
    r.add_argument(
        "--compare-laws",
        default=",".join(WEIGHED_LAWS),
        help="comma-separated laws weighed by evidence with --velocity-law weighed "
        "(compare_velocity_laws; default the stage's)",
    )
    r.add_argument(
        "--anisotropy",
        default=DynamicsSettings.anisotropy,
        choices=ANISOTROPY,
        help="the dynamics stage's anisotropy model (default: the stage's); the out file's "
        "finished trials are keyed by seed, case and mass only: one file per setting",
    )
    r.add_argument(
        "--kinematic-evidence",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also the kinematics-only evidences (doubles the nested sampling)",
    )
    t = sub.add_parser("table")
    t.add_argument("out")
    args = p.parse_args(argv)
    run(args) if args.cmd == "run" else table(args)


if __name__ == "__main__":
    main()
