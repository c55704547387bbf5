"""The registration error shared by epochs registered to the same reference list.

Synthetic epochs (no frames): every star's position error is an independent part
plus a registration part, drawn once and put into every epoch (one reference
list). The products say how large the registration part is
(``x_err_registration``) and which list it belongs to (``registration_reference``).
The proper-motion errors are compared with the analytic variance of the epoch
difference; the truth motions score the normalised residuals.
"""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable

from mavispm.measure.propermotions.cli import proper_motions

N = 3000
DT = 10.0  # yr
SIGMA = 0.05  # mas, independent part per epoch and axis
SHARED = 0.2  # mas, the registration part (epoch 1)


def _epochs(references, shared_scale=(1.0, 1.0), columns=True, seed=0):
    """Two epochs whose errors share one registration realisation scaled per epoch;
    ``references`` names each epoch's list (None: no attribute)."""
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(-10, 10, (2, N))  # arcsec
    pm = rng.normal(0.0, 0.3, (2, N))  # mas/yr
    xi = rng.normal(0.0, 1.0, (2, N))  # the registration field at each star, both axes
    out = []
    for t, ref, scale in zip((0.0, DT), references, shared_scale):
        r = SHARED * scale
        err = np.full(N, np.hypot(SIGMA, r))
        cols = {"id": np.arange(N)}
        for a, pos, p, z in (("x", x, pm[0], xi[0]), ("y", y, pm[1], xi[1])):
            shift = p * t + r * z + rng.normal(0.0, SIGMA, N)  # mas
            cols[a] = (pos + shift * 1e-3) * u.arcsec
            cols[a + "_err"] = err * u.mas
            if columns:
                cols[a + "_err_registration"] = np.full(N, r) * u.mas
        meta = {"epoch": t * u.yr}
        if ref is not None:
            meta["registration_reference"] = ref
        out.append(QTable(cols, meta=meta))
    truth = {"id": np.arange(N), "pm_x": pm[0], "pm_y": pm[1]}
    return out, truth


def _scored(references, **kw):
    """Median PM error [mas/yr] and robust std of the normalised residuals (x, y pooled)."""
    epochs, truth = _epochs(references, **kw)
    pm = proper_motions(epochs, {}, truth=truth)
    err = np.concatenate([pm[a + "_err"].to_value(u.mas / u.yr) for a in ("pm_x", "pm_y")])
    res = np.concatenate(
        [(pm[a] - pm[a + "_true"]).to_value(u.mas / u.yr) for a in ("pm_x", "pm_y")]
    )
    z = res / err
    return float(np.median(err)), float(1.4826 * np.median(np.abs(z - np.median(z)))), pm


def test_shared_registration_cancels_only_between_epochs_naming_the_same_list():
    """Same list: the PM error is the independent parts' (sqrt(2) 0.05 / 10 mas/yr) and
    the normalised residuals have unit scatter (expected 1 +- 0.015 for 6000 values: the
    MAD's 1.17 / sqrt(n)). Different lists, no attribute or a product without the
    columns (written before them): the totals (sqrt(2) 0.206 / 10), which here make the
    residuals look 4 x too small, as the registration really is shared."""
    independent = np.sqrt(2.0) * SIGMA / DT
    total = np.sqrt(2.0) * np.hypot(SIGMA, SHARED) / DT
    err, spread, pm = _scored(("truth@0yr:a", "truth@0yr:a"))
    assert err == pytest.approx(independent, rel=0.02)
    assert spread == pytest.approx(1.0, abs=0.06)
    assert "share the registration" in pm.meta["notes"]
    for references, columns in (
        (("truth@0yr:a", "truth@10yr:b"), True),
        ((None, None), True),
        (("truth@0yr:a", "truth@0yr:a"), False),
    ):
        err, spread, pm = _scored(references, columns=columns)
        assert err == pytest.approx(total, rel=0.02), (references, columns)
        assert spread < 0.35, (references, columns)
        assert "share the registration" not in pm.meta["notes"]


def test_unequal_shared_parts_leave_their_difference():
    """The shared realisation scaled by 1 at epoch 1 and 0.5 at epoch 2 leaves
    (0.2 - 0.1) mas in the difference: the PM variance is
    (0.05^2 + 0.05^2 + 0.1^2) / 10^2 (analytic), and the residuals are calibrated."""
    err, spread, _ = _scored(("truth@0yr:a", "truth@0yr:a"), shared_scale=(1.0, 0.5))
    expected = np.sqrt(2 * SIGMA**2 + (0.5 * SHARED) ** 2) / DT
    assert err == pytest.approx(expected, rel=0.02)
    assert spread == pytest.approx(1.0, abs=0.06)
