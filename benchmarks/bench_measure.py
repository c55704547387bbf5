"""Benchmark of the measure stage: fit time against astrometric error and star count.

Run ``python benchmarks/bench_measure.py [--quick]`` (with the repository's
``.dev`` folder on PYTHONPATH). Prints

1. time against astrometric error (robust sigma of (measured - true) / CRLB for
   stars brighter than m = 22) for the stamp radius, the number of iterations
   and the ePSF grid density;
2. ePSF grid building time;
3. fit time and peak extra memory (tracemalloc) against the number of stars
   for the batched engine with a field-variable (3 x 3 gridded) ePSF;
4. peers, in the same run on the same frames, against the installed photutils
   (``--only-peers`` runs 4, 4b and 4c only): the fit alone, ours (the stage's knobs,
   and a constant sky) against plain photutils ``PSFPhotometry`` (LevMar and default
   TRF fitters, no grouper, no local background, the same true ePSF and starting
   positions, 11 x 11 stamps) at 3,500 and 10,000 stars: wall and process CPU time,
   MAD / CRLB per magnitude bin, and the normalised residuals with each engine's
   own errors; 4b. the ePSF builders (ours, photutils ``EPSFBuilder``) on the same
   PSF stars of a field-constant frame, each ePSF used by our fitter; 4c. the
   whole process from the frame in memory: our ``measure_frame`` against a
   photutils script (``EPSFBuilder`` ePSFs, 3 x 3 or one, then ``PSFPhotometry``);
5. the whole stage (``measure_frame``: ePSF with the two half-set ePSFs of the
   error model, fit, errors) on frames with a truth table: times, and the
   normalised residuals (measured - true) / error per magnitude bin with the
   Fisher errors and with the reported errors (std; robust sigma). A crowded
   Moffat frame of the synthesiser by default; ``--frames F.h5 ...`` adds
   frames products (e.g. the NGC 3201 workflow's) measured with
   ``--grid`` (3) x ``--grid`` gridded ePSFs; ``--only-stage`` runs this section only.

Frames come from the independent synthesiser of the tests (Gaussian PSF whose
width varies by +-20 % over the field, 2 x 2 pixel-scale FWHM ~ 2.8 px).
"""

from __future__ import annotations

import argparse
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from measure_helpers import (  # noqa: E402
    Detector,
    SynthPSF,
    mag_to_flux,
    noisy_frame,
    normalised_residuals,
    render_image,
    robust_sigma,
    true_epsf,
    write_frames,
)

from mavispm.measure.stars.batched_fit import FitOptions, fit_stars  # noqa: E402
from mavispm.measure.stars.crlb import crlb  # noqa: E402
from mavispm.measure.stars.epsf import EPSFOptions, build_field_epsf  # noqa: E402
from mavispm.measure.stars.measure_frame import box_flux, fit_options  # noqa: E402
from mavispm.measure.stars.settings import MeasureSettings  # noqa: E402

PSF = SynthPSF(1.2, gradient=0.2)
DET = Detector(saturation=1e9)
RN2 = DET.read_noise**2 * DET.nexp


