"""Bias of the M_bh posterior per model, over many independent realistic clusters.

    python benchmarks/bh_mass_bias.py run OUT.jsonl [--seeds 200:230] [--case segregated]
        [--models imbh,imbh_dark] [--mass 1500] [--law free_kurtosis] [--scale-prior-mean 2.21]
        [--anisotropy general]
    python benchmarks/bh_mass_bias.py table OUT.jsonl [OUT2.jsonl ...]

Each row is one model's nested-sampling fit (``validation_settings``, no kinematics-only
evidence) to one ``ngc3201-nbody`` catalogue with an IMBH of ``--mass`` solMass (1500 by
default; luminous stars inside 15", true motions plus 15 microarcsec/yr errors), fitted
with the velocity law ``--law`` (``free_kurtosis`` by default) and the anisotropy model
``--anisotropy`` (the stage's by default), from the validation matrix's
observer's footing (``observer_priors``: centre, distance and scale-radius prior means
drawn about the literature values). ``--scale-prior-mean`` moves every trial's
scale-radius prior mean by the same amount, so that its mean is the given log10 a
[arcsec] (2.21 is the generator's own luminous-star Plummer scale: a diagnostic, not an
observer's prior); the trials stay paired with the observer's ones. ``table`` prints,
per file and model, the mean posterior median with its standard error, the pulls, how
often the 68% interval holds the truth, and the mean of the posterior median over the
highest-likelihood sample's M_bh (whether the marginal leans away from the best fit;
docs/dynamics.md, "Validation matrix").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from mavispm.dynamics.likelihood import VELOCITY_LAWS
from mavispm.dynamics.settings import ANISOTROPY, DynamicsSettings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from dynamics_helpers import (  # noqa: E402
    OBSERVER_LOG_SCALE_RADIUS,
    observer_trial_inputs,
    validation_settings,
)

#: IMBH mass [solMass] of rows written before ``--mass`` existed
DEFAULT_MASS = 1500.0


def trial(
    seed: int,
    case: str,
    models: list[str],
    scale_prior_mean: float | None,
    mass: float = DEFAULT_MASS,
    law: str = "free_kurtosis",
    anisotropy: str = DynamicsSettings.anisotropy,
) -> list[dict]:
    """One cluster's fits with an IMBH of ``mass`` [solMass], the velocity ``law`` and the
    ``anisotropy`` model, one row per model."""
    from mavispm.dynamics.fit import fit_model

    shift = 0.0 if scale_prior_mean is None else scale_prior_mean - OBSERVER_LOG_SCALE_RADIUS[0]
    base = validation_settings(
        kinematic_evidence=False,
        velocity_law=law,  # one law per fit_model (the stage's default weighs two)
        anisotropy=anisotropy,
    )
    stars, dist, s, draws = observer_trial_inputs(seed, case, mass, base, shift)
    rows = []
    for m in models:
        t0 = time.process_time()
        f = fit_model(stars, s, dist, m, seed)
        i = f.space.index("bh_mass")
        bh = np.percentile(f.chain.samples[:, i], [16, 50, 84])
        rows.append(
            {
                "seed": seed,
                "case": case,
                "model": m,
                "imbh_mass": mass,
                "velocity_law": law,
                "anisotropy": anisotropy,
                "n_stars": int(stars.R.size),
                "log_scale_radius_prior": draws["log_a"],
                "ln_z": f.evidence.log_z,
                "bh": bh.tolist(),
                "bh_max_like": float(f.chain.map_params[i]),
                "cpu_s": time.process_time() - t0,
            }
        )
    return rows


def table(paths: list[Path]) -> None:
    """Mean median, pulls and 68% coverage per file and model."""
    for path in paths:
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        for model in sorted({r["model"] for r in rows}):
            mine = [r for r in rows if r["model"] == model]
            for truth in sorted({r.get("imbh_mass", DEFAULT_MASS) for r in mine}):
                sel = [r for r in mine if r.get("imbh_mass", DEFAULT_MASS) == truth]
                print(f"{path.name} {model}, M_bh {truth:g} solMass: {_summary(sel, truth)}")


def _summary(rows: list[dict], truth: float) -> str:
    """One line: mean median, pulls, 68% coverage and median over best fit."""
    lo, med, hi = np.array([r["bh"] for r in rows]).T
    pull = np.where(med < truth, (med - truth) / (hi - med), (med - truth) / (med - lo))
    n = med.size
    se = med.std(ddof=1) / np.sqrt(n) if n > 1 else np.nan
    line = (
        f"{n} clusters, mean median {med.mean():.0f} +- {se:.0f} solMass "
        f"({100 * (med.mean() / truth - 1):+.1f}%), pulls "
        f"{pull.mean():+.2f} +- {pull.std(ddof=1) if n > 1 else np.nan:.2f}, "
        f"68% holds {int(np.sum((lo <= truth) & (truth <= hi)))}/{n}"
    )
    best = np.array([r.get("bh_max_like", np.nan) for r in rows])
    ok = np.isfinite(best) & (best > 0)
    if ok.any():
        ratio = med[ok] / best[ok]
        err = ratio.std(ddof=1) / np.sqrt(ratio.size) if ratio.size > 1 else np.nan
        line += f", median / best fit {ratio.mean():.3f} +- {err:.3f}"
    return line


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="fit and append rows")
    run.add_argument("out", type=Path)
    run.add_argument("--seeds", default="200:230", help="first:last+1")
    run.add_argument("--case", default="segregated")
    run.add_argument("--models", default="imbh,imbh_dark")
    run.add_argument("--scale-prior-mean", type=float, default=None)
    run.add_argument("--mass", type=float, default=DEFAULT_MASS, help="IMBH mass [solMass]")
    run.add_argument(
        "--law", default="free_kurtosis", choices=VELOCITY_LAWS, help="velocity law of every fit"
    )
    run.add_argument(
        "--anisotropy",
        default=DynamicsSettings.anisotropy,
        choices=ANISOTROPY,
        help="anisotropy model of every fit (default: the stage's)",
    )
    tab = sub.add_parser("table", help="print the summary")
    tab.add_argument("paths", type=Path, nargs="+")
    args = ap.parse_args(argv)
    if args.command == "table":
        table(args.paths)
        return
    lo, hi = (int(v) for v in args.seeds.split(":"))
    for seed in range(lo, hi):
        rows = trial(
            seed,
            args.case,
            args.models.split(","),
            args.scale_prior_mean,
            args.mass,
            args.law,
            args.anisotropy,
        )
        for row in rows:
            with open(args.out, "a") as fh:
                fh.write(json.dumps(row) + "\n")
            print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
