"""Oracle fits of the scale frame: how far below 1 % a perfect model could take the fit
(issue 14, deliverable 4; docs/measure-scale.md, thirty-first pass).

Run ``python benchmarks/bench_scale_oracles.py [--n 100000] [--work DIR] [--set
key=json ...]`` with the repository on PYTHONPATH as ``mavispm`` (the frame of
``bench_scale.py``, made once and cached in the same work folder; ``--set`` changes
measure settings, e.g. ``--set iterations=160``). The PSF is built once on the frame, as the stage builds
it (forced from the input list, the optics' PSF grid as the PSF-R prior); then the fit
(the stage's ``run_engine`` with the stage defaults) runs four times:

* ``stage``: the frame as it is (the stage's own flags);
* ``bright light exact``: the frame less a noise-free render of its ``--bright-mag``
  stars alone (the truth of their light, which no observer has; their photon noise
  stays in the frame);
* ``faint held at input``: the stars fainter than ``--faint-mag`` held at their input
  positions (``fit_stars(hold_positions=...)``; the input list is the truth at this
  epoch), their fluxes fitted;
* both.

It prints the failed (32) / not converged (1) fractions and their union among the stars
with ``--bright-mag`` <= V < 25 whose centres lie inside the frame (the subtracted stars
themselves are left out of every row, so the rows compare), split into the stars with a
comparable neighbour (at most 1 mag fainter) within 1.5 FWHM and the isolated ones, and
into those within / beyond 60 px of a ``--bright-mag`` star, and the isolated ones beyond. The truth is used to build
the oracles and to score, never by the stage itself.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import astropy.units as u
import numpy as np
from bench_scale import add_set_option, make_frame, set_settings
from scipy.spatial import cKDTree

from mavispm.core.catalogue import read_catalogue
from mavispm.core.frame import on_detector
from mavispm.measure.stars.cli import validate_settings
from mavispm.measure.stars.confusion import effective_fwhm, nearest_comparable
from mavispm.measure.stars.measure_frame import (
    build_psf,
    read_frame,
    run_engine,
    starting_positions,
)
from mavispm.simulate.render.cli import build_scene_optics, epoch_rng, scene_from_mapping
from mavispm.simulate.render.frame import render_stack

#: Radius [pixel] of the bright stars' neighbourhood (the halo model's ``halo_radius``).
NEAR_BRIGHT = 60.0


def bright_light(n: int, work: Path, bright_mag: float) -> np.ndarray:
    """Noise-free light [electron] of the catalogue's stars brighter than ``bright_mag``,
    rendered alone with the scene defaults of ``bench_scale.make_frame`` (cached)."""
    path = work / f"bright_light_{n}_{bright_mag:g}.npy"
    if path.exists():
        return np.load(path)
    table = read_catalogue(work / f"cat_{n}.h5").epochs["e0"]
    stars = table[np.asarray(u.Quantity(table["mag"], u.mag).value) < bright_mag]
    scene = scene_from_mapping({})
    optics = build_scene_optics(scene, None, False)
    epoch = u.Quantity(table.meta["epoch"], u.yr)
    with_stars = render_stack(stars, epoch, scene, optics, epoch_rng(1, "e0")).noiseless
    without = render_stack(stars[:0], epoch, scene, optics, epoch_rng(1, "e0")).noiseless
    light = (with_stars - without).astype(np.float32)
    np.save(path, light)
    return light


def fractions(flag, sel) -> str:
    failed, unconverged = flag[sel] & 32 > 0, flag[sel] & 1 > 0
    return f"{failed.mean():.2%} / {unconverged.mean():.2%} ({(failed | unconverged).mean():.2%})"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=100000)
    ap.add_argument("--work", type=Path, default=Path("bench_scale_work"))
    ap.add_argument("--bright-mag", type=float, default=15.0)
    ap.add_argument("--faint-mag", type=float, default=25.0)
    add_set_option(ap)
    args = ap.parse_args(argv)
    extra = set_settings(args.set)
    path = make_frame(args.n, args.work)
    frame = read_frame(path)
    settings = validate_settings({"psf_prior": str(args.work / "psf.h5"), **extra})
    x0, y0 = starting_positions(frame, settings, np.random.default_rng(0))
    t0 = time.perf_counter()
    frame_psf = build_psf(frame, x0, y0, settings)
    print(f"{path.name}: PSF built once in {time.perf_counter() - t0:.1f} s")
    ny, nx = frame.shape
    tx, ty = np.asarray(frame.truth["x_pix"], float), np.asarray(frame.truth["y_pix"], float)
    mag = frame.truth["mag"].value
    sel = on_detector(tx, ty, (ny, nx)) & (mag < 25) & (mag >= args.bright_mag)
    fwhm = effective_fwhm(
        frame_psf.psf.epsf_at((nx - 1) / 2, (ny - 1) / 2), frame_psf.psf.oversampling
    )[0]
    near, _ = nearest_comparable(tx, ty, mag, 1.5 * fwhm)
    blend = near < 1.5 * fwhm
    bright = mag < args.bright_mag
    tree = cKDTree(np.column_stack([tx[bright], ty[bright]]))
    d_bright = tree.query(np.column_stack([tx, ty]))[0]
    close = d_bright < NEAR_BRIGHT
    print(
        f"  {sel.sum()} stars with {args.bright_mag:g} <= V < 25 inside: "
        f"{(sel & blend).sum() / sel.sum():.1%} with a comparable neighbour within 1.5 FWHM "
        f"({fwhm:.2f} px), {(sel & close).sum() / sel.sum():.1%} within {NEAR_BRIGHT:g} px of a "
        f"V < {args.bright_mag:g} star"
    )
    light = bright_light(args.n, args.work, args.bright_mag)
    faint = mag > args.faint_mag
    print(
        "  failed / not converged (union): all | blends | isolated | within "
        f"{NEAR_BRIGHT:g} px of a bright star | beyond | isolated beyond"
    )
    exact = frame.image - light
    for name, image, hold in (
        ("stage", frame.image, None),
        ("bright light exact", exact, None),
        (f"V > {args.faint_mag:g} held at input", frame.image, faint),
        ("both", exact, faint),
    ):
        t0 = time.perf_counter()
        fit = run_engine(
            replace(frame, image=image), frame_psf.psf, x0, y0, settings, return_model=False,
            halo=frame_psf.halo, halo_shape=frame_psf.halo_shape, hold_positions=hold,
        )  # fmt: skip
        wall = time.perf_counter() - t0
        print(
            f"  {name:>26}: " + " | ".join(
                fractions(fit.flag, sel & part) for part in (True, blend, ~blend, close, ~close, ~blend & ~close)
            ) + f"  [fit {wall:.1f} s]"
        )  # fmt: skip


if __name__ == "__main__":
    main()
