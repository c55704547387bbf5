"""The stars stage end to end: product contract, report, CLI, blind mode, bad input."""

from __future__ import annotations

import astropy.units as u
import h5py
import numpy as np
import pytest
from measure_helpers import SynthPSF, write_frames

from mavispm.core.errors import ConfigError, InputError
from mavispm.core.products import read_product
from mavispm.measure.stars.cli import run_stage, validate_settings, write_report
from mavispm.measure.stars.measure_frame import MEASURED_SPEC
from mavispm.measure.stars.truth_match import match_to_truth
from mavispm.workflows.cli import main

SHAPE = (200, 200)
FAST = {"psf_grid": 2, "psf_stars_per_node": 12, "psf_star_min_snr": 50.0, "epsf_iterations": 5}


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    rng = np.random.default_rng(21)
    n = 120
    x, y = rng.uniform(4, 196, n), rng.uniform(4, 196, n)
    mag = rng.uniform(15.5, 25.5, n)
    path = tmp_path_factory.mktemp("frames") / "frame.h5"
    write_frames(path, SHAPE, x, y, mag, SynthPSF(1.2, gradient=0.2), seed=5)
    return path


@pytest.fixture(scope="module")
def measured(frame, tmp_path_factory):
    out = tmp_path_factory.mktemp("measured") / "measured.h5"
    return run_stage(frame, FAST, out, seed=1)


def test_measured_product_contract(frame, measured):
    prod = read_product(measured, "measured", specs={"stars": MEASURED_SPEC})
    stars = prod.tables["stars"]
    truth = read_product(frame, "frames").tables["truth"]
    assert len(stars) == len(truth)
    assert prod.attrs["engine"] == "fast"
    assert prod.attrs["pixel_scale"].to_value(u.mas) == pytest.approx(7.36)
    for col in ("x", "y", "x_err", "x_true", "match_dist"):
        assert stars[col].unit == u.arcsec
    assert np.array_equal(np.asarray(stars["id"]), np.asarray(truth["id"]))
    good = (np.asarray(stars["flag"]) & (16 | 32)) == 0
    assert good.mean() > 0.6
    # bright unflagged stars are measured within a few mas of the truth
    bright = good & (stars["mag"].value < 21)
    dx = (stars["x"] - stars["x_true"]).to_value(u.mas)[bright]
    assert np.median(np.abs(dx)) < 1.0
    # x_pix <-> x follows docs/formats.md
    ny, nx = SHAPE
    np.testing.assert_allclose(
        stars["x"].to_value(u.arcsec), (stars["x_pix"] - (nx - 1) / 2) * 7.36e-3, rtol=1e-12
    )


def test_report(measured, tmp_path):
    paths = write_report([measured], tmp_path / "report")
    assert [p.name for p in paths] == ["accuracy.ecsv", "accuracy.md", "astrometry_x.png"]
    from astropy.table import QTable

    table = QTable.read(paths[0])
    assert len(table) == 9
    assert table["bin"][0] == "m<16" and table["bin"][-1] == "m>=26"
    stars = read_product(measured, "measured").tables["stars"]
    mags = stars["mag"].value
    assert table["n_input"].sum() == len(stars)
    assert table["n_input"][1] == np.count_nonzero((mags >= 16) & (mags < 17))
    assert np.all(table["n_recovered"] <= table["n_input"])
    assert "sigma_x [uas]" in paths[1].read_text()
    assert paths[2].stat().st_size > 1000


def test_cli_runs(frame, tmp_path, capsys):
    out = tmp_path / "cli.h5"
    cfg = tmp_path / "stars.toml"
    cfg.write_text("[stars]\n" + "\n".join(f"{k} = {v}" for k, v in FAST.items()) + "\n")
    code = main(
        [
            "measure",
            "stars",
            str(frame),
            "-o",
            str(out),
            "--config",
            str(cfg),
            "--report",
            str(tmp_path / "r"),
        ]
    )
    assert code == 0
    assert out.exists() and (tmp_path / "r" / "accuracy.md").exists()


def test_blind_mode(frame, tmp_path):
    out = run_stage(
        frame, {**FAST, "blind": True, "detection_fwhm": "2.8 pix"}, tmp_path / "blind.h5", seed=0
    )
    prod = read_product(out, "measured", specs={"stars": MEASURED_SPEC})
    assert 0.3 < prod.attrs["detect_completeness"] <= 1.0
    assert prod.attrs["detect_false_fraction"] < 0.2
    stars = prod.tables["stars"]
    matched = (np.asarray(stars["flag"]) & 16) == 0
    # id: the detection index (an observer's); id_true: the truth match, scoring only
    assert np.array_equal(np.asarray(stars["id"]), np.arange(len(stars)))
    id_true = np.asarray(stars["id_true"])
    assert np.all(id_true[~matched] == -1) and np.all(id_true[matched] >= 0)
    assert len(np.unique(id_true[matched])) == np.count_nonzero(matched)
    assert np.all(np.isfinite(stars["match_dist"][matched]))
    truth = read_product(frame, "frames").tables["truth"]
    row = {int(i): k for k, i in enumerate(np.asarray(truth["id"]))}
    k = np.array([row[i] for i in id_true[matched]])
    dx = np.asarray(stars["x_pix"])[matched] - np.asarray(truth["x_pix"])[k]
    dy = np.asarray(stars["y_pix"])[matched] - np.asarray(truth["y_pix"])[k]
    assert np.all(np.hypot(dx, dy) <= 2.0)  # the truth star at id_true is the detection


def test_match_is_one_to_one():
    tx, ty = np.array([0.0, 10.0, 20.0]), np.zeros(3)
    x, y = np.array([0.2, 0.1, 10.5, 40.0, np.nan]), np.zeros(5)
    index, dist = match_to_truth(x, y, tx, ty, radius=2.0)
    assert index.tolist() == [-1, 0, 1, -1, -1]
    np.testing.assert_allclose(dist[:3], [np.nan, 0.1, 0.5])


def test_unknown_engine_and_keys():
    with pytest.raises(ConfigError, match="engine"):
        validate_settings({"engine": "daophot"})
    with pytest.raises(ConfigError, match="stamp_radus"):
        validate_settings({"stamp_radus": 4})
    with pytest.raises(ConfigError, match="psf_grid"):
        validate_settings({"psf_variation": "polynomial", "psf_grid": 2, "psf_poly_order": 3})
    assert validate_settings({"match_radius": "1.5 pix"}).match_radius == 1.5


def test_forced_mode_needs_truth(tmp_path):
    path = tmp_path / "notruth.h5"
    write_frames(path, (40, 40), [20.0], [20.0], [18.0], SynthPSF(), truth=False)
    with pytest.raises(InputError, match="truth"):
        run_stage(path, {}, tmp_path / "m.h5", seed=0)
    assert not (tmp_path / "m.h5").exists()
    assert main(["measure", "stars", str(path), "-o", str(tmp_path / "m.h5")]) == 2


def test_mismatched_mask_shape(tmp_path):
    path = tmp_path / "bad.h5"
    write_frames(path, (40, 40), [20.0], [20.0], [18.0], SynthPSF())
    with h5py.File(path, "a") as f:
        del f["saturated"]
        f["saturated"] = np.zeros((30, 40), bool)
    with pytest.raises(InputError, match="saturated"):
        run_stage(path, {}, tmp_path / "m.h5", seed=0)


def test_not_a_frames_product(measured, tmp_path):
    with pytest.raises(InputError, match="frames"):
        run_stage(measured, {}, tmp_path / "m.h5", seed=0)
