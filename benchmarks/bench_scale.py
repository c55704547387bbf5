"""Scale benchmark of the stars stage (issue 14, deliverable 4; docs/measure-scale.md).

Run ``python benchmarks/bench_scale.py --n 10000 30000 100000 [--work DIR]`` with the
repository on PYTHONPATH as ``mavispm``. For each N it makes (once, cached in the work
folder) the NGC 3201 preset catalogue with N stars over 30" (epoch 0), the default
optics' PSF grid and the rendered frame, then measures the frame forced with the stage
defaults and the grid as the PSF-R prior, and prints the stage times, the peak RSS of
the process so far, the failed / not-converged fractions among stars with V < 25 whose
centres lie inside the frame (those outside fail by design), and the robust scatter
over the CRLB and the robust std of the normalised residuals ``(x - x_true - offset) /
x_err`` (the frame's common offset removed) per magnitude bin, and the same fractions
by confusion class (docs/measure-scale.md, tenth pass): the stars with a comparable
neighbour (at most 1 mag fainter) within 1.5 FWHM of the frame's PSF model, and the
isolated ones per magnitude bin; and the normalised residuals of the isolated stars
within 60 px of a V < 15 star (fourteenth pass). ``--set key=json ...`` changes measure
settings (e.g. ``--set correlated_misfit=false``, ``--set threads=1``). The stage's CPU
time (``time.process_time``, all threads) is printed beside its wall time. Run each N in its own process (``/usr/bin/time -v``)
for a clean peak memory.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from mavispm.core.frame import on_detector
from mavispm.measure.stars.cli import validate_settings
from mavispm.measure.stars.confusion import effective_fwhm, nearest_comparable
from mavispm.measure.stars.measure_frame import measure_frame, read_frame


def _run(*args):
    subprocess.run([sys.executable, "-m", "mavispm.workflows.cli", *args], check=True)


def make_frame(n: int, work: Path) -> Path:
    """The catalogue, PSF grid and frame of ``n`` stars in ``work`` (made once)."""
    work.mkdir(parents=True, exist_ok=True)
    psf, cat, frame = work / "psf.h5", work / f"cat_{n}.h5", work / f"f_{n}.h5"
    if not psf.exists():
        _run("simulate", "optics", "-o", str(psf), "--quiet")
    if not cat.exists():
        _run(
            "simulate",
            "cluster",
            "-o",
            str(cat),
            "--n-stars",
            str(n),
            "--epochs",
            "0",
            "--seed",
            "1",
        )
    if not frame.exists():
        _run("simulate", "frames", str(cat), "--epoch", "e0", "-o", str(frame))
    return frame


def robust_sigma(a):
    a = a[np.isfinite(a)]
    return 1.4826 * np.median(np.abs(a - np.median(a))) if len(a) else np.nan


def psfr_grid(attrs) -> str:
    """The PSF-R correction grid of a measurement's attributes ("" without one)."""
    if not attrs.get("psfr"):
        return ""
    model = json.loads(attrs["psfr"])
    return f", PSF-R grid {model.get('grid', 3)} x {model.get('grid', 3)}"


