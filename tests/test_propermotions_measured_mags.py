"""Proper motions carry the measured magnitude and choose reference stars by it."""

from __future__ import annotations

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.measure.propermotions.cli import proper_motions
from mavispm.measure.propermotions.pipeline import PMFlag


def _epochs(with_fit: bool):
    rng = np.random.default_rng(5)
    n = 60
    x, y = rng.uniform(-2, 2, (2, n))
    mag_in = np.where(np.arange(n) < 30, 18.0, 23.0)  # input: first half bright
    mag_fit = np.where(np.arange(n) < 30, 23.0, 18.0)  # measured: the other way round
    out = []
    for t in (0.0, 10.0):
        tab = QTable(
            {
                "id": np.arange(n),
                "x": x * u.arcsec,
                "y": y * u.arcsec,
                "x_err": np.full(n, 0.2) * u.mas,
                "y_err": np.full(n, 0.2) * u.mas,
                "mag": mag_in * u.mag,
            },
            meta={"epoch": t * u.yr},
        )
        if with_fit:
            tab["mag_fit"] = (mag_fit + rng.normal(0, 0.01, n)) * u.mag
        out.append(tab)
    return out


def test_reference_stars_are_chosen_by_the_measured_magnitude():
    pm = proper_motions(_epochs(True), {"ref_mag_max": 20.0})
    not_ref = (np.asarray(pm["flag"]) & PMFlag.NOT_REFERENCE) > 0
    assert not_ref[:30].all() and not not_ref[30:].any()
    # the measured magnitude is reported as the median over the epochs
    assert np.allclose(pm["mag_fit"][30:].to_value(u.mag), 18.0, atol=0.05)
    assert np.all(pm["mag"][:30] == 18 * u.mag)  # the input magnitude stays as it was


def test_without_measured_magnitudes_the_input_ones_are_used():
    pm = proper_motions(_epochs(False), {"ref_mag_max": 20.0})
    not_ref = (np.asarray(pm["flag"]) & PMFlag.NOT_REFERENCE) > 0
    assert not not_ref[:30].any() and not_ref[30:].all()
    assert "mag_fit" not in pm.colnames