def make_frame(n, size, seed=0):
    """A frame of ``n`` stars (m = 16..25, uniform) on ``size`` x ``size`` pixels."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(3, size - 4, n), rng.uniform(3, size - 4, n)
    mag = rng.uniform(16, 25, n)
    flux = mag_to_flux(mag)
    image, sat = noisy_frame(render_image((size, size), x, y, flux, PSF), DET, rng)
    start_x, start_y = x + rng.normal(0, 0.05, n), y + rng.normal(0, 0.05, n)
    return dict(
        image=image.astype(float) * DET.gain,
        sat=sat,
        x=x,
        y=y,
        mag=mag,
        flux=flux,
        x0=start_x,
        y0=start_y,
    )


def accuracy(frame, res, epsf_true, radius=5):
    """Robust sigma of (measured - true) / CRLB for m < 22 stars, and the bias."""
    sel = (frame["mag"] < 22) & ((res.flag & 32) == 0)
    bound = crlb(
        epsf_true, frame["x"][sel], frame["y"][sel], frame["flux"][sel], DET.sky, RN2, radius
    )
    z = np.r_[
        (res.x[sel] - frame["x"][sel]) / bound[:, 0], (res.y[sel] - frame["y"][sel]) / bound[:, 1]
    ]
    return robust_sigma(z), np.median(z)


def timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t0


def fit_fast(frame, epsf, options=None, **opts):
    """Our batched fit of a frame from its start positions (``options``, else
    :class:`FitOptions` with ``opts``)."""
    return fit_stars(
        frame["image"], epsf, frame["x0"], frame["y0"], read_noise_var=RN2, sky0=DET.sky,
        saturated=frame["sat"], options=options or FitOptions(**opts),
    )  # fmt: skip


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smaller frames and star counts")
    ap.add_argument("--frames", nargs="*", default=[], help="frames products for section 5")
    ap.add_argument("--grid", type=int, default=3, help="ePSF grid of the --frames runs")
    ap.add_argument("--only-stage", action="store_true", help="run section 5 only")
    ap.add_argument("--only-peers", action="store_true", help="run section 4 only")
    args = ap.parse_args(argv)
    if args.only_peers:
        peer_section(args, {})
        return 0
    if args.only_stage:
        return stage_section(args)
    size = 1000 if args.quick else 2000
    n_knobs = 1000 if args.quick else 3500
    counts = [1000, 3500] if args.quick else [1000, 3500, 10000]

    frame = make_frame(n_knobs, size, seed=1)
    shape = frame["image"].shape
    grid_true = true_epsf(PSF, shape, grid=5, size=21)
    print(f"# frame {size}x{size} px, {n_knobs} stars, PSF sigma 1.2 px +-20 %")
    print("\n## 1. time vs astrometric error (robust sigma of error/CRLB, m < 22; 1.0 = CRLB)")
    print(f"{'knob':<22}{'value':>8}{'fit time [s]':>14}{'sigma/CRLB':>12}{'bias/CRLB':>11}")
    for radius in (3, 4, 5, 7):
        res, t = timed(fit_fast, frame, grid_true, radius=radius)
        s, b = accuracy(frame, res, grid_true, radius)
        print(f"{'stamp radius [px]':<22}{radius:>8}{t:>14.2f}{s:>12.2f}{b:>11.2f}")
    for iters in (1, 2, 4, 10):
        res, t = timed(fit_fast, frame, grid_true, iterations=iters)
        s, b = accuracy(frame, res, grid_true)
        print(f"{'iterations':<22}{iters:>8}{t:>14.2f}{s:>12.2f}{b:>11.2f}")
    for grid in (1, 2, 3, 5):
        epsf = true_epsf(PSF, shape, grid=grid, size=21)
        res, t = timed(fit_fast, frame, epsf)
        s, b = accuracy(frame, res, grid_true)
        print(f"{'true ePSF grid':<22}{grid:>8}{t:>14.2f}{s:>12.2f}{b:>11.2f}")

    print("\n## 2. ePSF building from the frame (fast builder) and fit with it")
    noise = DET.sky + RN2
    box = frame["flux"]  # selection only; the builder measures fluxes itself
    cases = [(v, g, 4) for v, g in (("constant", 1), ("grid", 3), ("grid", 5), ("polynomial", 3))]
    cases += [("constant", 1, 2), ("grid", 3, 2)]  # oversampling 2: fewer phase bins to fill
    for variation, grid, over in cases:
        opts = EPSFOptions(
            variation=variation, grid=grid, size=21, stars_per_node=150, min_snr=100,
            oversampling=over,
        )  # fmt: skip
        (epsf, used), t_build = timed(
            build_field_epsf,
            frame["image"] - DET.sky,
            frame["x0"],
            frame["y0"],
            box,
            frame["sat"],
            noise,
            opts,
        )
        res, t = timed(fit_fast, frame, epsf)
        s, b = accuracy(frame, res, grid_true)
        print(
            f"{variation:<11} grid {grid} x{over}: build {t_build:6.2f} s ({len(used)} PSF stars), "
            f"fit {t:5.2f} s, sigma/CRLB {s:6.2f}, bias/CRLB {b:6.2f}"
        )

    print("\n## 3. batched engine: cost vs number of stars (3x3 gridded ePSF, 10 iterations)")
    print(f"{'stars':>8}{'frame':>12}{'fit [s]':>10}{'peak extra MB':>15}{'sigma/CRLB':>12}")
    frames: dict = {}
    for n in counts:
        side = int(max(size, np.sqrt(n / 3500) * 2000))
        fr = make_frame(n, side, seed=n)
        frames[n] = fr
        epsf = true_epsf(PSF, fr["image"].shape, grid=3, size=21)
        tracemalloc.start()
        res, t = timed(fit_fast, fr, epsf)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
        s, _ = accuracy(fr, res, true_epsf(PSF, fr["image"].shape, grid=5, size=21))
        print(f"{n:>8}{side:>7}x{side:<4}{t:>10.2f}{peak:>15.1f}{s:>12.2f}")

    peer_section(args, frames)
    return stage_section(args)


#: Magnitude bins of the peer comparison (MAD / CRLB per bin).
PEER_BINS = ((16, 18), (18, 20), (20, 22), (22, 24), (24, 25))

#: The stage's fitter knobs (``[measure.knobs]`` defaults: a sky plane per star,
#: relative tolerance 0.2), as ``mavispm measure stars`` runs the fit.
STAGE_FIT = fit_options(MeasureSettings())


def _peer_ok(x, y, flag):
    return ((flag & 32) == 0) & np.isfinite(x) & np.isfinite(y)


def _bins(frame):
    for lo, hi in PEER_BINS:
        yield (frame["mag"] >= lo) & (frame["mag"] < hi)


def mad_over_crlb(frame, x, y, flag, epsf_true, radius=5):
    """Robust sigma (1.4826 MAD) of (measured - true) / CRLB per :data:`PEER_BINS` bin,
    x and y pooled; stars flagged failed (32) or non-finite are left out."""
    ok = _peer_ok(x, y, flag)
    bound = crlb(epsf_true, frame["x"], frame["y"], frame["flux"], DET.sky, RN2, radius)
    out = []
    for s in _bins(frame):
        s = s & ok
        z = np.r_[(x[s] - frame["x"][s]) / bound[s, 0], (y[s] - frame["y"][s]) / bound[s, 1]]
        out.append(robust_sigma(z) if z.size >= 6 else np.nan)
    return out


def error_honesty(frame, x, y, x_err, y_err, flag):
    """Honesty of the reported errors and gross failures, x and y pooled.

    Returns (per :data:`PEER_BINS` bin, (robust sigma, std) of (measured - true) /
    reported error: 1 for honest errors), the fraction of all stars beyond 5
    reported sigma, and the fraction more than 0.5 pixel from the truth (a fit
    caught by a neighbour); failed (32) or non-finite stars are left out of the
    first two and counted in the last."""
    ok = _peer_ok(x, y, flag) & np.isfinite(x_err) & np.isfinite(y_err) & (x_err > 0)
    zx, zy = (x - frame["x"]) / x_err, (y - frame["y"]) / y_err
    per_bin = []
    for s in _bins(frame):
        z = np.r_[zx[s & ok], zy[s & ok]]
        per_bin.append((robust_sigma(z), np.std(z)) if z.size >= 6 else (np.nan, np.nan))
    beyond = np.mean(np.hypot(zx[ok], zy[ok]) > 5)
    off = np.hypot(x - frame["x"], y - frame["y"])
    lost = np.mean(~_peer_ok(x, y, flag) | ~(off <= 0.5))
    return per_bin, beyond, lost


def plain_photutils(frame, epsf, fitter: str):
    """Plain photutils ``PSFPhotometry``: no grouper, no local background (the known
    sky is subtracted), the ePSF ``epsf`` handed over as a ``GriddedPSFModel``
    (``ImagePSF`` when constant), 11 x 11 fit stamps, the same starting positions;
    ``fitter`` "levmar" (``LevMarLSQFitter``) or "default" (``TRFLSQFitter``).
    Returns x, y, x_err, y_err [pixel] and flags (32: failed)."""
    import warnings

    from astropy.modeling.fitting import LevMarLSQFitter, TRFLSQFitter
    from astropy.table import QTable
    from photutils.psf import PSFPhotometry

    from mavispm.measure.stars.photutils_engine import to_photutils_model

    data = frame["image"] - DET.sky
    err = np.sqrt(np.maximum(frame["image"], DET.sky) + RN2)
    phot = PSFPhotometry(
        to_photutils_model(epsf, data.shape),
        (11, 11),
        fitter=LevMarLSQFitter() if fitter == "levmar" else TRFLSQFitter(),
        aperture_radius=3.0,
    )
    init = QTable({"x": frame["x0"], "y": frame["y0"]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = phot(data, mask=frame["sat"], error=err, init_params=init)

    def col(name):
        if name not in table.colnames:
            return np.full(len(table), np.nan)
        return np.asarray(getattr(table[name], "value", table[name]), float)

    x, y = col("x_fit"), col("y_fit")
    flag = np.where(np.isfinite(x) & (col("flux_fit") > 0), 0, 32)
    return x, y, col("x_err"), col("y_err"), flag


def timed_cpu(fn, *args, **kw):
    """Result, wall time [s] and process CPU time [s] (all threads) of a call."""
    w0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args, **kw)
    return out, time.perf_counter() - w0, time.process_time() - c0


def warm_up() -> None:
    """One small fit with each engine before anything is timed: numba loads (or, on a
    fresh checkout, compiles) its kernels and astropy/photutils import their modules
    on the first call; neither is part of a fit's cost."""
    fr = make_frame(60, 200, seed=99)
    epsf = true_epsf(PSF, fr["image"].shape, grid=3, size=21)
    fit_fast(fr, epsf)
    fit_fast(fr, epsf, options=STAGE_FIT)
    for fitter in ("levmar", "default"):
        plain_photutils(fr, epsf, fitter)


