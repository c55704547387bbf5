"""Rendered pinhole images of the calibration mask, measured with the PSF fitter.

:func:`~mavispm.simulate.optics.calibration_mask.simulate_calibration` draws each
hole's centroid error from a Gaussian of the ``centroid_noise`` setting (MAVISIM's
analytic simulation). :func:`rendered_hole_imager` replaces that draw with the full
chain: the holes, at their true imaged positions (machining error, mask shift and
distortion included), are rendered as point sources of magnitude ``hole_magnitude``
through the scene's PSF, detector and noise (:func:`~mavispm.simulate.render.frame.render_frame`),
and measured by the star fitter (:func:`~mavispm.measure.stars.measure_frame.measure_frame`,
ePSF built from the hole images themselves, started ``perturbation`` pixels off). The
fitter also returns each hole's Cramér-Rao bound, the analytic centroid noise of that
image, to compare with.

The scene's own position terms (distortion, refraction, telescope) are switched off
for the hole frame: the positions handed in already include what the mask sees.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.errors import InputError
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings

__all__ = ["HoleMeasurement", "measure_hole_images", "rendered_hole_imager"]


@dataclasses.dataclass(frozen=True)
class HoleMeasurement:
    """Measured hole images of one exposure of the mask.

    Parameters
    ----------
    x, y : numpy.ndarray
        Measured positions [arcsec] (NaN where the fit failed).
    crlb_x, crlb_y : numpy.ndarray
        Cramér-Rao bound of each hole's position per axis [arcsec].
    """

    x: np.ndarray
    y: np.ndarray
    crlb_x: np.ndarray
    crlb_y: np.ndarray


def _plain_optics(optics):
    """``optics`` with the distortion, refraction and telescope terms switched off."""
    settings = getattr(optics, "settings", None)
    changes = {"distortion": Distortion(DistortionSettings(enabled=False))}
    if settings is not None and dataclasses.is_dataclass(settings):
        off = {}
        for name in ("refraction", "telescope"):
            sub = getattr(settings, name, None)
            if sub is not None and getattr(sub, "enabled", False):
                off[name] = dataclasses.replace(sub, enabled=False)
        if off:
            changes["settings"] = dataclasses.replace(settings, **off)
    return dataclasses.replace(optics, **changes)


def measure_hole_images(
    x,
    y,
    scene,
    optics,
    hole_magnitude: float,
    rng: np.random.Generator,
    measure_settings=None,
) -> HoleMeasurement:
    """Render point sources at ``x, y`` through the scene and measure them.

    Parameters
    ----------
    x, y : array
        True imaged hole positions [arcsec] from the field centre.
    scene : SceneSettings
        Detector, exposure and photometry of the hole frame.
    optics : Optics
        The scene's optics (a dataclass; its position terms are switched off here).
    hole_magnitude : float
        Brightness of every hole in the scene's photometric system [mag].
    rng : numpy.random.Generator
        Source of the photon and read noise and of the start-position offsets.
    measure_settings : MeasureSettings, optional
        Fitter settings (default: fast engine, one constant ePSF, forced start
        0.5 pixel off the true position).

    Returns
    -------
    HoleMeasurement
    """
    from mavispm.measure.stars.measure_frame import measure_frame
    from mavispm.measure.stars.settings import MeasureSettings
    from mavispm.simulate.render.frame import render_frame

    x = np.asarray(x, float)
    y = np.asarray(y, float)
    holes = QTable()
    holes["id"] = np.arange(x.size, dtype=np.int64)
    holes["x"] = x * u.arcsec
    holes["y"] = y * u.arcsec
    holes["mag"] = np.full(x.size, float(hole_magnitude)) * u.mag
    frame = render_frame(holes, 0.0 * u.yr, scene, _plain_optics(optics), rng)
    if len(frame.truth) != x.size:
        raise InputError(
            f"{x.size - len(frame.truth)} of {x.size} calibration holes fall off the "
            f"{scene.detector.nx} x {scene.detector.ny} pixel detector; expected a mask "
            "inside the field",
            column="x",
        )
    settings = measure_settings or MeasureSettings(
        engine="fast",
        psf_variation="constant",
        perturbation=0.5,
        later_epochs="truth",
        crowding_radius=2.0,
    )
    try:
        stars, _, _ = measure_frame(frame, settings, seed=int(rng.integers(2**31)))
    except InputError as exc:
        saturated = int(np.count_nonzero(frame.saturated))
        raise InputError(
            f"the calibration holes (hole_magnitude {hole_magnitude:g}) could not be measured: "
            f"{exc} ({saturated} saturated pixels); expected unsaturated hole images",
            column="hole_magnitude",
        ) from None
    order = np.argsort(np.asarray(stars["id"], np.int64))
    stars = stars[order]
    ok = (np.asarray(stars["flag"]).astype(int) & (1 | 16 | 32)) == 0

    def col(name):
        v = stars[name].to_value(u.arcsec)
        return np.where(ok, v, np.nan)

    return HoleMeasurement(col("x"), col("y"), col("crlb_x"), col("crlb_y"))


def rendered_hole_imager(
    scene, optics, hole_magnitude: float, seed: int = 0, record: list | None = None
) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """An ``imager`` for :func:`~mavispm.simulate.optics.calibration_mask.simulate_calibration`.

    Parameters
    ----------
    scene, optics, hole_magnitude
        As in :func:`measure_hole_images`.
    seed : int
        Seed of the noise of all the mask's exposures.
    record : list, optional
        Receives the :class:`HoleMeasurement` of every exposure.

    Returns
    -------
    callable
        ``imager(x_true, y_true) -> (x_measured, y_measured)`` [arcsec].
    """
    rng = np.random.default_rng(seed)

    def imager(x_true, y_true):
        m = measure_hole_images(x_true, y_true, scene, optics, hole_magnitude, rng)
        if record is not None:
            record.append(m)
        return m.x, m.y

    return imager
