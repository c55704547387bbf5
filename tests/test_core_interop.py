"""Products other tools open: astropy's HDF5 table reader, FITS/ECSV/CSV export."""

from __future__ import annotations

import astropy.units as u
import h5py
import numpy as np
import pytest
from astropy.io import ascii as astropy_ascii
from astropy.io import fits
from astropy.table import QTable, Table

from mavispm.core.errors import InputError
from mavispm.core.products import export_table, read_product, read_table, write_product
from mavispm.workflows.cli import main


def _stars(n=5):
    rng = np.random.default_rng(1)
    t = QTable()
    t["id"] = np.arange(n, dtype=np.int64)
    t["x"] = rng.normal(size=n) * u.arcsec
    t["pm_x"] = rng.normal(size=n) * u.mas / u.yr
    t["mag"] = rng.uniform(16, 22, n) * u.mag
    t["flag"] = np.array([0, 1, 0, 0, 2][:n])
    t["x_err"] = np.r_[np.nan, rng.uniform(0.1, 1, n - 1)] * u.mas
    t["label"] = np.array(["a", "bb", "ccc", "d", "e"][:n])
    return t


@pytest.fixture
def product(tmp_path):
    return write_product(
        tmp_path / "pm.h5",
        "propermotions",
        tables={"stars": _stars(), "epochs/e0": _stars(3)},
        attrs={"epoch": 10.0 * u.yr, "distance": 4.6 * u.kpc, "notes": "x"},
        config={"a": 1},
        seed=2,
    )


def test_astropy_reads_every_table_with_units(product):
    t = _stars()
    plain = Table.read(product, path="stars")
    assert plain["pm_x"].unit == u.mas / u.yr and plain["x_err"].unit == u.mas
    np.testing.assert_array_equal(plain["pm_x"], t["pm_x"].value)
    assert list(plain["label"]) == list(t["label"])  # text survives (as bytes or str)
    nested = QTable.read(product, path="epochs/e0")
    assert nested["x"].unit == u.arcsec and len(nested) == 3


def test_read_table_carries_the_root_attributes(product):
    t = read_table(product)
    assert t.meta["distance"] == 4.6 * u.kpc and t.meta["kind"] == "propermotions"
    with pytest.raises(InputError, match=r"no table 'nope'.*stars"):
        read_table(product, "nope")


@pytest.mark.parametrize("suffix", [".fits", ".ecsv", ".csv"])
def test_export_round_trips_values_and_units(product, tmp_path, suffix):
    out = export_table(product, tmp_path / f"t{suffix}")
    back = Table.read(out, format="ascii.csv") if suffix == ".csv" else Table.read(out)
    t = _stars()
    np.testing.assert_allclose(np.asarray(back["pm_x"], float), t["pm_x"].value, rtol=1e-15)
    assert np.isnan(np.asarray(back["x_err"], float)[0]) or np.ma.is_masked(back["x_err"][0])
    if suffix != ".csv":
        assert back["pm_x"].unit == u.mas / u.yr
    if suffix == ".fits":
        header = fits.getheader(out, 1)
        assert header["TUNIT3"] == "mas / yr" or u.Unit(header["TUNIT3"]) == u.mas / u.yr
        assert "EPOCH" not in header  # the product's epoch is not the FITS equinox word
        assert header["HIERARCH MAVISPM DISTANCE"] == "4.6 kpc"
    if suffix == ".ecsv":
        assert astropy_ascii.read(out).meta["distance"] == "4.6 kpc"


def test_export_command_and_its_errors(product, tmp_path, capsys):
    assert main(["export", str(product), "-o", str(tmp_path / "t.ecsv"), "--table", "stars"]) == 0
    assert (tmp_path / "t.ecsv").is_file()
    assert main(["export", str(product), "-o", str(tmp_path / "t.xlsx")]) == 2
    assert "unknown table format '.xlsx'" in capsys.readouterr().err
    assert not (tmp_path / "t.xlsx").exists()


def test_version_1_products_are_still_read(tmp_path):
    """A product written in format 1 (a group per table, a dataset per column)."""
    path = tmp_path / "v1.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update({"format": "mavispm", "kind": "measured", "format_version": 1})
        grp = f.create_group("stars")
        grp.attrs.update({"mavispm_table": True, "nrows": 2})
        grp["id"] = np.array([3, 4])
        grp["id"].attrs["unit"] = ""
        grp["x"] = np.array([0.5, 1.5])
        grp["x"].attrs["unit"] = "arcsec"
        f["image"] = np.zeros((2, 2))
        f["image"].attrs["unit"] = "adu"
    prod = read_product(path, "measured")
    assert prod.tables["stars"]["x"].unit == u.arcsec
    np.testing.assert_array_equal(prod.tables["stars"]["id"], [3, 4])
    assert list(prod.arrays) == ["image"]
