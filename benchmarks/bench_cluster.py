"""Benchmark of the cluster catalogue stage.

Prints
1. DF construction time (Eddington inversion) against the energy-grid size, with the
   DF's error against a finer grid;
2. table resolution against Jeans-agreement error (reduced chi^2 and the largest
   relative bin error of sigma^2 against the independent quad Jeans projection)
   and table-build / sampling time;
3. cost against number of field stars (end-to-end catalogue in memory and written
   to HDF5) with peak traced memory.

4. the full multi-mass model (preset ngc3201-nbody with IMBH, Osipkov-Merritt anisotropy
   and a black-hole subsystem): construction time of all DFs, and time and peak memory
   for 1e5 and 1e6 field objects.

Targets (2 cores): DF <= 0.5 s; 1e5 field stars <= 2 s; 1e6 <= 20 s; <= 2 GiB for 1e6.
Multi-mass (issue 12): DFs <= 5 s; 1e5 objects <= 5 s, 1e6 <= 40 s, <= 2 GiB.

Usage: ``python benchmarks/bench_cluster.py [--quick]``
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from cluster_helpers import JeansReference, sigma2_interpolator  # noqa: E402

from mavispm.core.catalogue import write_catalogue  # noqa: E402
from mavispm.simulate.cluster.eddington import eddington_df  # noqa: E402
from mavispm.simulate.cluster.field_sampler import SamplerResolution, build_field_sampler  # noqa: E402
from mavispm.simulate.cluster.generator import (  # noqa: E402
    build_cluster_model,
    model_from_params,
    resolve_model_params,
    simulate_catalogue,
)
from mavispm.simulate.cluster.projection import arcsec_to_pc  # noqa: E402
from mavispm.simulate.cluster.settings import ClusterSettings  # noqa: E402


def _timed(fn, *args, repeat=1, **kw):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        best = min(best, time.perf_counter() - t0)
    return best, out


def bench_df(settings):
    print("\n== DF construction (NGC 3201, IMBH 1500 Msun, cusp 1.55) ==")
    params = resolve_model_params(settings)
    model = model_from_params(params)
    ref = eddington_df(model.mass, n_energy=1600, n_nodes=192)
    print(f"{'n_energy':>9} {'time [s]':>9} {'max|df/f| (f>1e-3 fmax)':>24} {'(f>1e-6 fmax)':>14}")
    inner = slice(5, -5)
    e, fref = ref.energy[inner], ref.f[inner]
    for n in (100, 200, 400, 800):
        t, df = _timed(eddington_df, model.mass, n_energy=n, repeat=3)
        err = np.abs(df(e) / fref - 1)
        e3 = err[fref > 1e-3 * ref.f.max()].max()
        e6 = err[fref > 1e-6 * ref.f.max()].max()
        print(f"{n:9d} {t:9.3f} {e3:24.2e} {e6:14.2e}")
    t_all, _ = _timed(build_cluster_model, settings, repeat=2)
    print(f"full model set-up (params, mass model, DF): {t_all:.3f} s (target <= 0.5 s)")


def _jeans_error(sigma2, sampler, n, seed=1):
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    s = sampler.sample("field", rng.random((n, 4)), rng.random((n, 3)))
    t_sample = time.perf_counter() - t0
    R = np.hypot(s["x"], s["y"])
    v_rad = (s["x"] * s["vx"] + s["y"] * s["vy"]) / R
    order = np.argsort(R)
    chi2, worst = 0.0, 0.0
    bins = np.array_split(order, 20)
    for idx in bins:
        v2 = v_rad[idx] ** 2
        expect = np.mean(sigma2(R[idx]))
        err = np.std(v2, ddof=1) / np.sqrt(idx.size)
        chi2 += ((v2.mean() - expect) / err) ** 2
        worst = max(worst, abs(v2.mean() / expect - 1))
    return chi2 / len(bins), worst, t_sample


def bench_resolution(settings, n):
    print(f"\n== table resolution vs Jeans agreement ({n} field stars, 20 bins, v_R) ==")
    model = build_cluster_model(settings)
    m = model.mass
    half = arcsec_to_pc(settings.field_size / 2, model.params["distance"])
    margin = arcsec_to_pc(settings.margin, model.params["distance"])
    ref = JeansReference(m.density, m.bh_mass, m.r[0], m.r_max)
    sigma2 = sigma2_interpolator(ref, half * 1e-4, half * np.sqrt(2))
    print(
        f"{'rows':>5} {'levels':>6} {'grid':>5} {'build [s]':>9} {'sample [s]':>10} "
        f"{'chi2/dof':>8} {'max|dsig2|/sig2':>15}"
    )
    for rows, levels, grid in (
        (16, 33, 64),
        (40, 129, 128),
        (80, 257, 256),
        (160, 513, 512),
        (320, 1025, 1024),
    ):
        res = SamplerResolution(n_rows=rows, n_levels=levels, n_los=grid, n_speed=grid)
        t_build, sampler = _timed(build_field_sampler, m, model.df, half, margin, res)
        chi2, worst, t_sample = _jeans_error(sigma2, sampler, n)
        print(
            f"{rows:5d} {levels:6d} {grid:5d} {t_build:9.3f} {t_sample:10.3f} {chi2:8.2f} {worst:15.2e}"
        )
    print(
        "(statistical floor of max|dsig2|/sig2 with this many stars per bin: "
        f"~{3 * np.sqrt(2 / (n / 20)):.1e})"
    )


def bench_scaling(settings, sizes):
    print("\n== cost vs number of field stars (model prebuilt; 2 epochs) ==")
    model = build_cluster_model(settings)
    print(
        f"{'n_stars':>9} {'total rows':>10} {'simulate [s]':>12} {'write [s]':>9} {'peak [MiB]':>10}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            s = settings.replace(n_stars=n)
            tracemalloc.start()
            t_sim, (tables, attrs) = _timed(simulate_catalogue, s, 1, model)
            t_write, _ = _timed(write_catalogue, Path(tmp) / "c.h5", tables, attrs=attrs, seed=1)
            peak = tracemalloc.get_traced_memory()[1] / 2**20
            tracemalloc.stop()
            print(f"{n:9d} {len(tables['e0']):10d} {t_sim:12.2f} {t_write:9.2f} {peak:10.0f}")
            del tables


def bench_multimass(sizes):
    print('\n== multi-mass model (ngc3201-nbody, IMBH 1500, r_a 300", BH subsystem 2000) ==')
    settings = ClusterSettings(
        preset="ngc3201-nbody",
        imbh_mass=1500.0,
        anisotropy_radius=300.0,
        bh_subsystem_mass=2000.0,
    )
    t_model, model = _timed(build_cluster_model, settings)
    n_groups = len(model.params["groups"])
    print(
        f"model set-up (params, {n_groups} groups, {len(model.components)} DFs): "
        f"{t_model:.2f} s (target <= 5 s)"
    )
    print(f"{'n_stars':>9} {'objects':>9} {'simulate [s]':>12} {'peak [MiB]':>10}")
    for n in sizes:
        s = settings.replace(n_stars=n)
        tracemalloc.start()
        t_sim, (tables, _) = _timed(simulate_catalogue, s, 1, model)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        print(f"{n:9d} {len(tables['e0']):9d} {t_sim:12.2f} {peak:10.0f}")
        del tables
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**10
    print(f"process peak RSS so far: {rss:.0f} MiB (target <= 2048)")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes for development")
    parser.add_argument(
        "--multimass-only", action="store_true", help="only the multi-mass section (4)"
    )
    args = parser.parse_args(argv)
    if args.multimass_only:
        bench_multimass([10_000] if args.quick else [70_000, 700_000])
        return
    settings = ClusterSettings(imbh_mass=1500.0)
    bench_df(settings)
    bench_resolution(settings, 50_000 if args.quick else 400_000)
    bench_scaling(
        settings, [1_000, 10_000, 100_000] if args.quick else [1_000, 10_000, 100_000, 1_000_000]
    )
    bench_multimass([10_000] if args.quick else [70_000, 700_000])


if __name__ == "__main__":
    main()
