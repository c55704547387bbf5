"""Which error terms set the normalised residuals of small frames (issue 14, item 1).

Two sections, truth for scoring only (docs/measure.md, "Small frames: what the bright
bins' normalised residuals measure"; docs/propermotions.md, "PM errors on the quickstart"):

* ``quickstart DIR``: a run directory's ``products`` of ``workflows/quickstart.toml``
  (``python -m mavispm.workflows.cli run quickstart.toml --workdir W``, then
  ``W/quickstart/products``). Per V bin: each epoch's normalised residuals, the two
  epochs' measured - true difference over their reported and their Fisher errors (what
  repeats between the epochs cancels in the motion), the PM's normalised residuals and
  the transformation's share of ``pm_err^2``, and the transformation's realisation
  (fitted to the reference stars' measured - true differences) against its prediction.
* ``frames --n N --seeds S ...``: the peer benchmark's section 4c scene (``bench_measure``)
  with ``N`` stars, measured by ``measure_frame`` (frame-built ePSF); per V bin the
  normalised residuals, the error terms at the bin's median, the node registration's
  realisation (3 x 3 cell medians of the V < 20 stars) against its prediction, and the
  rest (cell medians removed, errors less the registration).

Usage::

    python benchmarks/error_shares.py quickstart W/quickstart/products
    python benchmarks/error_shares.py frames --n 2000 --seeds 0 1 2000 --work /tmp/frames
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

BINS_PM = ((14, 20), (20, 22), (22, 24), (24, 26), (26, 30))
BINS_FRAME = ((16, 18), (18, 20), (20, 22), (22, 24), (24, 25))


def rstd(v) -> float:
    """1.4826 MAD about the median of the finite values (NaN with fewer than 4)."""
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(1.4826 * np.median(np.abs(v - np.median(v)))) if v.size > 3 else np.nan


def quickstart(products: Path) -> None:
    """Per-epoch, epoch-difference and PM shares of a quickstart run's products."""
    from astropy.table import Table

    from mavispm.measure.propermotions.cli import truth_from_catalogue
    from mavispm.measure.propermotions.inputs import read_measured
    from mavispm.measure.propermotions.pipeline import _gather, derive_proper_motions
    from mavispm.measure.propermotions.settings import validate_settings

    names = sorted(p.name for p in (products / "stars" / "main").iterdir())[:2]
    paths = [products / "stars" / "main" / e / "measured.h5" for e in names]
    epochs = [read_measured(p) for p in paths]
    tables = [Table.read(p) for p in paths]
    for ep, tab in zip(epochs, tables):  # the Fisher errors, for the difference only
        ep.x_fisher = np.asarray(tab["x_err_fisher"], float)
        ep.y_fisher = np.asarray(tab["y_err_fisher"], float)
    truth = truth_from_catalogue(products / "cluster" / "catalogue.h5")
    result = derive_proper_motions(epochs, validate_settings({}), truth_pm=truth)
    match, fit = result.match, next(f for f in result.fits if f is not None)
    k_other = result.fits.index(fit)
    g = {c: _gather(epochs, match, c) for c in ("x", "y", "x_true", "y_true", "x_err", "y_err")}
    for c in ("x_fisher", "y_fisher"):
        g[c] = _gather(epochs, match, c)
    flag, mag = _gather(epochs, match, "flag"), _gather(epochs, match, "mag")[:, 0]
    e = np.stack([g["x"] - g["x_true"], g["y"] - g["y_true"]])  # (axis, star, epoch) [arcsec]
    rep = np.stack([g["x_err"], g["y_err"]])
    fis = np.stack([g["x_fisher"], g["y_fisher"]])
    both = np.all(np.isfinite(e), axis=(0, 2)) & np.all(flag == 0, axis=1)
    both &= np.all(np.isfinite(rep), axis=(0, 2))
    # the transformation's realisation: its weighted fit to the reference stars' errors
    xo, yo = (np.where(both, g[c][:, k_other], 0.0) for c in ("x", "y"))
    feats = fit.model.features(xo, yo)
    used = fit.used & both
    diff = np.nan_to_num(e[:, :, 0] - e[:, :, k_other])
    real = np.zeros_like(diff)
    for a in range(2):
        w = np.sqrt(fit.weights[used, a])
        coef = np.linalg.lstsq(feats[used] * w[:, None], diff[a, used] * w, rcond=None)[0]
        real[a] = feats @ coef
    tx, ty, _ = fit.model.position_covariance(fit.measurement_covariance, xo, yo)
    stars = result.stars
    row = {v: i for i, v in enumerate(np.asarray(match.ids))}
    k = np.array([row[v] for v in np.asarray(stars["id"])])
    col = {c: np.asarray(stars[c].value, float) for c in stars.colnames if c.startswith("pm_")}
    pm_ok = (np.asarray(stars["flag"]) == 0) & both[k]
    z = [(col[f"pm_{a}"] - col[f"pm_{a}_true"]) / col[f"pm_{a}_err"] for a in "xy"]
    dt = abs(result.epochs[k_other] - result.reference_epoch)
    # the transformation's variance over pm_err^2 (both as position variances [arcsec^2])
    share = [t[k] / (col[f"pm_{a}_err"] * dt / 1e3) ** 2 for t, a in ((tx, "x"), (ty, "y"))]
    print(f"epochs {names}; transformation {fit.model.name}, {used.sum()} reference stars")
    print("V bin  stars  per-epoch e0 / e1  diff/rep  diff/Fisher   PM   transformation share")
    for lo, hi in BINS_PM:
        s = both & (mag >= lo) & (mag < hi)
        per = [rstd((e[:, :, i] / rep[:, :, i])[:, s]) for i in (0, 1)]
        d = (e[:, :, 1] - e[:, :, 0])[:, s]
        r_rep = rstd(d / np.hypot(rep[:, s, 0], rep[:, s, 1]))
        r_fis = rstd(d / np.hypot(fis[:, s, 0], fis[:, s, 1]))
        p = pm_ok & (mag[k] >= lo) & (mag[k] < hi)
        print(
            f"{lo}-{hi}  {s.sum():5d}  {per[0]:7.2f} / {per[1]:4.2f}  {r_rep:8.2f}  {r_fis:11.2f}"
            f"  {rstd(np.r_[z[0][p], z[1][p]]):5.2f}  {np.median(np.r_[share[0][p], share[1][p]]):8.2f}"
        )
    rms = np.sqrt(np.mean(real[:, both] ** 2, axis=1)) * 1e6
    pred = np.sqrt([np.median(tx[both]), np.median(ty[both])]) * 1e6
    print(
        f"transformation realisation RMS x / y {rms[0]:.1f} / {rms[1]:.1f} microarcsec, "
        f"predicted (median) {pred[0]:.1f} / {pred[1]:.1f}"
    )