def _print_peer_rows(n, rows) -> None:
    """Rows (name, wall, CPU, CPU reference, MAD/CRLB per bin) of a peer table."""
    for name, w, c, c_ref, mad in rows:
        cells = "".join(f"{m:8.2f}" for m in mad)
        print(f"{n:>6} {name:<34}{w:9.1f}{c:9.1f}{c / c_ref:8.1f}  {cells}")


def _print_honesty(rows) -> None:
    head = "".join(f"{f'{lo}-{hi}':>12}" for lo, hi in PEER_BINS)
    print("   normalised residuals (measured - true) / reported error, robust/std per V bin;")
    print("   fraction of stars beyond 5 reported sigma; fraction failed or > 0.5 px off:")
    print(f"{'':>6} {'':<34}{head}{'> 5 sig':>9}{'> 0.5px':>9}")
    for n, name, (per_bin, beyond, lost) in rows:
        cells = "".join(f"{f'{r:.2f}/{s:.2f}':>12}" for r, s in per_bin)
        print(f"{n:>6} {name:<34}{cells}{beyond:9.2%}{lost:9.2%}")


def peer_section(args, frames: dict) -> None:
    """Section 4: honest peer comparison on the same frames, in one run.

    4. fit only: our batched fitter (the stage's knobs, and a constant sky) against
       plain photutils ``PSFPhotometry`` (LevMar and the default TRF fitter, no
       grouper, the same 3 x 3 gridded true ePSF and starting positions, 11 x 11
       stamps): time, MAD / CRLB and normalised residuals per magnitude bin;
    4b. the ePSF builders on the same PSF stars of a field-constant frame (ours and
       photutils' ``EPSFBuilder``), each ePSF used by our fitter;
    4c. whole process from the frame in memory: our ``measure_frame`` (ePSF with a
       neighbour pass and the half-set ePSFs of the error model, fit, errors,
       truth match) against a photutils script (``EPSFBuilder`` on the same PSF
       stars per node of the same 3 x 3 grid, ``GriddedPSFModel``, plain
       ``PSFPhotometry``).
    """
    warm_up()
    counts = [1000] if args.quick else [3500, 10000]
    head = "".join(f"{f'{lo}-{hi}':>8}" for lo, hi in PEER_BINS)
    print("\n## 4. peers, fit only, same frames: plain photutils PSFPhotometry (no grouper)")
    print("   (the same 3 x 3 gridded true ePSF and start positions; CPU = process time)")
    print(
        f"{'stars':>6} {'engine':<34}{'wall [s]':>9}{'CPU [s]':>9}{'x ours':>8}  MAD/CRLB per V bin:"
    )
    print(f"{'':>6} {'':<34}{'':>9}{'':>9}{'(CPU)':>8}  {head}")
    honesty = []
    for n in counts:
        side = int(max(1000, np.sqrt(n / 3500) * 2000))
        fr = frames.get(n) or make_frame(n, side, seed=n)
        epsf = true_epsf(PSF, fr["image"].shape, grid=3, size=21)
        ref = true_epsf(PSF, fr["image"].shape, grid=5, size=21)
        ours = []
        for name, opts in (("mavispm (stage knobs)", STAGE_FIT), ("mavispm (constant sky)", None)):
            res, w, c = timed_cpu(fit_fast, fr, epsf, options=opts)
            ours.append((name, w, c, res))
        c_ref = ours[0][2]
        rows = []
        for name, w, c, res in ours:
            rows.append((name, w, c, c_ref, mad_over_crlb(fr, res.x, res.y, res.flag, ref)))
            honesty.append(
                (n, name, error_honesty(fr, res.x, res.y, res.x_err, res.y_err, res.flag))
            )
        for fitter in ("levmar", "default"):
            (x, y, xe, ye, flag), w, c = timed_cpu(plain_photutils, fr, epsf, fitter)
            name = f"photutils {'LevMar' if fitter == 'levmar' else 'TRF (default)'}"
            rows.append((name, w, c, c_ref, mad_over_crlb(fr, x, y, flag, ref)))
            honesty.append((n, name, error_honesty(fr, x, y, xe, ye, flag)))
        _print_peer_rows(n, rows)
    _print_honesty(honesty)
    builder_section(args)
    whole_process_section(args)


