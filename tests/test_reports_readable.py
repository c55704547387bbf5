"""Reports a reader understands: accuracy per epoch, plots titled and labelled with units."""

from __future__ import annotations

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.products import write_product
from mavispm.measure.stars.accuracy_report import write_report
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


def test_accuracy_report_is_per_epoch(tmp_path):
    paths = [_measured(tmp_path / "a.h5", 0, 1.0, 1), _measured(tmp_path / "b.h5", 10, 3.0, 2)]
    ecsv, md, png = write_report(paths, tmp_path / "r")
    table = QTable.read(ecsv)
    assert sorted(set(table["epoch"].to_value(u.yr))) == [0.0, 10.0]
    sigma = {}
    for epoch in (0.0, 10.0):
        rows = table[(table["epoch"].to_value(u.yr) == epoch) & (table["n_recovered"] > 500)]
        assert len(rows) == 4  # the four 1-mag bins between 16 and 20
        sigma[epoch] = np.median(rows["sigma_x"].to_value(u.mas))
    # the epochs are not pooled: their dispersions keep the injected ratio of 3
    assert 2.7 < sigma[10.0] / sigma[0.0] < 3.3
    text = md.read_text()
    assert "**epoch 0 yr**" in text and "**epoch 10 yr**" in text and "measured.h5" not in text
    assert png.stat().st_size > 1000


def test_panel_titles_name_studies_and_scenes():
    node = {"labels": {"study": "imbh", "point": "mass=1500", "scene": "main", "epoch": "e1"}}
    assert panel_title(node) == "study imbh, mass=1500, scene main, epoch e1"
    assert panel_title({"labels": {"scene": "main"}}, ("study", "point", "scene")) == "scene main"
    assert panel_title({"labels": {}}) == "run"
