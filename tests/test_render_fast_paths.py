"""The per-process shortcuts of ``simulate frames`` against the library code they replace.

* the halo convolution (numpy transforms) against ``scipy.signal.fftconvolve``;
* ``next_fast_len`` against ``scipy.fft.next_fast_len(real=True)``;
* the products' table header written without astropy's YAML machinery against
  ``astropy.io.misc.hdf5.write_table_hdf5(serialize_meta=True)``, byte for byte, and
  read back by astropy;
* the frames product written from :func:`render_stack` equal to the one written from
  the :class:`Frame` of :func:`render_frame`;
* tables of plain headers read without astropy's YAML against astropy's reader;
* a frames process imports neither ``scipy.fft`` nor ``astropy.io.misc.yaml``.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import astropy.units as u
import h5py
import numpy as np
import pytest
import scipy.fft
import scipy.signal
from astropy.io.misc.hdf5 import read_table_hdf5, write_table_hdf5
from astropy.table import QTable, Table
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core import products
from mavispm.simulate.render.halo_convolution import _convolve_same, next_fast_len

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("shape, ksize", [((40, 57), 9), ((64, 64), 21), ((31, 90), 5)])
def test_halo_convolution_equals_fftconvolve_away_from_the_rim(shape, ksize):
    rng = np.random.default_rng(ksize)
    field = rng.random(shape)
    kernel = rng.random((ksize, ksize))
    got = _convolve_same(field, kernel)
    ref = scipy.signal.fftconvolve(field, kernel, mode="same")
    h = ksize // 2
    inner = (slice(h, shape[0] - h), slice(h, shape[1] - h))
    assert got.shape == field.shape
    np.testing.assert_allclose(got[inner], ref[inner], rtol=0, atol=1e-12 * ref.max())


def test_next_fast_len_matches_scipy():
    for n in range(1, 3001):
        assert next_fast_len(n) == scipy.fft.next_fast_len(n, real=True), n


def _astropy_header_and_data(table: QTable, tmp_path: Path):
    """What astropy writes for the same columns (the path products.py took before)."""
    out = Table()
    for name in table.colnames:
        arr, unit = products._column_values(table[name])
        out[name] = arr
        if unit:
            out[name].unit = unit
    path = tmp_path / "astropy.h5"
    with h5py.File(path, "w") as f:
        write_table_hdf5(out, f, path="t", serialize_meta=True)
    with h5py.File(path) as f:
        return f["t.__table_column_meta__"][()], f["t"][()]


UNITS = [None, u.arcsec, u.mas / u.yr, u.electron, u.electron / u.adu, u.mag, u.K, u.mas**2,
         u.solMass, u.km / u.s, u.pix, u.dimensionless_unscaled, u.erg / (u.s * u.cm**2)]  # fmt: skip
DTYPES = [np.int64, np.int32, np.uint8, np.float64, np.float32, bool, "U3"]


@given(
    cols=st.lists(
        st.tuples(
            st.sampled_from(
                ["id", "x", "y", "n", "x_pix", "flux", "mag", "pm_x", "yes", "null", "a1", "_k"]
            ),
            st.sampled_from(range(len(DTYPES))),
            st.sampled_from(range(len(UNITS))),
        ),
        min_size=1,
        max_size=6,
        unique_by=lambda c: c[0],
    ),
    nrows=st.integers(0, 4),
)
@settings(max_examples=25, deadline=None)
def test_table_header_equals_astropys(tmp_path_factory, cols, nrows):
    tmp_path = tmp_path_factory.mktemp("hdr")
    t = QTable()
    for name, d, k in cols:
        dtype, unit = DTYPES[d], UNITS[k]
        if dtype == "U3":
            t[name] = np.array(["ab", "c", "def", "g"][:nrows], dtype="U3")
        elif unit is None or dtype is bool:
            t[name] = np.arange(nrows).astype(dtype)
        else:
            t[name] = np.arange(nrows).astype(dtype) * unit
    path = tmp_path / "ours.h5"
    with h5py.File(path, "w") as f:
        products._write_table(f, "t", t)
    ref_header, ref_data = _astropy_header_and_data(t, tmp_path)
    with h5py.File(path) as f:
        header, data = f["t.__table_column_meta__"][()], f["t"][()]
    assert list(header) == list(ref_header)
    assert header.dtype == ref_header.dtype
    assert data.dtype == ref_data.dtype
    assert data.tobytes() == ref_data.tobytes()
    back = read_table_hdf5(str(path), path="t")
    for name, d, k in cols:
        if UNITS[k] not in (None, u.dimensionless_unscaled) and DTYPES[d] not in (bool, "U3"):
            assert back[name].unit == UNITS[k]
    # read back without astropy's YAML: the same table as through astropy's reader
    with h5py.File(path) as f:
        fast = products._read_simple_table(f["t"])
        general = products._read_astropy_table_general(f["t"])
    plain = products._simple_table_header({n: products._column_values(t[n]) for n in t.colnames})
    assert (fast is not None) == (plain is not None and all(DTYPES[d] != "U3" for _, d, _ in cols))
    if fast is not None:
        assert fast.colnames == general.colnames
        for name in general.colnames:
            assert type(fast[name]) is type(general[name])
            assert fast[name].dtype == general[name].dtype
            assert getattr(fast[name], "unit", None) == getattr(general[name], "unit", None)
            np.testing.assert_array_equal(np.asarray(fast[name]), np.asarray(general[name]))


def test_plain_header_left_to_astropy_when_yaml_would_quote():
    arr = np.zeros(2)
    assert products._simple_table_header({"yes": (arr, "")}) is None  # a YAML boolean
    assert products._simple_table_header({"a b": (arr, "")}) is None
    assert products._simple_table_header({"x": (arr.astype(complex), "")}) is None
    assert products._simple_table_header({"x": (arr, "1 / s")}) is None  # starts with a digit
    assert products._simple_table_header({"x": (arr, "mas / yr")}) == [
        b"datatype:",
        b"- {name: x, unit: mas / yr, datatype: float64}",
    ]


def test_stack_and_frame_write_the_same_product(tmp_path):
    from render_helpers import random_epoch, tiptilt_halo_optics

    from mavispm.core.catalogue import Catalogue
    from mavispm.core.products import read_product
    from mavispm.simulate.render import cli
    from mavispm.simulate.render.frame import render_frame, render_stack
    from mavispm.simulate.render.scene import scene_from_mapping

    optics = tiptilt_halo_optics()
    scene = scene_from_mapping({"detector": {"nx": 72, "ny": 64, "gain": 1.7}, "nexp": 4})
    t = random_epoch(12, 0.25, 0.2)
    cat = Catalogue(epochs={"e0": t}, attrs={})
    args = (t, 0.0 * u.yr, scene, optics)
    frame = render_frame(*args, cli.epoch_rng(5, "e0"))
    stack = render_stack(*args, cli.epoch_rng(5, "e0"))
    assert np.array_equal(frame.adu, stack.adu)  # the float64 electrons round trip is exact
    assert np.array_equal(frame.image, stack.frame().image)
    a = read_product(cli.write_frame(frame, tmp_path / "a.h5", scene, cat, 5), "frames")
    b = read_product(cli.write_frame(stack, tmp_path / "b.h5", scene, cat, 5), "frames")
    for name in ("image", "saturated"):
        assert np.array_equal(a.arrays[name], b.arrays[name])
    for name in a.tables["truth"].colnames:
        assert np.array_equal(a.tables["truth"][name], b.tables["truth"][name])
    assert a.tables["truth"].colnames == b.tables["truth"].colnames


def test_frames_process_imports_neither_scipy_fft_nor_astropy_yaml(tmp_path):
    """The modules of a warm ``simulate frames`` process, the halo convolution and a
    product with a table written and read back in a fresh interpreter."""
    script = textwrap.dedent(
        f"""
        import sys
        import numpy as np
        import astropy.units as u
        from astropy.table import QTable
        import mavispm.simulate.render.cli
        import mavispm.simulate.render.frame
        import mavispm.simulate.optics.model
        from mavispm.core.products import write_product
        from mavispm.simulate.render.halo_convolution import _convolve_same
        _convolve_same(np.ones((20, 20)), np.ones((5, 5)))
        t = QTable({{"id": np.arange(3), "x": np.ones(3) * u.arcsec}})
        write_product({str(tmp_path / "p.h5")!r}, "frames", tables={{"truth": t}})
        from mavispm.core.products import read_product
        back = read_product({str(tmp_path / "p.h5")!r}, "frames")
        assert back.tables["truth"]["x"].unit == u.arcsec
        print(sorted(m for m in ("scipy.fft", "astropy.io.misc.yaml", "astropy.coordinates")
                     if m in sys.modules))
        """
    )
    env = dict(os.environ)
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "[]"


#: Modules a warm ``mavispm simulate frames`` process must not import: other stages'
#: libraries and scipy / astropy parts the frames path has no use for (each costs
#: 0.03-1 s of a process whose whole budget is ~2 s at 3,500 stars).
FRAMES_FORBIDDEN = (
    "scipy.special", "scipy.fft", "scipy.sparse", "scipy.stats", "scipy.optimize",
    "scipy.interpolate", "scipy.ndimage", "scipy.signal", "photutils", "dynesty",
    "emcee", "matplotlib", "dask", "tqdm", "astropy.coordinates", "astropy.io.misc.yaml",
    "astropy.modeling", "astropy.convolution", "mavispm.measure", "mavispm.dynamics",
)  # fmt: skip


def _write_psf_database(path, n=33, scale=3.75):
    """A 3 x 3 PSF database in the MAVISIM FITS layout: Gaussians 8-10 mas wide."""
    from astropy.io import fits

    off = (np.arange(n) - n // 2) * scale
    yy, xx = np.meshgrid(off, off, indexing="ij")
    hdus = [fits.PrimaryHDU()]
    for yv in (-10.0, 0.0, 10.0):
        for xv in (-10.0, 0.0, 10.0):
            sig = 8.0 + 0.1 * abs(xv)
            img = np.exp(-0.5 * (xx**2 + yy**2) / sig**2)
            h = fits.ImageHDU(img / img.sum())
            h.header.update(XPOS=xv, YPOS=yv, LAMBDA=550e-9, PIXSIZE=scale)
            hdus.append(h)
    fits.HDUList(hdus).writeto(path)


def test_warm_frames_process_imports_no_heavy_modules(tmp_path):
    """A whole ``mavispm simulate frames`` process, run twice on one cache folder: the
    second (warm caches: PSF grid, tip-tilt table, halo, stamp plans) imports none of
    ``FRAMES_FORBIDDEN``, nor the ``scipy.linalg`` package (numba's BLAS check gets
    ``scipy.linalg.cython_blas`` alone, ``core/blas_preload.py``); the first may (it
    computes the caches)."""
    from render_helpers import epoch_table

    from mavispm.core.catalogue import write_catalogue

    _write_psf_database(tmp_path / "psfs.fits")
    rng = np.random.default_rng(4)
    t = epoch_table(*rng.uniform([-0.5, -0.5, 17], [0.5, 0.5, 23], (20, 3)).T)
    write_catalogue(tmp_path / "cat.h5", {"e0": t})
    (tmp_path / "scene.toml").write_text(
        "[detector]\nnx = 160\nny = 160\n"
        f'[optics.psf]\nmode = "file"\nfile = "{tmp_path / "psfs.fits"}"\n'
        'pixel_scale = "3.75 mas"\nstamp_size = "0.12375 arcsec"\n'
    )
    script = textwrap.dedent(
        """
        import atexit, json, sys, runpy
        forbidden = json.loads(sys.argv[1])
        FORBIDDEN_PACKAGES = ("scipy.linalg",)  # its cython_blas is loaded alone
        atexit.register(lambda: print("LOADED", json.dumps(
            sorted(m for m in sys.modules if m.split(".")[0] in forbidden or any(
                m == f or m.startswith(f + ".") for f in forbidden)
                or m in FORBIDDEN_PACKAGES))))
        sys.argv = ["mavispm"] + sys.argv[2:]
        runpy.run_module("mavispm.workflows.cli", run_name="__main__")
        """
    )
    import json

    cmd = [sys.executable, "-c", script, json.dumps(FRAMES_FORBIDDEN), "simulate", "frames",
           str(tmp_path / "cat.h5"), "--scene", str(tmp_path / "scene.toml"), "-o",
           str(tmp_path / "f.h5"), "--cache-dir", str(tmp_path / "cache")]  # fmt: skip
    for _ in range(2):  # cold (computes the caches), then warm
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
    loaded = json.loads(out.stdout.strip().splitlines()[-1].removeprefix("LOADED "))
    assert loaded == []
    assert (tmp_path / "f.h5").exists()