def builder_section(args) -> None:
    """Section 4b: the ePSF builders on the same PSF stars (field-constant PSF)."""
    head = "".join(f"{f'{lo}-{hi}':>8}" for lo, hi in PEER_BINS)
    print("\n## 4b. ePSF builders on the same PSF stars (field-constant PSF), our fitter")
    n, side = (1000, 1000) if args.quick else (3500, 2000)
    flat = SynthPSF(1.2, gradient=0.0)
    rng = np.random.default_rng(11)
    x, y = rng.uniform(3, side - 4, n), rng.uniform(3, side - 4, n)
    mag = rng.uniform(16, 25, n)
    flux = mag_to_flux(mag)
    image, sat = noisy_frame(render_image((side, side), x, y, flux, flat), DET, rng)
    fr = dict(
        image=image.astype(float) * DET.gain, sat=sat, x=x, y=y, mag=mag, flux=flux,
        x0=x + rng.normal(0, 0.05, n), y0=y + rng.normal(0, 0.05, n),
    )  # fmt: skip
    ref = true_epsf(flat, (side, side), grid=1, size=21)
    print(
        f"{'builder':<22}{'stars':>6}{'wall [s]':>9}{'CPU [s]':>9}{'misfit':>9}"
        "  MAD/CRLB per V bin (misfit: rms of ePSF - true ePSF over its peak)"
    )
    print(f"{'':<22}{'':>6}{'':>9}{'':>9}{'':>9}  {head}")
    common = dict(variation="constant", grid=1, size=21, stars_per_node=150, min_snr=100)
    for builder in ("fast", "photutils"):
        opts = EPSFOptions(builder=builder, oversampling=4, **common)
        (epsf, used), w, c = timed_cpu(
            build_field_epsf, fr["image"] - DET.sky, fr["x0"], fr["y0"], fr["flux"], fr["sat"],
            DET.sky + RN2, opts,
        )  # fmt: skip
        res = fit_fast(fr, epsf, options=STAGE_FIT)
        cells = "".join(f"{m:8.2f}" for m in mad_over_crlb(fr, res.x, res.y, res.flag, ref))
        name = "mavispm (fast)" if builder == "fast" else "photutils EPSFBuilder"
        truth = ref.basis[0]
        misfit = np.sqrt(np.mean((epsf.basis[0] - truth) ** 2)) / truth.max()
        print(f"{name:<22}{len(used):>6}{w:9.1f}{c:9.1f}{misfit:9.5f}  {cells}")


