"""Reports a reader understands: accuracy per epoch, plots titled and labelled with units."""

from __future__ import annotations

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.products import write_product
from mavispm.workflows.report import panel_title


def _measured(path, epoch, sigma_mas, seed):
    """A measured product whose x errors are Gaussian with ``sigma_mas`` (known truth)."""
    rng = np.random.default_rng(seed)
    n = 4000
    t = QTable()
    t["id"] = np.arange(n)
    t["x_pix"] = rng.uniform(0, 100, n)
    t["y_pix"] = rng.uniform(0, 100, n)
    t["x_true"] = rng.uniform(-1, 1, n) * u.arcsec
    t["y_true"] = rng.uniform(-1, 1, n) * u.arcsec
    t["x"] = t["x_true"] + rng.normal(0, sigma_mas, n) * u.mas
    t["y"] = t["y_true"] + rng.normal(0, sigma_mas, n) * u.mas
    for c in ("x_err", "y_err"):
        t[c] = np.full(n, sigma_mas) * u.mas
    t["flux"] = np.full(n, 1e4) * u.electron
    t["flux_err"] = np.full(n, 1e2) * u.electron
    t["sky"] = np.full(n, 10.0) * u.electron
    t["chi2"] = np.ones(n)
    t["flag"] = np.zeros(n, np.int64)
    t["mag"] = rng.uniform(16.0, 20.0, n) * u.mag
    return write_product(
        path, "measured", tables={"stars": t}, attrs={"epoch": epoch * u.yr, "frames": f"e{epoch}"}
    )


def test_panel_titles_name_studies_and_scenes():
    node = {"labels": {"study": "imbh", "point": "mass=1500", "scene": "main", "epoch": "e1"}}
    assert panel_title(node) == "study imbh, mass=1500, scene main, epoch e1"
    assert panel_title({"labels": {"scene": "main"}}, ("study", "point", "scene")) == "scene main"
    assert panel_title({"labels": {}}) == "run"
