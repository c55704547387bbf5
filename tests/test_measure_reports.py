"""Reports and products: per-epoch accuracy reports with the frame offset shown
separately, and readers that drop flagged rows (NaN truth columns) before validating.

The measured tables are built here with a known per-frame offset and a known
scatter, so the expected numbers are analytic, not the code's own.
"""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable
from scipy.stats import norm

from mavispm.core.errors import InputError
from mavispm.core.products import write_product
from mavispm.dynamics.cli import load_stars
from mavispm.dynamics.settings import DynamicsSettings
from mavispm.measure.stars.accuracy_report import frame_offset, write_report

SIGMA = 50.0  # uas, per axis


def _measured(path, offset_uas, epoch, seed, n=4000):
    rng = np.random.default_rng(seed)
    mag = rng.uniform(17.0, 21.0, n)
    xt, yt = rng.uniform(-2, 2, n), rng.uniform(-2, 2, n)
    t = QTable()
    t["id"] = np.arange(n, dtype=np.int64)
    t["x_pix"] = xt / 7.36e-3
    t["y_pix"] = yt / 7.36e-3
    t["x"] = (xt + (offset_uas[0] + rng.normal(0, SIGMA, n)) * 1e-6) * u.arcsec
    t["y"] = (yt + (offset_uas[1] + rng.normal(0, SIGMA, n)) * 1e-6) * u.arcsec
    t["x_err"] = np.full(n, SIGMA * 1e-6) * u.arcsec
    t["y_err"] = np.full(n, SIGMA * 1e-6) * u.arcsec
    t["flux"] = np.full(n, 1e5) * u.electron
    t["flux_err"] = np.full(n, 3e2) * u.electron
    t["sky"] = np.full(n, 60.0) * u.electron
    t["chi2"] = np.ones(n)
    t["flag"] = np.zeros(n, np.int64)
    t["x_true"] = xt * u.arcsec
    t["y_true"] = yt * u.arcsec
    t["mag"] = mag * u.mag
    return write_product(
        path,
        "measured",
        tables={"stars": t},
        attrs={"epoch": epoch * u.yr, "pixel_scale": 7.36 * u.mas},
    )


def _clipped_gaussian_std(k: float, iterations: int) -> float:
    """Std (in sigma) of a Gaussian after ``iterations`` of k-sigma clipping about
    the centre, each with the std of the previous survivors (truncated normal)."""
    s = 1.0
    for _ in range(iterations):
        c = k * s
        s = np.sqrt(1.0 - 2.0 * c * norm.pdf(c) / (2.0 * norm.cdf(c) - 1.0))
    return float(s)


def test_accuracy_report_is_per_epoch_about_each_frame_offset(tmp_path):
    offsets = {0.0: (200.0, -120.0), 10.0: (-150.0, 80.0)}
    paths = [
        _measured(tmp_path / f"m{int(t)}.h5", off, t, seed=int(t)) for t, off in offsets.items()
    ]
    ecsv, md, png = write_report(paths, tmp_path / "report")
    table = QTable.read(ecsv)
    assert sorted(set(table["epoch"].to_value(u.yr))) == [0.0, 10.0]
    assert len(table) == 2 * 9
    for t, (ox, oy) in offsets.items():
        rows = table[table["epoch"].to_value(u.yr) == t]
        # the offset is shown separately (to the median's precision, ~1.3 SIGMA / sqrt(n))
        assert rows["offset_x"][0].to_value(u.uas) == pytest.approx(ox, abs=5.0)
        assert rows["offset_y"][0].to_value(u.uas) == pytest.approx(oy, abs=5.0)
        # and the dispersion is the injected scatter, not the offsets' spread
        full = rows[rows["n_used"] > 200]
        assert len(full) == 4
        expected = _clipped_gaussian_std(2.0, 3) * SIGMA
        np.testing.assert_allclose(full["sigma_x"].to_value(u.uas), expected, rtol=0.08)
        assert np.all(np.abs(full["bias_x"].to_value(u.uas)) < 10.0)
    text = md.read_text()
    assert text.count("Frame offset") == 2 and "+200" in text.replace(" ", "")[:10000]
    assert png.stat().st_size > 1000


