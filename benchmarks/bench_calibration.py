"""Benchmark of the astrometric calibration mask, with MAVISIM 1.1.20 as the peer.

Prints
1. the post-calibration residual (RMS over the 15" science field, mean removed) against
   the polynomial order, the hole machining error, the number of holes (same span), the centroid
   noise and the mask shift, for the differential and direct methods, with run time;
2. the same input distortion calibrated by the published MAVISIM 1.1.20
   (``mavisim.AstromCalibSimAna``, installed on demand with ``pip install --no-deps
   --target``) and by mavispm, on the same mask settings, in one run: residual RMS of
   each over 10 seeds, and their run times.

The input distortion is mavispm's default static map (0.44 mas at the corner) plus an
optional dynamic term; MAVISIM reads it as its own ``Field_x(deg) ... Real_y(mm)`` table.

Usage: ``python benchmarks/bench_calibration.py [--quick] [--no-peer]``
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mavispm.simulate.optics.calibration_mask import CalibrationMaskSettings, simulate_calibration
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings

MAVISIM_VERSION = "1.1.20"
#: MAVISIM's sensor plate scale (arcsec/mm): 7.36 mas pixels of 10 micron
MAVISIM_PLATE_SCALE = 7.36e-3 / 10e-3


def _residual(distortion, **kw) -> tuple[float, float]:
    t0 = time.perf_counter()
    r = simulate_calibration(distortion, CalibrationMaskSettings(**kw))
    return r.residual_rms, time.perf_counter() - t0


def sweep(distortion, quick: bool) -> None:
    seeds = range(3 if quick else 10)
    base = dict(order=6, hole_position_error=0.01, centroid_noise=0.01, shift=0.2, n_holes=35)
    sweeps = {
        "order": [2, 3, 4, 6, 8],
        "hole_position_error": [0.0, 0.001, 0.01, 0.05],
        "n_holes": [10, 15, 20, 35],
        "centroid_noise": [0.001, 0.01, 0.1],
        "shift": [0.1, 0.2, 0.5, 1.0, 2.0],
    }
    units = {"hole_position_error": "mm", "centroid_noise": "mas", "shift": "mm"}
    print("\n== residual after calibration [mas RMS] (default map, mean of seeds) ==")
    print(f"base: {base}")
    for knob, values in sweeps.items():
        print(f"\n{knob} [{units.get(knob, '')}]  differential  direct   time/calib [ms]")
        for value in values:
            row = []
            times = []
            for method in ("differential", "direct"):
                rs = []
                for seed in seeds:
                    kw = {**base, knob: value, "method": method, "seed": seed}
                    if knob == "n_holes":  # the same span (+-14.6") with fewer holes
                        kw["pitch"] = 0.5 * 34 / (value - 1)
                    try:
                        r, t = _residual(distortion, **kw)
                    except ValueError:
                        r, t = np.nan, np.nan
                    rs.append(r)
                    times.append(t)
                row.append(float(np.sqrt(np.mean(np.square(rs)))))
            print(f"{value:>10}  {row[0]:12.5f}  {row[1]:8.4f}   {1e3 * np.nanmean(times):8.1f}")


def _ensure_mavisim(cache: Path) -> Path | None:
    """Install MAVISIM 1.1.20 (no dependencies) into its own folder; None if impossible."""
    target = cache / f"mavisim-{MAVISIM_VERSION}"
    if (target / "mavisim" / "astromsim.py").exists():
        return target
    cmd = [
        sys.executable,
        "-m",
        "pip",
        "install",
        "-q",
        "--no-deps",
        "--target",
        str(target),
        f"mavisim=={MAVISIM_VERSION}",
    ]
    try:
        subprocess.run(cmd, check=True, timeout=300, capture_output=True)
    except (subprocess.SubprocessError, OSError) as exc:
        print(f"MAVISIM {MAVISIM_VERSION} could not be installed ({exc}); peer comparison skipped")
        return None
    return target


_PEER_SCRIPT = r"""
import json, sys, time
import numpy as np
from astropy.table import Table
from mavisim.astromsim import AstromCalibSimAna
args = json.loads(sys.argv[1])
tab = Table.read(args["table"], format="ascii.ecsv")
gx, gy = np.array(args["gx"]), np.array(args["gy"])
out = []
for seed in args["seeds"]:
    np.random.seed(seed)
    t0 = time.perf_counter()
    sim = AstromCalibSimAna(tab, centroid_noise_std=args["noise_as"],
                            hole_position_std=args["hole_mm"], dx=args["shift"], dy=args["shift"],
                            n_poly=args["order"], pin_pitch=args["pitch"], num_pin_x=args["n_pin"])
    rx, ry = sim.residual_dist(gx, gy)
    t = time.perf_counter() - t0
    rx, ry = rx * 1e3, ry * 1e3
    out.append([float(np.sqrt(np.mean((rx - rx.mean())**2 + (ry - ry.mean())**2))), t])
