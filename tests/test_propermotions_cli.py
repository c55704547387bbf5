"""The propermotions stage end to end: files in, product and report out, CLI."""

from __future__ import annotations

import json

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable
from propermotions_helpers import distortion_transform, make_cluster, observe, write_measured

from mavispm.core.catalogue import write_catalogue
from mavispm.core.errors import InputError
from mavispm.core.products import read_product
from mavispm.measure.propermotions import cli as propermotions_cli
from mavispm.measure.propermotions.report import load_accuracy, paper_statistic
from mavispm.workflows.cli import main

FORMATS_COLUMNS = [
    "id", "x", "y", "R", "pm_x", "pm_y", "pm_x_err", "pm_y_err", "pm_xy_corr",
    "pm_r", "pm_t", "pm_r_err", "pm_t_err", "n_epochs", "flag", "mag",
    "pm_x_true", "pm_y_true",
]  # fmt: skip


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pm")
    truth = make_cluster(n=1500, seed=21, n_fast=5)
    epochs = [0.0, 4.0, 10.0]
    trans = [None, distortion_transform(seed=1), distortion_transform(seed=2)]
    obs = observe(truth, epochs, trans, seed=22)
    paths = [write_measured(tmp / f"measured_e{k}.h5", o) for k, o in enumerate(obs)]
    return truth, paths, tmp


def test_cli_writes_product_per_formats_and_report(inputs, capsys):
    truth, paths, tmp = inputs
    out = tmp / "pm.h5"
    rep = tmp / "report"
    argv = ["measure", "propermotions", *map(str, paths[::-1]), "-o", str(out)]
    rc = main([*argv, "--order", "2", "--report", str(rep)])
    assert rc == 0
    prod = read_product(out, "propermotions")
    stars = prod.tables["stars"]
    for col in FORMATS_COLUMNS:
        assert col in stars.colnames, col
    assert stars["pm_x"].unit == u.mas / u.yr and stars["R"].unit == u.arcsec
    np.testing.assert_allclose(prod.attrs["epochs"].to_value(u.yr), [0.0, 4.0, 10.0])
    assert prod.attrs["flag_reject_mask"] == 4 + 8 + 16 + 64 + 128  # docs/formats.md
    assert prod.attrs["reference_epoch"].to_value(u.yr) == 0.0
    assert prod.attrs["distance"].to_value(u.kpc) == pytest.approx(4.6)  # from the inputs
    transform = json.loads(prod.attrs["transform"])
    assert transform["order"] == 2 and transform["epochs"]["0"] == "reference"
    assert transform["epochs"]["10"]["n_clipped"] >= 5
    # km/s columns with the distance: v = 4.74047 km/s per (mas/yr x kpc)
    np.testing.assert_allclose(
        stars["v_x"].to_value(u.km / u.s), 4.740470 * 4.6 * stars["pm_x"].value, rtol=1e-5
    )
    # radial/tangential consistent with x/y
    rad = (stars["x"] * stars["pm_x"] + stars["y"] * stars["pm_y"]) / stars["R"]
    np.testing.assert_allclose(stars["pm_r"].value, rad.to_value(u.mas / u.yr), atol=1e-9)
    names = sorted(p.name for p in rep.iterdir())
    assert names == sorted(
        [
            "pm_pm_by_mag.ecsv",
            "pm_pm_by_radius.ecsv",
            "pm_pm_accuracy.md",
            "pm_pm_errors.png",
            "pm_pm_residuals.png",
        ]
    )
    by_mag = QTable.read(rep / "pm_pm_by_mag.ecsv")
    assert by_mag["n"].sum() == len(stars)
    text = (rep / "pm_pm_accuracy.md").read_text()
    assert "m <= 25" in text and "1182/1194" in text


def test_report_statistics_against_direct_count(inputs):
    _, paths, tmp = inputs
    out = propermotions_cli.run_stage(paths, {"order": 2}, tmp / "pm_direct.h5")
    data = load_accuracy(out)
    stars = read_product(out, "propermotions").tables["stars"]
    d = np.hypot(
        (stars["pm_x"] - stars["pm_x_true"]).to_value(u.uas / u.yr),
        (stars["pm_y"] - stars["pm_y_true"]).to_value(u.uas / u.yr),
    )
    mag = stars["mag"].value
    stat = paper_statistic(data)
    assert stat["bright"] == (int(np.sum((d <= 50) & (mag <= 25))), int(np.sum(mag <= 25)))
    assert stat["faint"] == (int(np.sum((d <= 50) & (mag > 25))), int(np.sum(mag > 25)))
    # calibrated errors in the written product
    z = np.concatenate(
        [
            ((stars["pm_x"] - stars["pm_x_true"]) / stars["pm_x_err"]).value,
            ((stars["pm_y"] - stars["pm_y_true"]) / stars["pm_y_err"]).value,
        ]
    )
    assert abs(z.mean()) < 0.1 and abs(z.std() - 1) < 0.1