def frames(n: int, seeds: list[int], work: Path) -> None:
    """Error-term shares of ``measure_frame`` on the section 4c scene, one frame per seed."""
    import astropy.units as u
    import bench_measure as bm

    from mavispm.measure.stars.measure_frame import measure_frame, read_frame
    from mavispm.measure.stars.settings import MeasureSettings

    work.mkdir(parents=True, exist_ok=True)
    side = int(max(1000, np.sqrt(n / 3500) * 2000))
    grid = 3
    for seed in seeds:
        rng = np.random.default_rng(seed + 1)
        x, y = rng.uniform(3, side - 4, n), rng.uniform(3, side - 4, n)
        mag = rng.uniform(16, 25, n)
        path = work / f"frame{n}_{seed}.h5"
        if not path.exists():
            bm.write_frames(path, (side, side), x, y, mag, bm.PSF, det=bm.DET, seed=seed + 2)
        frame = read_frame(path)
        t0 = time.process_time()
        stars, _, _ = measure_frame(frame, MeasureSettings(perturbation=0.05), seed=5)
        cpu = time.process_time() - t0
        scale = frame.pixel_scale

        def pix(c, stars=stars, scale=scale):
            return np.asarray(stars[c].to_value(u.arcsec)) / scale

        ok = (np.asarray(stars["flag"]) & 32) == 0
        dx, dy = np.asarray(stars["x_pix"]) - x, np.asarray(stars["y_pix"]) - y
        ex, ey, fx = pix("x_err"), pix("y_err"), pix("x_err_fisher")
        rx, ry = pix("x_err_registration"), pix("y_err_registration")
        col = np.clip(x * grid // side, 0, grid - 1)
        cell = (np.clip(y * grid // side, 0, grid - 1) * grid + col).astype(int)
        bright = ok & (mag < 20)
        med = np.array(
            [[np.median(v[bright & (cell == c)]) for v in (dx, dy)] for c in range(grid * grid)]
        )
        uas = frame.pixel_scale * 1e6  # [arcsec / pixel] -> microarcsec
        print(
            f"seed {seed}: {cpu:.1f} s CPU; registration realisation (cell medians, V < 20) RMS "
            f"{np.sqrt(np.mean(med**2)) * uas:.1f} against {np.median(rx[ok]) * uas:.1f} microarcsec"
        )
        rest_x = np.sqrt(np.maximum(ex**2 - rx**2, 0.0))
        rest_y = np.sqrt(np.maximum(ey**2 - ry**2, 0.0))
        for lo, hi in BINS_FRAME:
            s = ok & (mag >= lo) & (mag < hi)
            norm = rstd(np.r_[dx[s] / ex[s], dy[s] / ey[s]])
            rest = rstd(
                np.r_[(dx - med[cell, 0])[s] / rest_x[s], (dy - med[cell, 1])[s] / rest_y[s]]
            )
            print(
                f"  V {lo}-{hi}: {s.sum():4d} stars, normalised {norm:.2f}; err / Fisher / "
                f"registration {np.median(ex[s]) * uas:.1f} / {np.median(fx[s]) * uas:.1f} / "
                f"{np.median(rx[s]) * uas:.1f} microarcsec; rest {rest:.2f}"
            )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    q = sub.add_parser("quickstart", help="a quickstart run's products folder")
    q.add_argument("products", type=Path)
    f = sub.add_parser("frames", help="section 4c frames of N stars")
    f.add_argument("--n", type=int, default=2000)
    f.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    f.add_argument("--work", type=Path, default=Path("error_shares_work"))
    args = ap.parse_args(argv)
    if args.what == "quickstart":
        quickstart(args.products)
    else:
        frames(args.n, args.seeds, args.work)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
