"""External inputs (N-body snapshots, MAVISIM lists), bad input, the stage and its CLI."""

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable, Table
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.catalogue import read_catalogue
from mavispm.core.errors import ConfigError, InputError
from mavispm.simulate.cluster.cli import run_stage, validate_settings
from mavispm.simulate.cluster.generator import sample_stars
from mavispm.simulate.cluster.settings import ClusterSettings
from mavispm.workflows.cli import main


@pytest.fixture(scope="module")
def snapshot():
    """A 3-D snapshot with units (drawn from the model, 40" field)."""
    stars, _ = sample_stars(
        ClusterSettings(n_stars=400, field_size=40.0, include_remnants=False), 9
    )
    t = QTable()
    t["id"] = stars["id"] + 1000
    for k in ("x", "y", "z"):
        t[k] = stars[k] * u.pc
    for k in ("vx", "vy", "vz"):
        t[k] = stars[k] * u.km / u.s
    t["mass"] = stars["mass"] * u.solMass
    return t


def _external(path, **kw):
    return {"external": {"path": str(path), **kw}}


@pytest.mark.parametrize("ext", ["ecsv", "fits", "h5", "csv"])
def test_snapshot_formats_round_trip(tmp_path, snapshot, ext):
    path = tmp_path / f"snap.{ext}"
    extra = {}
    if ext == "csv":
        Table(snapshot).write(path, format="ascii.csv")  # CSV drops the units
        extra["column_units"] = {
            "x": "pc",
            "y": "pc",
            "z": "pc",
            "vx": "km/s",
            "vy": "km/s",
            "vz": "km/s",
            "mass": "solMass",
        }
    elif ext == "h5":
        snapshot.write(path, path="stars", serialize_meta=True)
        extra["hdf5_path"] = "stars"
    else:
        snapshot.write(path)
    out = run_stage({**_external(path, **extra)}, tmp_path / "cat.h5", seed=0)
    cat = read_catalogue(out)
    t = cat.epochs["e0"]
    inside = (np.abs(snapshot["x"].value) <= 0.5 * 32 * 4.6 / 206.2648) & (
        np.abs(snapshot["y"].value) <= 0.5 * 32 * 4.6 / 206.2648
    )
    assert len(t) == inside.sum()
    row = np.flatnonzero(inside)[0]
    got = t[t["id"] == snapshot["id"][row]]
    assert got["x"][0].to_value(u.arcsec) == pytest.approx(
        snapshot["x"][row].value / 4.6 * 206.264806, rel=1e-6
    )
    assert got["pm_y"][0].to_value(u.mas / u.yr) == pytest.approx(
        snapshot["vy"][row].value / (4.740470463 * 4.6), rel=1e-6
    )
    assert got["vz"][0].value == pytest.approx(snapshot["vz"][row].value)


def _mavisim_file(path, pm_values):
    rows = ["Star RA Dec X Y Flux PM_X PM_Y"]
    for i, (pmx, pmy) in enumerate(pm_values):
        rows.append(
            f"{i + 1} 154.40 -46.41 {0.5 * i:.3f} {-0.3 * i:.3f} {1000.0 * (i + 1):.1f} {pmx} {pmy}"
        )
    path.write_text("\n".join(rows) + "\n")
    return path


def test_mavisim_list_pm_convention(tmp_path):
    path = _mavisim_file(tmp_path / "src.txt", [(0.002, -0.001), (0.0005, 0.0)])
    common = {"format": "mavisim", "flux_zeropoint": 30.0}
    out = run_stage(
        _external(path, pm_convention="arcsec_per_baseline", **common), tmp_path / "a.h5", 0
    )
    t = read_catalogue(out).epochs["e0"]
    np.testing.assert_allclose(t["pm_x"].to_value(u.mas / u.yr), [0.2, 0.05])  # 2 mas over 10 yr
    np.testing.assert_allclose(t["mag"].value, 30.0 - 2.5 * np.log10([1000.0, 2000.0]))
    out = run_stage(_external(path, pm_convention="mas_per_yr", **common), tmp_path / "b.h5", 0)
    np.testing.assert_allclose(read_catalogue(out).epochs["e0"]["pm_x"].value, [0.002, 0.0005])
    with pytest.raises(ConfigError, match="pm_convention"):
        validate_settings(_external(path, **common))


def _broken(kind, snapshot, tmp_path):
    t = snapshot.copy()
    path = tmp_path / "bad.ecsv"
    if kind == "missing":
        t.rename_column("vx", "v_x")
    elif kind == "wrong_unit":
        t["x"] = t["x"].value * u.km / u.s
    elif kind == "nan":
        t["vy"][3] = np.nan * u.km / u.s
    elif kind == "duplicate":
        t["id"][5] = t["id"][6]
    elif kind == "no_unit":
        t = Table(t)
        t["z"].unit = None
    if kind == "empty":
        path.write_text("")
    elif kind == "unreadable":
        path = tmp_path / "bad.fits"
        path.write_bytes(b"\x00garbage" * 50)
    else:
        t.write(path)
    return path


@pytest.mark.parametrize(
    "kind, pattern",
    [
        ("missing", "column 'vx'.*missing.*v_x"),
        ("wrong_unit", "column 'x'.*cannot be converted"),
        ("nan", "column 'vy'.*NaN"),
        ("duplicate", "column 'id'.*duplicate"),
        ("no_unit", "column 'z'.*no unit"),
        ("empty", "empty"),
        ("unreadable", "cannot read"),
    ],
)
def test_bad_external_input_is_refused_without_output(tmp_path, snapshot, kind, pattern):
    path = _broken(kind, snapshot, tmp_path)
    out = tmp_path / "cat.h5"
    with pytest.raises(InputError, match=pattern) as err:
        run_stage(_external(path), out, seed=0)
    assert str(path) in str(err.value)
    assert not out.exists()
    assert list(tmp_path.glob("*.tmp")) == []


