"""Simulation-based calibration of the velocity laws on equilibrium (DF) velocities.

Each draw of ``tests/sbc_helpers.py`` (``sbc_full_trial``, ``velocities = "df"``): the full
``imbh`` model's parameters from the prior ``SBC_DF_PRIORS`` (where the constant-beta DF
exists; the same prior in the fit), stars at their 3-D radii with velocities drawn from
the tracer's Cuddeford DF in the model's total potential, a nested fit (100 / 0.5) with
each velocity law, the rank of the true M_bh. The same seeds (data) for every law.
``null``: M_bh = 0, fitted with the models ``none`` and ``imbh`` (the stage's
``fit_models`` and ``compare``): ln B and verdict per law; with ``--model imbh_dark`` the
stage's four models (``none``, ``imbh``, ``dark``, ``imbh_dark``), the verdict between the
best with an IMBH and the best without.

Resumable: every finished fit is a JSON line; a rerun skips the (case, seed) pairs done.

Usage::

    python benchmarks/sbc_df.py run OUT.jsonl --laws line_of_sight,gaussian,free_kurtosis \\
        --seeds 3000:3060 [--field 15] [--stars 800] [--workers 2] [--null] [--model imbh_dark]
    python benchmarks/sbc_df.py table OUT.jsonl
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from mavispm.dynamics.settings import DynamicsSettings

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

#: law names of this script: the package's, plus the radial free-kurtosis profile
LAWS = {
    "line_of_sight": ("line_of_sight", {}),
    "gaussian": ("gaussian", {}),
    "free_kurtosis": ("free_kurtosis", {}),
    "free_kurtosis_radial": ("free_kurtosis", {"kappa_profile": "radial"}),
    "line_of_sight_kurtosis": ("line_of_sight_kurtosis", {}),
    # nulls only (the SBC fit does not go through fit_models): the two laws weighed
    "weighed": ("weighed", {"compare_velocity_laws": ("free_kurtosis", "line_of_sight")}),
    # the same with the general anisotropy profile (beta_0, beta_inf, r_a) in every model
    "weighed_general": (
        "weighed",
        {"compare_velocity_laws": ("free_kurtosis", "line_of_sight"), "anisotropy": "general"},
    ),
}

#: the models a null fits, by ``--model``: the two of the IMBH test, or the stage's four
NULL_MODELS = {"imbh": ("none", "imbh"), "imbh_dark": DynamicsSettings.models}


def _job(args):
    law, seed, field, n_stars, null, model = args
    import sbc_helpers as h

    velocity_law, kw = LAWS[law]
    t0 = time.process_time()
    if null:
        models = NULL_MODELS[model]
        out = h.null_df_trial(
            seed, n_stars, velocity_law, field, h.SBC_DF_PRIORS, models=models, **kw
        )
    else:
        out = h.sbc_full_trial(
            seed,
            model=model,
            n_stars=n_stars,
            velocities="df",
            velocity_law=velocity_law,
            field_radius=field,
            priors=h.SBC_DF_PRIORS,
            **kw,
        )
    out.update(
        law=law, null=null, model=model, cpu_s=time.process_time() - t0, load=os.getloadavg()[0]
    )
    return out


def _key(r) -> tuple:
    return (
        r["law"],
        r["seed"],
        float(r["field_radius"]),
        r["n_stars"],
        bool(r["null"]),
        r.get("model", "imbh"),
    )


def run(path: Path, laws, seeds, field: float, n_stars: int, workers: int, null: bool, model: str):
    done = set()
    if path.exists():
        done = {_key(json.loads(line)) for line in path.read_text().splitlines() if line}
    # seed by seed over every law, so that an interrupted run leaves matched draws
    jobs = [
        (law, s, field, n_stars, null, model)
        for s in seeds
        for law in laws
        if (law, s, float(field), n_stars, null, model) not in done
    ]
    print(f"{len(jobs)} fits to run ({len(done)} done)", flush=True)
    if workers <= 1:
        results = map(_job, jobs)
    else:
        import multiprocessing as mp

        pool = mp.get_context("spawn").Pool(workers, maxtasksperchild=20)
        results = pool.imap_unordered(_job, jobs)
    with path.open("a") as fh:
        for r in results:
            fh.write(json.dumps(r) + "\n")
            fh.flush()
            tag = f"ln B {r['ln_b']:+.2f} {r['verdict']}" if null else f"rank {r['rank']}"
            print(f"{r['law']} {r['seed']} {tag} cpu {r['cpu_s']:.1f}", flush=True)


def _rank_p(ranks, n_ranks: int = 99, bins: int = 10):
    from scipy.stats import chi2

    h = np.bincount(np.asarray(ranks) * bins // (n_ranks + 1), minlength=bins)
    e = len(ranks) / bins
    return h, float(chi2.sf(np.sum((h - e) ** 2 / e), bins - 1))


#: the laws whose SBC rows are weighed by evidence (``compare_velocity_laws``'s choice)
WEIGHED = ("free_kurtosis", "line_of_sight")


def _add_weighed(groups: dict) -> None:
    """Add, per SBC (field, stars) group with rows of both :data:`WEIGHED` laws that carry
    ``log_z``, a row per common seed from the law with the higher evidence: the posterior
    the stage's ``compare_velocity_laws`` keeps (CPU: both fits)."""
    for (null, field, n, law), rs in list(groups.items()):
        other = groups.get((null, field, n, WEIGHED[1]))
        if null or law != WEIGHED[0] or other is None:
            continue
        by_seed = {r["seed"]: r for r in other if "log_z" in r}
        rows = []
        for r in rs:
            o = by_seed.get(r["seed"])
            if o is not None and "log_z" in r:
                pick = r if r["log_z"] >= o["log_z"] else o
                keep = {k: v for k, v in pick.items() if not k.startswith("kappa")}
                rows.append({**keep, "cpu_s": r["cpu_s"] + o["cpu_s"]})
        if rows:
            groups[(null, field, n, "weighed (" + ", ".join(WEIGHED) + ")")] = rows