def photutils_process(frame, x0, y0, grid=3, fitters=("levmar", "default")):
    """A photutils script from the frame in memory: one ``EPSFBuilder`` ePSF per node
    of a ``grid`` x ``grid`` grid (1: one ePSF), from the PSF stars our first pass
    picks per node (isolated, SNR > 100, at most 150), handed to plain
    ``PSFPhotometry`` (no grouper, the known sky subtracted) as a
    ``GriddedPSFModel`` (``ImagePSF``), from the same start positions.

    Returns the ePSF build's (wall, CPU) [s], the number of PSF stars, and per fitter
    ((x, y, x_err, y_err, flag), wall, CPU)."""
    fr = dict(image=frame.image, sat=frame.bad, x0=x0, y0=y0)
    opts = EPSFOptions(
        variation="grid" if grid > 1 else "constant", grid=grid, size=25, oversampling=4,
        builder="photutils",
        stars_per_node=150, min_snr=100.0,
    )  # fmt: skip

    def build():
        return build_field_epsf(
            frame.image - frame.sky, x0, y0, box_flux(frame, x0, y0), frame.bad,
            frame.sky + frame.read_noise_var, opts,
        )  # fmt: skip

    (epsf, used), w_b, c_b = timed_cpu(build)
    fits = {f: timed_cpu(plain_photutils, fr, epsf, f) for f in fitters}
    return (w_b, c_b), len(used), fits


