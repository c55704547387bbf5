"""Tests of the shared product format, atomic writes and config parsing."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import astropy.units as u
import h5py
import numpy as np
import pytest
from astropy.table import QTable, Table

from mavispm.core.atomic import atomic_path
from mavispm.core.catalogue import CATALOGUE_SPEC, read_catalogue, write_catalogue
from mavispm.core.config import from_mapping, unit_field
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.products import TableSpec, read_product, validate_table, write_product


def _epoch_table(n=5, epoch=0.0):
    rng = np.random.default_rng(1)
    t = QTable()
    t["id"] = np.arange(n, dtype=np.int64)
    t["x"] = rng.normal(size=n) * u.arcsec
    t["y"] = rng.normal(size=n) * u.arcsec
    t["pm_x"] = rng.normal(size=n) * u.mas / u.yr
    t["pm_y"] = rng.normal(size=n) * u.mas / u.yr
    t["mag"] = rng.uniform(14, 27, n) * u.mag
    t.meta["epoch"] = epoch * u.yr
    return t


def test_catalogue_roundtrip(tmp_path):
    e0, e1 = _epoch_table(epoch=0.0), _epoch_table(epoch=10.0)
    path = write_catalogue(
        tmp_path / "c.h5",
        {"e1": e1, "e0": e0},
        attrs={"distance": 4.6 * u.kpc},
        config={"a": 1},
        seed=3,
    )
    cat = read_catalogue(path)
    assert list(cat.epochs) == ["e0", "e1"]
    assert cat.attrs["seed"] == 3
    assert cat.attrs["config"] == {"a": 1}
    assert cat.attrs["distance"].to_value(u.kpc) == pytest.approx(4.6)
    np.testing.assert_array_equal(cat.epochs["e0"]["x"].value, e0["x"].value)
    assert cat.epochs["e1"]["pm_x"].unit == u.mas / u.yr
    assert cat.epoch_times()["e1"].to_value(u.yr) == 10.0
    with h5py.File(path) as f:
        assert "mavispm_version" in f.attrs and "created" in f.attrs
    # a peer reader (astropy's own HDF5 table reader) opens every table with its units
    plain = Table.read(path, path="epochs/e0")
    assert plain["x"].unit == u.arcsec and plain["pm_x"].unit == u.mas / u.yr
    np.testing.assert_array_equal(plain["x"], e0["x"].value)


def test_units_are_converted_on_read(tmp_path):
    t = _epoch_table()
    t["x"] = t["x"].to(u.mas)
    path = write_catalogue(tmp_path / "c.h5", {"e0": t})
    cat = read_catalogue(path)
    assert cat.epochs["e0"]["x"].unit == u.arcsec
    np.testing.assert_allclose(cat.epochs["e0"]["x"].value, t["x"].to_value(u.arcsec))


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda t: t.rename_column("pm_x", "pmx"), "pm_x.*did you mean 'pmx'"),
        (lambda t: t.__setitem__("x", t["x"].value * u.km), "cannot be converted"),
        (lambda t: t.__setitem__("id", np.zeros(len(t), dtype=np.int64)), "duplicate IDs"),
        (lambda t: t["y"].__setitem__(2, np.nan * u.arcsec), "NaN"),
    ],
)
def test_bad_catalogue_names_column_and_writes_nothing(tmp_path, mutate, match):
    t = _epoch_table()
    mutate(t)
    out = tmp_path / "bad.h5"
    with pytest.raises(InputError, match=match):
        write_catalogue(out, {"e0": t})
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_missing_unit_is_refused():
    t = _epoch_table()
    t["x"] = t["x"].value
    with pytest.raises(InputError, match="column 'x'.*no unit"):
        validate_table(t, CATALOGUE_SPEC, path="cat.csv")


@pytest.mark.parametrize("content", [b"", b"not hdf5 at all"])
def test_unreadable_files(tmp_path, content):
    p = tmp_path / "x.h5"
    p.write_bytes(content)
    with pytest.raises(InputError, match=str(p.name)):
        read_catalogue(p)
    with pytest.raises(InputError, match="does not exist"):
        read_catalogue(tmp_path / "missing.h5")


def test_wrong_kind(tmp_path):
    p = write_product(tmp_path / "f.h5", "frames", arrays={"image": np.zeros((2, 2)) * u.adu})
    with pytest.raises(InputError, match="expected a 'catalogue' product"):
        read_catalogue(p)
    prod = read_product(p, "frames")
    assert prod.arrays["image"].unit == u.adu


def test_atomic_path_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("good")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        Path(tmp).write_text("half")
        raise RuntimeError("crash")
    assert target.read_text() == "good"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_empty_table_spec():
    spec = TableSpec(required={"a": ""}, allow_empty=False, id_column=None)
    with pytest.raises(InputError, match="empty"):
        validate_table(QTable({"a": np.array([], dtype=float)}), spec)


@dataclasses.dataclass(frozen=True)
class _Knobs:
    oversampling: int = 2
    pixel_scale: float = unit_field(7.5, "mas")
    halo: bool = True
    mode: str = "fast"


def test_config_from_mapping():
    k = from_mapping(_Knobs, {"oversampling": 4, "pixel_scale": "0.0075 arcsec"})
    assert k.oversampling == 4 and k.pixel_scale == pytest.approx(7.5)
    with pytest.raises(ConfigError, match="scene.oversampling.*integer"):
        from_mapping(_Knobs, {"oversampling": "x"}, prefix="scene", source="w.toml")
    with pytest.raises(ConfigError, match="did you mean 'halo'"):
        from_mapping(_Knobs, {"hallo": True})
    with pytest.raises(ConfigError, match="pixel_scale"):
        from_mapping(_Knobs, {"pixel_scale": "3 kg"})