def test_truth_catalogue_and_distance_setting(inputs, tmp_path):
    truth, paths, _ = inputs
    table = QTable()
    table["id"] = truth.ids
    table["x"] = truth.x * u.arcsec
    table["y"] = truth.y * u.arcsec
    table["pm_x"] = truth.pm_x * u.mas / u.yr
    table["pm_y"] = truth.pm_y * u.mas / u.yr
    table["mag"] = truth.mag * u.mag
    table.meta["epoch"] = 0.0 * u.yr
    cat = write_catalogue(tmp_path / "cluster.h5", {"e0": table}, attrs={"distance": 4.6 * u.kpc})
    out = tmp_path / "pm_truth.h5"
    rc = main(
        ["measure", "propermotions", *map(str, paths), "-o", str(out), "--order", "2",
         "--truth", str(cat), "--distance", "9.2kpc"]
    )  # fmt: skip
    assert rc == 0
    prod = read_product(out, "propermotions")
    assert prod.attrs["distance"].to_value(u.kpc) == pytest.approx(9.2)
    s = prod.tables["stars"]
    # catalogue truth (relative frame) agrees with the truth from x_true/y_true positions
    ref = propermotions_cli.run_stage(paths, {"order": 2}, tmp_path / "pm_pos.h5")
    s_pos = read_product(ref, "propermotions").tables["stars"]
    np.testing.assert_allclose(s["pm_x_true"].value, s_pos["pm_x_true"].value, atol=1e-6)


def test_missing_distance_omits_kms_with_note(tmp_path):
    truth = make_cluster(n=300, seed=4)
    obs = observe(truth, [0.0, 10.0], None, seed=5)
    paths = [write_measured(tmp_path / f"m{k}.h5", o, distance=None) for k, o in enumerate(obs)]
    out = propermotions_cli.run_stage(paths, {}, tmp_path / "pm.h5")
    prod = read_product(out, "propermotions")
    assert "distance" not in prod.attrs
    assert "v_x" not in prod.tables["stars"].colnames
    assert "km/s columns omitted" in prod.attrs["notes"]


def test_cli_errors_are_one_line(tmp_path, capsys, inputs):
    _, paths, _ = inputs
    rc = main(["measure", "propermotions", str(paths[0]), "-o", str(tmp_path / "x.h5")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "at least two epochs" in err and "Traceback" not in err
    rc = main(
        ["measure", "propermotions", *map(str, paths), "-o", str(tmp_path / "x.h5"),
         "--distance", "4.6 km/s"]
    )  # fmt: skip
    assert rc == 2 and "distance" in capsys.readouterr().err
    out = tmp_path / "bare.h5"
    assert (
        main(["measure", "propermotions", *map(str, paths), "-o", str(out), "--distance", "5"]) == 0
    )
    assert read_product(out, "propermotions").attrs["distance"].to_value(u.kpc) == 5.0
    with pytest.raises(InputError, match="no truth columns"):
        _no_truth_report(tmp_path, paths)


def _no_truth_report(tmp_path, paths):
    from mavispm.core.products import write_product

    prod = read_product(paths[0], "measured")
    stars = prod.tables["stars"]
    pm = QTable()
    for col in ("id", "x", "y"):
        pm[col] = stars[col]
    pm["R"] = np.hypot(stars["x"], stars["y"])
    for col in ("pm_x", "pm_y", "pm_x_err", "pm_y_err"):
        pm[col] = np.ones(len(stars)) * u.mas / u.yr
    pm["flag"] = np.zeros(len(stars), np.int64)
    path = write_product(tmp_path / "nt.h5", "propermotions", tables={"stars": pm})
    propermotions_cli.write_report([path], tmp_path / "r")


def test_accuracy_attrs_against_injected_residuals():
    from mavispm.measure.propermotions.cli import accuracy_attrs

    rng = np.random.default_rng(11)
    n, sigma = 40000, 0.03  # mas/yr per axis
    mas_yr = u.mas / u.yr
    true = rng.normal(0, 0.2, (2, n))
    meas = true + 0.7 + rng.normal(0, sigma, (2, n))  # a common offset (mean motion) + noise
    table = QTable(
        {
            "pm_x": meas[0] * mas_yr,
            "pm_y": meas[1] * mas_yr,
            "pm_x_err": np.full(n, 0.02) * mas_yr,
            "pm_y_err": np.full(n, 0.04) * mas_yr,
            "pm_x_true": true[0] * mas_yr,
            "pm_y_true": true[1] * mas_yr,
        }
    )
    table["pm_x"][0] = np.nan * mas_yr  # left out, not propagated
    out = accuracy_attrs(table)
    assert out["pm_err_median"].to_value(mas_yr) == pytest.approx(
        np.sqrt(0.5 * (0.02**2 + 0.04**2))
    )
    assert out["pm_rms_true"].to_value(mas_yr) == pytest.approx(sigma, rel=0.02)
    # |d| of a 2-D Gaussian is Rayleigh: P(|d| <= 0.05) = 1 - exp(-0.05^2 / (2 sigma^2))
    assert out["pm_frac_50uas"] == pytest.approx(1 - np.exp(-(0.05**2) / (2 * sigma**2)), abs=0.01)
    assert set(accuracy_attrs(table[["pm_x_err", "pm_y_err"]])) == {"pm_err_median"}