def whole_process_section(args) -> None:
    """Section 4c: our whole measure stage against a photutils script (see
    :func:`photutils_process`), on the same frames, from the same start positions."""
    import tempfile

    import astropy.units as u

    from mavispm.measure.stars.measure_frame import measure_frame, read_frame, starting_positions

    head = "".join(f"{f'{lo}-{hi}':>8}" for lo, hi in PEER_BINS)
    print("\n## 4c. whole process from the frame in memory: ePSF from the frame + fit")
    print("   ours: measure_frame, default settings (3 x 3 gridded ePSF, one neighbour pass,")
    print("   half-set ePSFs of the error model, truth match); photutils: EPSFBuilder per node")
    print("   on the same PSF stars + plain PSFPhotometry; starts perturbed by 0.05 px")
    print(
        f"{'stars':>6} {'process':<34}{'wall [s]':>9}{'CPU [s]':>9}{'x ours':>8}  MAD/CRLB per V bin:"
    )
    print(f"{'':>6} {'':<34}{'':>9}{'':>9}{'(CPU)':>8}  {head}")
    settings = MeasureSettings(perturbation=0.05)
    honesty = []
    counts = [1000] if args.quick else [3500, 10000]
    with tempfile.TemporaryDirectory() as tmp:
        for n in counts:
            side = int(max(1000, np.sqrt(n / 3500) * 2000))
            rng = np.random.default_rng(n + 1)
            x, y = rng.uniform(3, side - 4, n), rng.uniform(3, side - 4, n)
            mag = rng.uniform(16, 25, n)
            path = Path(tmp) / f"frame{n}.h5"
            write_frames(path, (side, side), x, y, mag, PSF, det=DET, seed=n + 2)
            frame = read_frame(path)
            truth = dict(x=x, y=y, mag=mag, flux=mag_to_flux(mag))
            ref = true_epsf(PSF, (side, side), grid=5, size=21)
            (stars, attrs, _), w, c = timed_cpu(measure_frame, frame, settings, seed=5)
            x0, y0 = starting_positions(frame, settings, np.random.default_rng(5))
            scale = frame.pixel_scale
            sx, sy = np.asarray(stars["x_pix"]), np.asarray(stars["y_pix"])
            sflag = np.asarray(stars["flag"])
            xe = stars["x_err"].to_value(u.arcsec) / scale
            ye = stars["y_err"].to_value(u.arcsec) / scale
            rows = [("mavispm measure_frame", w, c, c, mad_over_crlb(truth, sx, sy, sflag, ref))]
            honesty.append(
                (n, "mavispm measure_frame", error_honesty(truth, sx, sy, xe, ye, sflag))
            )
            notes = []
            for grid, fitters in ((3, ("levmar", "default")), (1, ("levmar",))):
                (w_b, c_b), n_psf, fits = photutils_process(frame, x0, y0, grid, fitters)
                notes.append(f"{grid}x{grid} {w_b:.1f} s wall / {c_b:.1f} s CPU, {n_psf} stars")
                for fitter, ((px, py, pxe, pye, pflag), w_f, c_f) in fits.items():
                    fit_name = "LevMar" if fitter == "levmar" else "TRF"
                    name = f"photutils {fit_name}, EPSFBuilder {grid}x{grid}"
                    mad = mad_over_crlb(truth, px, py, pflag, ref)
                    rows.append((name, w_b + w_f, c_b + c_f, c, mad))
                    honesty.append((n, name, error_honesty(truth, px, py, pxe, pye, pflag)))
            _print_peer_rows(n, rows)
            print(
                f"{'':>6} ours: ePSF {attrs['time_epsf'].value:.1f} s, fit "
                f"{attrs['time_fit'].value:.1f} s, errors {attrs['time_errors'].value:.1f} s "
                f"(wall), {attrs['n_psf_stars']} PSF stars; EPSFBuilder " + "; ".join(notes)
            )
    _print_honesty(honesty)


