"""Static and dynamic distortion."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mavispm.core.errors import InputError
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings, read_distortion_map


def _disk(n=121, r=15.0):
    g = np.linspace(-r, r, n)
    gx, gy = np.meshgrid(g, g)
    inside = np.hypot(gx, gy) <= r
    return gx[inside], gy[inside]


def test_default_map_matches_paper_numbers():
    d = Distortion(DistortionSettings())
    dx, dy = d.displacement(np.array([15.0, 0.0, 15.0]), np.array([-15.0, 0.0, 0.0]))
    amp = np.hypot(dx, dy) * 1000
    assert amp[0] == pytest.approx(0.44, rel=1e-9)
    assert amp[1] == 0.0
    assert amp[2] == pytest.approx(0.156, abs=0.01)
    x, y = _disk()
    ddx, ddy = d.displacement(x, y)
    assert np.std(np.hypot(ddx, ddy) * 1000) == pytest.approx(0.05, abs=0.01)


def test_disabled_is_exactly_zero():
    d = Distortion(DistortionSettings(enabled=False, dynamic=True, dynamic_amplitude=5.0))
    dx, dy = d.displacement(np.array([3.0, -7.0]), np.array([1.0, 9.0]), epoch=3.0)
    assert not d.enabled
    assert np.all(dx == 0) and np.all(dy == 0)


def test_dynamic_amplitude_zero_is_identity():
    x, y = _disk(31)
    stat = Distortion(DistortionSettings())
    dyn0 = Distortion(DistortionSettings(dynamic=True, dynamic_amplitude=0.0))
    for epoch in (0.0, 1.5, 10.0):
        a = stat.displacement(x, y, epoch)
        b = dyn0.displacement(x, y, epoch)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
    none = Distortion(DistortionSettings(static="none", dynamic=True, dynamic_amplitude=0.0))
    assert np.all(none.displacement(x, y, 2.0)[0] == 0)


def test_dynamic_term_rms_and_epoch_dependence():
    s = DistortionSettings(
        static="none", dynamic=True, dynamic_amplitude=1.0, dynamic_terms=("scale",)
    )
    d = Distortion(s)
    x, y = _disk()
    c = d.dynamic_coefficients(2.0)["scale"]
    dx, dy = d.displacement(x, y, 2.0)
    rms = np.sqrt(np.mean(dx**2 + dy**2)) * 1000
    assert rms == pytest.approx(abs(c), rel=0.02)
    # deterministic per epoch, different between epochs
    assert d.dynamic_coefficients(2.0) == Distortion(s).dynamic_coefficients(2.0)
    assert d.dynamic_coefficients(2.0) != d.dynamic_coefficients(3.0)


def test_polynomial_and_file_maps_agree(tmp_path):
    coeff_x = ((1, 0, 0.2), (0, 2, -0.1))
    coeff_y = ((0, 1, 0.3),)
    poly = Distortion(
        DistortionSettings(static="polynomial", coefficients_x=coeff_x, coefficients_y=coeff_y)
    )
    g = np.linspace(-20, 20, 9)
    gx, gy = np.meshgrid(g, g)
    dx, dy = poly.static_displacement(gx, gy)
    rows = np.stack([gx.ravel(), gy.ravel(), dx.ravel(), dy.ravel()], -1)
    csv_path = tmp_path / "map.csv"
    np.savetxt(csv_path, rows, delimiter=",", header="x,y,dx,dy", comments="")
    txt_path = tmp_path / "map.txt"
    np.savetxt(txt_path, rows, header="x y dx dy (arcsec, arcsec, mas, mas)")
    for path in (csv_path, txt_path):
        d = Distortion(DistortionSettings(static="file", file=str(path)))
        # linear terms are reproduced exactly by bilinear interpolation at the nodes
        fx, fy = d.static_displacement(gx, gy)
        np.testing.assert_allclose(fx, dx, atol=1e-12)
        np.testing.assert_allclose(fy, dy, atol=1e-12)
        mx, my = d.static_displacement(np.array([2.5]), np.array([0.0]))
        assert my[0] == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize(
    "content, message",
    [
        ("x,y,dx\n0,0,1\n", "lacks columns"),
        ("x,y,dx,dy\n0,0,nan,0\n1,0,0,0\n0,1,0,0\n1,1,0,0\n", "NaN"),
        ("x,y,dx,dy\n0,0,0,0\n1,0,0,0\n0,1,0,0\n5,5,0,0\n", "regular grid"),
    ],
)
def test_bad_map_files_named(tmp_path, content, message):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as err:
        read_distortion_map(path)
    assert "bad.csv" in str(err.value)


def test_missing_map_file(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        Distortion(DistortionSettings(static="file", file=str(tmp_path / "nope.txt")))


@settings(max_examples=30, deadline=None)
@given(
    x=st.lists(st.floats(-40, 40), min_size=1, max_size=20),
    epoch=st.floats(-50, 50),
    amplitude=st.floats(0, 5),
)
def test_hypothesis_dynamic_finite_and_zero_amplitude_identity(x, epoch, amplitude):
    xs = np.asarray(x)
    ys = xs[::-1].copy()
    dyn = Distortion(
        DistortionSettings(
            dynamic=True, dynamic_amplitude=amplitude, dynamic_terms=("scale", "rotation", "cubic")
        )
    )
    dx, dy = dyn.displacement(xs, ys, epoch)
    assert np.all(np.isfinite(dx)) and np.all(np.isfinite(dy))
    c = dyn.dynamic_coefficients(epoch)
    assert all(abs(v) <= 10 * amplitude for v in c.values())
    zero = Distortion(DistortionSettings(dynamic=True, dynamic_amplitude=0.0))
    sx, sy = Distortion(DistortionSettings()).displacement(xs, ys)
    zx, zy = zero.displacement(xs, ys, epoch)
    np.testing.assert_array_equal(sx, zx)
    np.testing.assert_array_equal(sy, zy)
