"""Benchmark: the full calibration mask rendered and PSF-fitted, against the analytic noise.

The default 35 x 35 mask is imaged through the default static distortion map, each of
its three exposures rendered with the static central MAVIS PSF (no tip-tilt kernel, no
halo) on the default 4000 x 4000 detector, one 30 s exposure, and measured by the star
fitter (``imaging = "rendered"``). Prints, per hole magnitude, the RMS Cramér-Rao bound of
the holes, the residual distortion RMS over the science field (and with the best affine
map removed, as the alignment of every epoch does), and the same for the analytic
simulation with ``centroid_noise`` set to that bound.

Usage: ``python benchmarks/bench_rendered_mask.py [--mags 18 20] [--seed 1]``
(about a minute per magnitude; ~1 GB of memory).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mavispm.simulate.optics.calibration_mask import (
    CalibrationMaskSettings,
    _science_grid,
    simulate_calibration,
)
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings
from mavispm.simulate.optics.pinhole_imaging import rendered_hole_imager
from mavispm.simulate.render import cli as render_cli

SCENE = {
    "nexp": 1,
    "render": {"halo": False, "threads": 1},
    "optics": {
        "psf": {"mode": "static"},
        "tiptilt": {"enabled": False},
        "halo": {"enabled": False},
    },
}


def affine_free_rms(distortion: Distortion, result) -> float:
    """Residual RMS [mas] over the science field after removing the best affine map."""
    gx, gy = _science_grid()
    tx, ty = (1e3 * v for v in distortion.displacement(gx, gy, 0.0))
    rx, ry = result.recovered.displacement_mas(gx, gy)
    a = np.column_stack([np.ones_like(gx), gx, gy])
    ex, ey = tx - rx, ty - ry
    ex = ex - a @ np.linalg.lstsq(a, ex, rcond=None)[0]
    ey = ey - a @ np.linalg.lstsq(a, ey, rcond=None)[0]
    return float(np.sqrt(np.mean(ex**2 + ey**2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mags", type=float, nargs="+", default=[18.0, 20.0])
    parser.add_argument("--seed", type=int, default=1, help="seed of the image noise")
    args = parser.parse_args()
    scene = render_cli.validate_settings(SCENE)
    optics = render_cli.build_scene_optics(scene)
    dist = Distortion(DistortionSettings())
    for mag in args.mags:
        record = []
        t0 = time.time()
        # mask draws (hole errors) from the default mask seed; image noise from --seed
        mask = CalibrationMaskSettings(imaging="rendered", hole_magnitude=mag)
        imager = rendered_hole_imager(scene, optics, mag, seed=args.seed, record=record)
        rendered = simulate_calibration(dist, mask, imager=imager)
        wall = time.time() - t0
        bounds = np.concatenate([np.r_[m.crlb_x, m.crlb_y] for m in record])
        crlb = float(np.sqrt(np.nanmean(bounds**2))) * 1e3
        analytic = simulate_calibration(dist, CalibrationMaskSettings(centroid_noise=crlb))
        failed = sum(int(np.isnan(m.x).sum()) for m in record)
        print(
            f"mag {mag:g}: bound {crlb:.4f} mas; rendered residual {rendered.residual_rms:.4f} "
            f"({affine_free_rms(dist, rendered):.4f} affine removed) mas; analytic at the "
            f"bound {analytic.residual_rms:.4f} ({affine_free_rms(dist, analytic):.4f}) mas; "
            f"{failed} holes failed; {wall:.0f} s"
        )


if __name__ == "__main__":
    main()