def table(path: Path, seeds=None):
    rows = [json.loads(line) for line in path.read_text().splitlines() if line]
    groups = {}
    for r in rows:
        if seeds is None or r["seed"] in seeds:
            law = r["law"] if r.get("model", "imbh") == "imbh" else f"{r['law']} ({r['model']})"
            groups.setdefault((r["null"], r["field_radius"], r["n_stars"], law), []).append(r)
    _add_weighed(groups)
    # keep the seeds every law of a (null, field, stars) group has, so that rows compare
    common = {}
    for (null, field, n, _law), rs in groups.items():
        s = {r["seed"] for r in rs}
        common[(null, field, n)] = common.get((null, field, n), s) & s
    print(
        "| field, stars | law | draws | M_bh rank histogram | chi^2 p | 68% / 95% | pulls | "
        "M_bh >= 1000: 68% / 95% | kappa medians | redraws | CPU s per fit (median, range) |"
        " load |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (null, field, n, law), rs in sorted(groups.items()):
        rs = [r for r in rs if r["seed"] in common[(null, field, n)]]
        cpu = np.array([r["cpu_s"] for r in rs])
        load = np.array([r["load"] for r in rs])
        cpu_txt = f"{np.median(cpu):.1f} ({cpu.min():.0f}-{cpu.max():.0f})"
        load_txt = f"{load.min():.1f}-{load.max():.1f}"
        if null:
            lnb = np.array([r["ln_b"] for r in rs])
            verd = {v: sum(r["verdict"] == v for r in rs) for v in ("imbh", "undecided", "no_imbh")}
            print(
                f'| null {field:g}", {n} | {law} | {len(rs)} | ln B median {np.median(lnb):+.2f}'
                f" ({lnb.min():+.2f} to {lnb.max():+.2f}), ln B < 1 in {np.sum(lnb < 1)} | "
                f"verdicts {verd} | | | | | {cpu_txt} | {load_txt} |"
            )
            continue
        truth = np.array([r["bh_true"] for r in rs])
        q = {k: np.array([r[k] for r in rs]) for k in ("q2.5", "q16", "q50", "q84", "q97.5")}
        c68 = (q["q16"] <= truth) & (truth <= q["q84"])
        c95 = (q["q2.5"] <= truth) & (truth <= q["q97.5"])
        pull = (q["q50"] - truth) / (0.5 * (q["q84"] - q["q16"]))
        big = truth >= 1000
        hist, p = _rank_p([r["rank"] for r in rs])
        kap = [k for k in rs[0] if k.startswith("kappa") and k.endswith("_median")]
        kap_txt = ", ".join(
            f"{k[:-7]} {np.median([r[k] for r in rs]):+.2f}"
            f" ({min(r[k] for r in rs):+.2f} to {max(r[k] for r in rs):+.2f})"
            for k in kap
        )
        redraws = sum(r.get("df_redraws", 0) for r in rs)
        print(
            f'| {field:g}", {n} | {law} | {len(rs)} | {" ".join(map(str, hist))} | {p:.2g} | '
            f"{c68.mean():.2f} / {c95.mean():.2f} | {pull.mean():+.2f} +- {pull.std(ddof=1):.2f} | "
            f"{c68[big].mean():.2f} / {c95[big].mean():.2f} ({big.sum()}) | {kap_txt or '-'} | "
            f"{redraws} | {cpu_txt} | {load_txt} |"
        )


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out", type=Path)
    r.add_argument("--laws", default="line_of_sight,gaussian,free_kurtosis")
    r.add_argument("--seeds", default="3000:3060")
    r.add_argument("--field", type=float, default=15.0, help="field radius [arcsec]")
    r.add_argument("--stars", type=int, default=800)
    r.add_argument("--workers", type=int, default=2)
    r.add_argument("--null", action="store_true", help="M_bh = 0, models none and imbh")
    r.add_argument(
        "--model",
        default="imbh",
        choices=("imbh", "imbh_dark"),
        help="the fitted model (SBC); with --null, imbh_dark fits the stage's four models",
    )
    t = sub.add_parser("table")
    t.add_argument("out", type=Path)
    t.add_argument("--seeds", default=None)
    a = ap.parse_args(argv)

    def seeds(txt):
        lo, hi = map(int, txt.split(":"))
        return range(lo, hi)

    if a.cmd == "run":
        laws = a.laws.split(",")
        for law in laws:
            if law not in LAWS:
                raise SystemExit(f"unknown law {law!r}; one of {sorted(LAWS)}")
        if "weighed" in laws and not a.null:
            raise SystemExit("law 'weighed' is for --null runs (the SBC fit bypasses fit_models)")
        run(a.out, laws, seeds(a.seeds), a.field, a.stars, a.workers, a.null, a.model)
    else:
        table(a.out, None if a.seeds is None else set(seeds(a.seeds)))


if __name__ == "__main__":
    main()