def measure(path: Path, prior: Path, extra: dict | None = None) -> None:
    frame = read_frame(path)
    cfg = validate_settings({"psf_prior": str(prior), **(extra or {})})
    t0, c0 = time.perf_counter(), time.process_time()
    stars, attrs, psf = measure_frame(frame, cfg, 0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    ny, nx = frame.shape
    tx = np.asarray(frame.truth["x_pix"], float)
    ty = np.asarray(frame.truth["y_pix"], float)
    mag = frame.truth["mag"].value
    flag = np.asarray(stars["flag"])
    inside = on_detector(tx, ty, (ny, nx))
    sel = inside & (mag < 25)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(
        f"{path.name}: {len(tx)} stars ({inside.sum()} inside), stage {wall:.1f} s "
        f"(PSF {attrs['time_epsf'].value:.1f}, fit {attrs['time_fit'].value:.1f}, errors "
        f"{attrs['time_errors'].value:.1f}), stage CPU {cpu:.1f} s (all threads), "
        f"peak RSS {peak:.2f} GB; PSF stars "
        f"{int(attrs['n_psf_stars'])}{psfr_grid(attrs)}; V < 25 inside: "
        f"failed {np.mean(flag[sel] & 32 > 0):.2%}, not converged {np.mean(flag[sel] & 1 > 0):.2%}"
    )
    failed, unconverged = flag & 32 > 0, flag & 1 > 0
    fwhm = effective_fwhm(psf.epsf_at((nx - 1) / 2, (ny - 1) / 2), psf.oversampling)[0]
    near, _ = nearest_comparable(tx, ty, mag, 1.5 * fwhm)
    blend = sel & (near < 1.5 * fwhm)
    iso = sel & ~blend
    print(
        f"  FWHM {fwhm:.2f} px; comparable neighbour within 1.5 FWHM: {blend.mean() / sel.mean():.2%}"
        f" of them, failed / not converged {failed[blend].mean():.2%} / "
        f"{unconverged[blend].mean():.2%}; isolated {failed[iso].mean():.2%} / "
        f"{unconverged[iso].mean():.2%}, V "
        + ", ".join(
            f"{lo}-{hi} {failed[b].mean():.2%} / {unconverged[b].mean():.2%}"
            for lo, hi in ((10, 22), (22, 24), (24, 25))
            for b in [iso & (mag >= lo) & (mag < hi)]
        )
    )
    scale = frame.pixel_scale
    ok = inside & (flag & 32 == 0)
    x, y = np.asarray(stars["x_pix"]), np.asarray(stars["y_pix"])
    # the frame's common offset (the epoch alignment absorbs it), as the accuracy report
    bright = ok & (mag < 22)
    off_x, off_y = np.median(x[bright] - tx[bright]), np.median(y[bright] - ty[bright])
    x_err, y_err = stars["x_err"].value / scale, stars["y_err"].value / scale
    for lo, hi in ((17, 20), (20, 22), (22, 24), (24, 25), (25, 26)):
        b = ok & (mag >= lo) & (mag < hi)
        dx, dy = x[b] - tx[b], y[b] - ty[b]
        cx = np.median(stars["crlb_x"].value[b]) / scale
        cy = np.median(stars["crlb_y"].value[b]) / scale
        nx_, ny_ = (dx - off_x) / x_err[b], (dy - off_y) / y_err[b]
        print(f"  V {lo}-{hi}: {b.sum()} stars, scatter / CRLB x / y "
              f"{robust_sigma(dx) / cx:.2f} / {robust_sigma(dy) / cy:.2f}, "
              f"normalised residuals (robust) x / y {robust_sigma(nx_):.2f} / {robust_sigma(ny_):.2f}")  # fmt: skip
    # the isolated stars within 60 px of a V < 15 star (their errors must hold the
    # bright stars' model misfit; docs/measure-scale.md, fourteenth pass)
    bright15 = mag < 15
    near_bright = np.zeros(len(tx), bool)
    if bright15.any():
        d, _ = cKDTree(np.column_stack([tx[bright15], ty[bright15]])).query(
            np.column_stack([tx, ty]), k=2
        )
        # a V < 15 star's own nearest is itself: take the next
        near_bright = np.where(bright15, d[:, 1], d[:, 0]) < 60
    nb = ok & iso & near_bright
    print(
        f"  isolated within 60 px of a V < 15 star ({nb.sum() / max(iso.sum(), 1):.1%} of the "
        "isolated), normalised residuals x / y: "
        + ", ".join(
            f"V {lo}-{hi} ({b.sum()}) {robust_sigma((x[b] - tx[b] - off_x) / x_err[b]):.2f} / "
            f"{robust_sigma((y[b] - ty[b] - off_y) / y_err[b]):.2f}"
            for lo, hi in ((17, 20), (20, 22), (22, 24), (24, 25))
            for b in [nb & (mag >= lo) & (mag < hi)]
        )
    )


def add_set_option(ap: argparse.ArgumentParser) -> None:
    """The ``--set key=json ...`` option: measure settings beside the defaults."""
    ap.add_argument(
        "--set",
        nargs="*",
        default=[],
        metavar="KEY=JSON",
        help="measure settings beside the defaults, e.g. correlated_misfit=false",
    )


def set_settings(items: list[str]) -> dict:
    """The settings of ``--set`` items ``key=json``."""
    return {k: json.loads(v) for k, v in (item.split("=", 1) for item in items)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, nargs="+", default=[10000, 30000, 100000])
    ap.add_argument("--work", type=Path, default=Path("bench_scale_work"))
    add_set_option(ap)
    args = ap.parse_args(argv)
    extra = set_settings(args.set)
    for n in args.n:
        measure(make_frame(n, args.work), args.work / "psf.h5", extra)


if __name__ == "__main__":
    main()