def test_frame_offset_without_bright_stars_is_zero(tmp_path):
    path = _measured(tmp_path / "m.h5", (100.0, 0.0), 0.0, seed=3, n=20)
    from mavispm.core.products import read_product

    stars = read_product(path, "measured").tables["stars"]
    stars["mag"] = 25.0 * u.mag
    assert frame_offset(stars) == (0.0, 0.0, 0)


def _pm_product(path, nan_mag_unflagged: bool):
    n = 40
    rng = np.random.default_rng(1)
    t = QTable()
    t["id"] = np.arange(n, dtype=np.int64)
    x, y = rng.uniform(-5, 5, n), rng.uniform(-5, 5, n)
    t["x"], t["y"], t["R"] = x * u.arcsec, y * u.arcsec, np.hypot(x, y) * u.arcsec
    pm = u.mas / u.yr
    for k in ("pm_x", "pm_y", "pm_r", "pm_t"):
        t[k] = rng.normal(0, 0.2, n) * pm
    for k in ("pm_x_err", "pm_y_err", "pm_r_err", "pm_t_err"):
        t[k] = np.full(n, 0.02) * pm
    t["flag"] = np.zeros(n, np.int64)
    t["mag"] = np.full(n, 20.0) * u.mag
    # a flagged detection without a truth match: NaN magnitude and R
    t["flag"][0] = 8
    t["mag"][0] = np.nan * u.mag
    t["R"][0] = np.nan * u.arcsec
    if nan_mag_unflagged:
        t["mag"][1] = np.nan * u.mag
    return write_product(
        path, "propermotions", tables={"stars": t}, attrs={"distance": 4.6 * u.kpc}
    )


def test_dynamics_reader_drops_flagged_rows_before_validating(tmp_path):
    path = _pm_product(tmp_path / "pm.h5", nan_mag_unflagged=True)
    stars, distance = load_stars(path, DynamicsSettings(field_radius=20.0))
    assert distance == pytest.approx(4.6)
    assert stars.R.size == 39  # the flagged row is gone; a NaN truth mag does not matter
    # with use_flagged the NaN radius of the flagged row is refused, naming the column
    with pytest.raises(InputError, match="'R'"):
        load_stars(path, DynamicsSettings(field_radius=20.0, use_flagged=True))


def test_recovered_fraction_counts_the_stars_the_detector_shows(tmp_path):
    # a rendered frame whose input list also holds stars centred off the detector (their
    # light spills in, as the frames command renders a margin): the report's input counts
    # are the stars with true centres on the detector, counted here from the truth, and
    # isolated bright stars are all recovered
    from astropy.table import Table
    from measure_helpers import SynthPSF, write_frames

    from mavispm.measure.stars.cli import run_stage

    rng = np.random.default_rng(11)
    shape = (160, 160)
    gx, gy = np.meshgrid(np.arange(14, 150, 17.0), np.arange(14, 150, 17.0))
    inside_x, inside_y = gx.ravel() + rng.uniform(-1, 1, gx.size), gy.ravel()
    out_x = np.r_[rng.uniform(-6, -1.5, 12), rng.uniform(161, 166, 12)]
    out_y = rng.uniform(10, 150, 24)
    x, y = np.r_[inside_x, out_x], np.r_[inside_y, out_y]
    mag = rng.uniform(17.0, 21.5, len(x))
    frame = tmp_path / "frame.h5"
    write_frames(frame, shape, x, y, mag, SynthPSF(1.3), seed=2)
    settings = {"psf_variation": "constant", "psf_stars_per_node": 20, "psf_star_min_snr": 30.0}
    measured = run_stage(frame, settings, tmp_path / "measured.h5", seed=1)
    write_report([measured], tmp_path / "report")
    table = Table.read(tmp_path / "report" / "accuracy.ecsv")
    shown = (x > -0.5) & (x < shape[1] - 0.5) & (y > -0.5) & (y < shape[0] - 0.5)
    assert shown.sum() == gx.size and (~shown).sum() == 24
    for row in table:
        inbin = (mag >= row["mag_lo"]) & (mag < row["mag_hi"])
        assert row["n_input"] == int(np.count_nonzero(inbin & shown))
        if row["n_input"]:
            assert row["n_recovered"] == row["n_input"]  # isolated, V < 21.5: every one