def test_settings_errors_name_the_key():
    with pytest.raises(ConfigError, match="n_strs.*n_stars"):
        validate_settings({"n_strs": 10})
    with pytest.raises(ConfigError, match="field_size"):
        validate_settings({"field_size": "3 kg"})
    with pytest.raises(ConfigError, match="An & Evans"):
        validate_settings({"imbh_mass": 1500, "cusp_gamma": 0.2})
    with pytest.raises(ConfigError, match="preset"):
        validate_settings({"preset": "ngc9999"})
    s = validate_settings({"field_size": "0.5 arcmin", "imbh_mass": 1500})
    assert s.field_size == pytest.approx(30.0)


def test_cli_writes_catalogue_with_model_truth(tmp_path, capsys):
    out = tmp_path / "cluster.h5"
    argv = ["simulate", "cluster", "--preset", "ngc3201", "--imbh-mass", "1500", "--epochs", "0,10"]
    assert main([*argv, "--seed", "1", "--n-stars", "500", "-o", str(out)]) == 0
    cat = read_catalogue(out)
    assert list(cat.epochs) == ["e0", "e1"]
    assert cat.attrs["imbh_mass"] == 1500 * u.solMass
    assert cat.attrs["distance"] == 4.6 * u.kpc
    assert cat.attrs["field_size"] == 30 * u.arcsec
    assert cat.attrs["seed"] == 1
    import json

    params = cat.attrs["model_params"]
    params = json.loads(params) if isinstance(params, str) else params
    assert params["bh_mass"] == 1500 and params["cusp_gamma"] == 1.55
    assert 5.0 <= params["central_dispersion_cored"] <= 6.0  # NGC 3201-like


def test_cli_refuses_cored_tracer_around_imbh(tmp_path, capsys):
    out = tmp_path / "c.h5"
    code = main(["simulate", "cluster", "--imbh-mass", "1500", "--cusp-gamma", "0", "-o", str(out)])
    assert code == 2
    assert "An & Evans" in capsys.readouterr().err
    assert not out.exists()


def test_same_seed_same_catalogue(tmp_path):
    a = run_stage({"n_stars": 300}, tmp_path / "a.h5", seed=7)
    b = run_stage({"n_stars": 300}, tmp_path / "b.h5", seed=7)
    c = run_stage({"n_stars": 300}, tmp_path / "c.h5", seed=8)
    ta, tb, tc = (read_catalogue(p).epochs["e1"] for p in (a, b, c))
    np.testing.assert_array_equal(ta["x"], tb["x"])
    np.testing.assert_array_equal(ta["pm_y"], tb["pm_y"])
    assert not np.array_equal(ta["x"][:100], tc["x"][:100])


def test_cli_reads_toml_and_names_bad_keys(tmp_path, capsys):
    good = tmp_path / "study.toml"
    good.write_text('[cluster]\nn_stars = 200\nfield_size = "0.25 arcmin"\nepochs = [0, 3]\n')
    out = tmp_path / "ok.h5"
    assert main(["simulate", "cluster", "--config", str(good), "-o", str(out)]) == 0
    cat = read_catalogue(out)
    assert cat.attrs["field_size"] == 15 * u.arcsec
    assert cat.epochs["e1"].meta["epoch"] == 3 * u.yr
    bad = tmp_path / "bad.toml"
    bad.write_text("[cluster]\nimbh_mas = 1500\n")
    assert main(["simulate", "cluster", "--config", str(bad), "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err
    assert "bad.toml" in err and "imbh_mas" in err and "imbh_mass" in err
    assert not (tmp_path / "x.h5").exists()


def test_impossible_geometry_is_a_clear_error(tmp_path):
    out = tmp_path / "far.h5"
    with pytest.raises(ConfigError, match="offset"):
        run_stage({"offset_x": "30 arcmin", "tracer": "plummer"}, out, seed=0)
    assert not out.exists()


@settings(max_examples=25, deadline=None)
@given(
    drop=st.sets(st.sampled_from(["x", "y", "z", "vx", "vy", "vz"]), max_size=3),
    junk_row=st.integers(0, 9),
    junk=st.sampled_from([np.nan, np.inf, -np.inf, None]),
)
def test_mangled_snapshots_raise_input_errors_only(tmp_path_factory, drop, junk_row, junk):
    rng = np.random.default_rng(junk_row)
    t = QTable({k: rng.normal(size=10) * 0.1 * u.pc for k in ("x", "y", "z")})
    for k in ("vx", "vy", "vz"):
        t[k] = rng.normal(size=10) * u.km / u.s
    t["mass"] = np.full(10, 0.5) * u.solMass
    if junk is not None:
        t["vz"][junk_row] = junk * u.km / u.s
    t.remove_columns(sorted(drop))
    path = tmp_path_factory.mktemp("mangled") / "snap.ecsv"
    t.write(path)
    out = path.with_suffix(".h5")
    if not drop and junk is None:
        assert run_stage(_external(path), out, seed=0).exists()
        return
    with pytest.raises(InputError, match="column '(x|y|z|vx|vy|vz)'"):
        run_stage(_external(path), out, seed=0)
    assert not out.exists()