def print_centre_residuals(frame, stars, centre_fraction: float = 0.15) -> None:
    """Robust offset from the truth [mas] of the m < 21 stars near the frame centre
    (within ``centre_fraction`` of the frame side: the cluster core of the NGC 3201
    frames) and outside, with the fraction beyond 3 reported sigma."""
    ny, nx = frame.shape
    scale = frame.pixel_scale * 1000.0
    dx = (np.asarray(stars["x_pix"]) - np.asarray(frame.truth["x_pix"])) * scale
    dy = (np.asarray(stars["y_pix"]) - np.asarray(frame.truth["y_pix"])) * scale
    r = np.hypot(frame.truth["x_pix"] - (nx - 1) / 2, frame.truth["y_pix"] - (ny - 1) / 2)
    ok = (stars["mag"].value < 21) & ((np.asarray(stars["flag"]) & 48) == 0)
    ok &= np.isfinite(stars["x_err"])
    for name, region in (
        ("centre", r < centre_fraction * nx),
        ("outside", r >= centre_fraction * nx),
    ):
        sel = ok & region
        if sel.sum() < 3:
            continue
        err = stars["x_err"][sel].to_value("mas")
        z = np.r_[dx[sel] / err, dy[sel] / stars["y_err"][sel].to_value("mas")]
        print(
            f"   m < 21 {name:8s} n {sel.sum():5d}  robust offset "
            f"{robust_sigma(np.r_[dx[sel], dy[sel]]):.3f} mas, beyond 3 sigma {np.mean(np.abs(z) > 3):.1%}"
        )


def stage_section(args) -> int:
    """Section 5: the whole stage, timings and normalised residuals per magnitude bin."""
    import tempfile

    from mavispm.measure.stars.cli import validate_settings
    from mavispm.measure.stars.measure_frame import measure_frame, read_frame

    print("\n## 5. whole stage: times and normalised residuals (Fisher errors -> reported)")
    runs = []
    with tempfile.TemporaryDirectory() as tmp:
        rng = np.random.default_rng(7)
        n, side = (300, 300) if args.quick else (1200, 600)
        x, y = rng.uniform(6, side - 6, n), rng.uniform(6, side - 6, n)
        mag = 16 + 10 * rng.uniform(0, 1, n) ** 0.6
        synth = Path(tmp) / "synth.h5"
        write_frames(synth, (side, side), x, y, mag, SynthPSF(1.3, 0.25, "moffat"), seed=3)
        small = {"psf_grid": 2, "psf_stars_per_node": 25, "psf_star_min_snr": 50.0}
        runs.append((f"synthetic Moffat {side} px, x4", synth, {**small, "oversampling": 4}))
        runs.append((f"synthetic Moffat {side} px, auto", synth, small))
        for path in args.frames:
            runs.append((Path(path).parent.name, path, {"psf_grid": args.grid}))
        for name, path, cfg in runs:
            frame = read_frame(path)
            stars, attrs, psf = measure_frame(frame, validate_settings(cfg), seed=1)
            print(
                f"{name}: {len(stars)} stars, {attrs['n_psf_stars']} PSF stars, "
                f"x{psf.oversampling}, ePSF {attrs['time_epsf'].value:.2f} s, "
                f"fit {attrs['time_fit'].value:.2f} s, errors {attrs['time_errors'].value:.2f} s, "
                f"sigma_ePSF {attrs['epsf_position_error'].to_value('mas'):.4f} mas"
            )
            print_centre_residuals(frame, stars)
            fisher = normalised_residuals(stars, "x_err_fisher")
            honest = normalised_residuals(stars, "x_err")
            for (lo, hi), z in honest.items():
                f = fisher[(lo, hi)]
                if len(z) < 6:
                    continue
                print(
                    f"   m {lo:5.1f}-{hi:<5.1f} n {len(z) // 2:5d}  std {np.std(f):8.2f} -> "
                    f"{np.std(z):5.2f}   robust {robust_sigma(f):7.2f} -> {robust_sigma(z):5.2f}"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