print(json.dumps(out))
"""


def peer(distortion, quick: bool, cache: Path) -> None:
    print(f"\n== peer: MAVISIM {MAVISIM_VERSION} AstromCalibSimAna vs mavispm, same input ==")
    target = _ensure_mavisim(cache)
    if target is None:
        return
    from astropy.table import Table

    # the input map on a 0.5" grid, in MAVISIM's table format (distortion = Predicted - Real)
    axis = np.arange(-18.0, 18.01, 0.5)
    fx, fy = (a.ravel() for a in np.meshgrid(axis, axis, indexing="ij"))
    dx, dy = distortion.displacement(fx, fy)  # arcsec
    pred_x, pred_y = fx / MAVISIM_PLATE_SCALE, fy / MAVISIM_PLATE_SCALE
    table = Table(
        {
            "Field_x(deg)": fx / 3600,
            "Field_y(deg)": fy / 3600,
            "Predicted_x(mm)": pred_x,
            "Predicted_y(mm)": pred_y,
            "Real_x(mm)": pred_x - dx / MAVISIM_PLATE_SCALE,
            "Real_y(mm)": pred_y - dy / MAVISIM_PLATE_SCALE,
        }
    )
    g = np.linspace(-15, 15, 31)
    gx, gy = np.meshgrid(g, g)
    inside = np.hypot(gx, gy) <= 15
    seeds = list(range(3 if quick else 10))
    cases = [
        dict(order=6, hole_mm=0.01, noise_mas=0.01, shift=0.2),
        dict(order=3, hole_mm=0.01, noise_mas=0.01, shift=0.2),
        dict(order=6, hole_mm=0.0, noise_mas=0.0, shift=0.2),
        dict(order=6, hole_mm=0.01, noise_mas=0.01, shift=1.0),
    ]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "distortion.ecsv"
        table.write(path, format="ascii.ecsv")
        print(
            f"{'order':>5} {'hole [mm]':>9} {'noise [mas]':>11} {'shift [mm]':>10} "
            f"{'MAVISIM [mas]':>14} {'mavispm [mas]':>14} {'MAVISIM [s]':>11} {'mavispm [s]':>11}"
        )
        for case in cases:
            args = {
                "table": str(path),
                "gx": gx[inside].tolist(),
                "gy": gy[inside].tolist(),
                "seeds": seeds,
                "noise_as": case["noise_mas"] / 1000,
                "hole_mm": case["hole_mm"],
                "shift": case["shift"],
                "order": case["order"],
                "pitch": 0.5,
                "n_pin": 40,
            }
            env = {**os.environ, "PYTHONPATH": str(target)}
            proc = subprocess.run(
                [sys.executable, "-c", _PEER_SCRIPT, json.dumps(args)],
                capture_output=True,
                text=True,
                env=env,
                timeout=1800,
            )
            if proc.returncode != 0:
                print(f"MAVISIM failed: {proc.stderr.strip().splitlines()[-1:]}")
                return
            theirs = np.array(json.loads(proc.stdout.strip().splitlines()[-1]))
            ours = [
                _residual(
                    distortion,
                    order=case["order"],
                    hole_position_error=case["hole_mm"],
                    centroid_noise=case["noise_mas"],
                    shift=case["shift"],
                    seed=s,
                )
                for s in seeds
            ]
            ours = np.array(ours)
            print(
                f"{case['order']:>5} {case['hole_mm']:>9} {case['noise_mas']:>11} "
                f"{case['shift']:>10} {np.sqrt(np.mean(theirs[:, 0] ** 2)):>14.5f} "
                f"{np.sqrt(np.mean(ours[:, 0] ** 2)):>14.5f} {theirs[:, 1].mean():>11.3f} "
                f"{ours[:, 1].mean():>11.4f}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 seeds instead of 10")
    parser.add_argument("--no-peer", action="store_true", help="skip the MAVISIM comparison")
    parser.add_argument(
        "--cache",
        default=os.environ.get("MAVISPM_CACHE", str(Path.home() / ".cache" / "mavispm")),
        help="folder for the peer package (default $MAVISPM_CACHE)",
    )
    args = parser.parse_args()
    distortion = Distortion(DistortionSettings())
    sweep(distortion, args.quick)
    if not args.no_peer:
        peer(distortion, args.quick, Path(args.cache))


if __name__ == "__main__":
    main()
