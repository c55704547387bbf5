"""The astrometric calibration mask: recovery of injected distortions against analytic truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mavispm.core.errors import ConfigError, InputError
from mavispm.simulate.optics.calibration_cli import load_mask_settings, run_calibration
from mavispm.simulate.optics.calibration_mask import (
    CalibrationMaskSettings,
    mask_holes,
    read_recovered_distortion,
    simulate_calibration,
)
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings
from mavispm.workflows.cli import main

#: an injected distortion: every power up to degree 4, in mas (u, v = x, y / 15")
POLY_X = ((1, 0, 0.3), (0, 1, -0.1), (2, 0, 0.05), (1, 1, 0.2), (3, 0, -0.12), (2, 2, 0.07))
POLY_Y = ((0, 1, 0.25), (1, 0, 0.08), (0, 2, -0.04), (1, 2, 0.15), (0, 4, 0.09), (3, 1, -0.05))


def _poly_distortion(**extra) -> Distortion:
    return Distortion(
        DistortionSettings(
            static="polynomial", coefficients_x=POLY_X, coefficients_y=POLY_Y, **extra
        )
    )


def _disk(n=41):
    axis = np.linspace(-15, 15, n)
    xx, yy = np.meshgrid(axis, axis)
    inside = np.hypot(xx, yy) <= 15
    return xx[inside], yy[inside]


@pytest.mark.parametrize("method", ["differential", "direct"])
def test_noise_free_recovery_is_exact(method):
    """No hole errors, no noise: the polynomial is recovered to rounding (up to a constant)."""
    d = _poly_distortion()
    mask = CalibrationMaskSettings(
        hole_position_error=0.0, centroid_noise=0.0, order=4, method=method
    )
    res = simulate_calibration(d, mask)
    assert res.residual_rms < 1e-9
    # coefficient by coefficient against the injected ones (the analytic truth)
    truth_x = {(i, j): c for i, j, c in POLY_X}
    for (i, j), c in zip(res.recovered.terms, res.recovered.coefficients_x):
        assert c == pytest.approx(truth_x.get((i, j), 0.0), abs=1e-9)


def test_differential_method_cancels_hole_errors_direct_does_not():
    """10 micron machining errors (17 mas on the sky): the differential fit ignores them,
    the direct fit aliases them as sigma sqrt(P/N) (least squares on N holes, P terms)."""
    d = _poly_distortion()
    err_mm = 0.01
    diff = simulate_calibration(
        d, CalibrationMaskSettings(hole_position_error=err_mm, centroid_noise=0.0, order=4)
    )
    assert diff.residual_rms < 1e-3  # second order only: gradient x hole error
    n, order = 35, 2
    direct = [
        simulate_calibration(
            d,
            CalibrationMaskSettings(
                hole_position_error=err_mm,
                centroid_noise=0.0,
                order=order,
                method="direct",
                seed=seed,
                pitch=30.0 / (n - 1) / (1000 / 582),  # holes span the whole 30" square
                n_holes=n,
            ),
        ).residual_rms
        for seed in range(8)
    ]
    sigma_mas = err_mm * 1000 / 582 * 1000
    p = (order + 1) * (order + 2) // 2  # with the constant
    expected = sigma_mas * np.sqrt(2 * p / n**2)  # both axes
    # the disk inside the hole square has slightly lower leverage than the square
    assert 0.5 * expected < np.sqrt(np.mean(np.square(direct))) < 1.2 * expected


def test_differential_noise_scales_inversely_with_the_shift():
    """Centroid noise enters through displacement / shift: doubling the shift halves it."""
    d = Distortion(DistortionSettings(static="none"))
    r = [
        simulate_calibration(
            d, CalibrationMaskSettings(hole_position_error=0.0, shift=s, order=3)
        ).residual_rms
        for s in (0.2, 0.4, 0.8)
    ]
    assert r[0] / r[1] == pytest.approx(2.0, rel=0.1)
    assert r[1] / r[2] == pytest.approx(2.0, rel=0.1)
    # and linearly with the centroid noise
    r10 = simulate_calibration(
        d, CalibrationMaskSettings(hole_position_error=0.0, centroid_noise=0.1, order=3)
    ).residual_rms
    assert r10 / r[0] == pytest.approx(10.0, rel=1e-6)


def test_calibration_sees_the_dynamic_term_of_its_epoch(tmp_path):
    """Calibrated at epoch 0, the frames of epoch 10 keep D_dyn(10) - D_dyn(0) exactly."""
    kw = dict(static="none", dynamic=True, dynamic_amplitude=0.3, dynamic_seed=4)
    mask = CalibrationMaskSettings(hole_position_error=0.0, centroid_noise=0.0, order=3)
    out = tmp_path / "calib.h5"
    run_calibration(DistortionSettings(**kw), mask, out)
    calibrated = Distortion(DistortionSettings(**kw, calibration=str(out)))
    plain = Distortion(DistortionSettings(**kw))
    x, y = _disk()
    for epoch in (0.0, 10.0):
        cx, cy = calibrated.displacement(x, y, epoch)
        ex = plain.displacement(x, y, epoch)[0] - plain.displacement(x, y, 0.0)[0]
        ey = plain.displacement(x, y, epoch)[1] - plain.displacement(x, y, 0.0)[1]
        assert np.allclose(cx, ex, atol=1e-12) and np.allclose(cy, ey, atol=1e-12)


def test_calibrated_default_map_leaves_only_the_noise(tmp_path):
    """The default cubic map after a noise-free calibration: nothing left."""
    out = tmp_path / "c.h5"
    mask = CalibrationMaskSettings(hole_position_error=0.0, centroid_noise=0.0, order=3)
    run_calibration(DistortionSettings(), mask, out)
    d = Distortion(DistortionSettings(calibration=str(out)))
    x, y = _disk()
    dx, dy = d.displacement(x, y)
    assert np.max(np.hypot(dx, dy)) < 1e-12  # arcsec
    rec = read_recovered_distortion(out)
    assert rec.terms[0] == (1, 0)


def test_mask_geometry():
    mask = CalibrationMaskSettings(n_holes=4, pitch=1.0, mask_scale=2.0, order=1)
    x, y = mask_holes(mask)
    assert sorted(set(x)) == [-3.0, -1.0, 1.0, 3.0]
    assert x.size == 16 and np.mean(y) == 0


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    order=st.integers(1, 8),
    n_holes=st.integers(8, 40),
    err=st.floats(0, 0.05),
    noise=st.floats(0, 1),
    shift=st.floats(0.01, 2.0),
    method=st.sampled_from(["differential", "direct"]),
)
def test_any_valid_mask_gives_finite_reproducible_results(
    order, n_holes, err, noise, shift, method
):
    try:
        mask = CalibrationMaskSettings(
            order=order,
            n_holes=n_holes,
            hole_position_error=err,
            centroid_noise=noise,
            shift=shift,
            method=method,
        )
    except ValueError as exc:  # a refusal names the setting
        assert any(k in str(exc) for k in ("n_holes", "order", "holes"))
        return
    d = Distortion(DistortionSettings())
    a = simulate_calibration(d, mask)
    b = simulate_calibration(d, mask)
    assert np.isfinite(a.residual_rms) and a.residual_rms == b.residual_rms


def test_cli_writes_product_and_refuses_bad_input(tmp_path, capsys):
    out = tmp_path / "c.h5"
    assert main(["simulate", "calibration", "-o", str(out), "--order", "3"]) == 0
    assert "residual after calibration" in capsys.readouterr().out
    assert out.exists()

    bad = tmp_path / "bad.h5"
    assert main(["simulate", "calibration", "-o", str(bad), "--order", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "order" in err and len(err.splitlines()) == 1
    toml = tmp_path / "mask.toml"
    toml.write_text("[calibration]\nholes = 3\n")
    assert main(["simulate", "calibration", "--mask", str(toml), "-o", str(bad)]) == 2
    assert "calibration.holes" in capsys.readouterr().err
    toml.write_text("[calibration\n")
    assert main(["simulate", "calibration", "--mask", str(toml), "-o", str(bad)]) == 2
    assert "invalid TOML" in capsys.readouterr().err
    assert not bad.exists()


def test_mask_settings_errors(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_mask_settings(tmp_path / "none.toml")
    with pytest.raises(ConfigError, match="calibration.*method"):
        load_mask_settings(None, {"method": "guess"})
    with pytest.raises(ConfigError, match="n_holes"):
        load_mask_settings(None, {"n_holes": 3, "order": 6})


def test_translation_error_becomes_a_linear_term():
    """An unknown error e in a mask translation s is fitted as the linear map e * p / s."""
    from mavispm.simulate.optics.calibration_mask import (
        CalibrationMaskSettings,
        simulate_calibration,
    )
    from mavispm.simulate.optics.distortion import Distortion, DistortionSettings

    mask = CalibrationMaskSettings(
        hole_position_error=0.0, centroid_noise=0.0, translation_error=0.002, seed=3, order=4
    )
    result = simulate_calibration(Distortion(DistortionSettings(enabled=False)), mask)
    e = result.translation_errors * 1000.0  # mas; rows: x- and y-translation
    assert np.all(np.abs(e) > 0)
    s = mask.shift * mask.mask_scale  # arcsec
    gx, gy = np.meshgrid(np.linspace(-15, 15, 7), np.linspace(-15, 15, 7))
    dx, dy = result.recovered.displacement_mas(gx, gy)
    assert np.allclose(dx, (e[0, 0] * gx + e[1, 0] * gy) / s, atol=1e-9)
    assert np.allclose(dy, (e[0, 1] * gx + e[1, 1] * gy) / s, atol=1e-9)
    # 0.002 mm is 3.4 mas on the sky: a 0.15% scale error, 26 mas at 15"
    assert np.max(np.abs(dx)) > 5.0
    # without the error the same draw of everything else recovers nothing
    clean = simulate_calibration(
        Distortion(DistortionSettings(enabled=False)),
        CalibrationMaskSettings(hole_position_error=0.0, centroid_noise=0.0, seed=3, order=4),
    )
    assert np.abs(clean.recovered.displacement_mas(gx, gy)[0]).max() < 1e-9
