"""Astrometric calibration mask: a pinhole grid imaged through the distortion, and its recovery.

MAVIS will calibrate the static distortion of its imager with a pinhole mask in the
focal plane of the AO module (paper section 2.3; the MAVISIM 1.1 package simulates the
same procedure in ``mavisim.astromsim.AstromCalibSim``). This module simulates that
calibration and the distortion it leaves behind.

The mask
    ``n_holes x n_holes`` holes on a square grid of pitch ``pitch`` [mm] at the input
    plane, ``mask_scale`` [arcsec/mm] on the sky, centred on the field. Each hole is
    machined with a random position error of RMS ``hole_position_error`` [mm] per axis,
    which the observer does not know.

The images
    The mask is imaged at its nominal position and after known translations by
    ``shift`` [mm] along x and along y (the differential method). The hole at true
    position ``q`` (arcsec) is seen at ``q + s + D(q + s)``, with ``s`` the translation
    and ``D`` the distortion being calibrated (static plus the dynamic term of the
    calibration epoch), and is measured with a Gaussian centroid noise of RMS
    ``centroid_noise`` [mas] per axis and image. Each translation misses its nominal
    value by a random error of RMS ``translation_error`` [mm] per axis, which the
    observer does not know: a constant difference between two images that the fit can
    only take as a linear (scale, rotation, shear) term, ``error / shift`` per unit of
    field.

The recovery
    ``D`` is modelled as a bivariate polynomial of total degree 1 to ``order`` in
    ``u, v = x / 15", y / 15"`` for each axis. The differential method fits the
    measured displacement of every hole between the shifted and unshifted images,
    ``D(p + s) - D(p)`` evaluated at the nominal position ``p``: the unknown hole errors
    cancel, and so does any constant offset of the mask. The direct method fits the
    measured position minus the nominal position, in which the hole errors alias into
    the recovered distortion. A constant offset is not observable by the differential
    method and is irrelevant to astrometry (it is absorbed by the alignment of every
    epoch), so the recovered and residual distortions are quoted with their mean over
    the science field removed.

The residual distortion ``D - D_hat`` is what an observer who applies the calibration
still suffers; ``mavispm simulate frames`` applies it when the scene's distortion names
a calibration product (``[scene.optics.distortion] calibration``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from mavispm.core.config import unit_field
from mavispm.simulate.optics.distortion import SCIENCE_RADIUS, Distortion

__all__ = [
    "CalibrationMaskSettings",
    "CalibrationResult",
    "PolynomialDistortion",
    "mask_holes",
    "polynomial_terms",
    "read_recovered_distortion",
    "simulate_calibration",
    "write_calibration",
]


@dataclass(frozen=True)
class CalibrationMaskSettings:
    """The calibration mask and its measurement (TOML table ``[calibration]``).

    Parameters
    ----------
    pitch : float
        Hole spacing at the input plane [mm]; 0.5 mm as in MAVISIM 1.1.
    n_holes : int
        Holes per side of the square grid; 35 at 0.5 mm covers the 30" field (the
        holes MAVISIM 1.1 keeps inside +-15").
    mask_scale : float
        Plate scale at the input plane [arcsec/mm]; MAVISIM 1.1's 1000/582.
    hole_position_error : float
        RMS machining error of each hole per axis [mm].
    shift : float
        Translation of the mask for the differential method [mm], applied along x
        and, in a third image, along y.
    translation_error : float
        RMS error of each translation per axis [mm] (unknown to the observer).
    imaging : {"analytic", "rendered"}
        "analytic": true positions plus Gaussian ``centroid_noise``; "rendered": every
        exposure rendered through a scene and measured by the PSF fitter
        (:mod:`mavispm.simulate.optics.pinhole_imaging`; needs the scene).
    hole_magnitude : float
        Brightness of each hole image with ``imaging = "rendered"`` [mag].
    centroid_noise : float
        RMS centroid noise of one hole in one image, per axis [mas].
    order : int
        Highest total degree of the recovered polynomial (1 to 10).
    method : {"differential", "direct"}
        Fit the displacements between shifted images (hole errors cancel) or the
        positions against the nominal grid (hole errors alias into the result).
    epoch : float
        Epoch of the calibration [yr], selecting the dynamic distortion term that
        the mask sees.
    seed : int
        Seed of the hole errors and centroid noise.
    """

    pitch: float = unit_field(0.5, "mm", "hole spacing at the input plane")
    n_holes: int = 35
    mask_scale: float = unit_field(1000.0 / 582.0, "arcsec / mm", "input-plane scale")
    hole_position_error: float = unit_field(0.01, "mm", "RMS machining error per axis")
    shift: float = unit_field(0.2, "mm", "translation of the differential method")
    translation_error: float = unit_field(0.0, "mm", "RMS error of each translation")
    imaging: Literal["analytic", "rendered"] = "analytic"
    hole_magnitude: float = unit_field(18.0, "mag", "hole images when rendered")
    centroid_noise: float = unit_field(0.01, "mas", "RMS per hole, image and axis")
    order: int = 6
    method: Literal["differential", "direct"] = "differential"
    epoch: float = unit_field(0.0, "yr", "calibration epoch")
    seed: int = 0

    def __post_init__(self):
        if not 2 <= self.n_holes <= 1000:
            raise ValueError(f"n_holes must be 2 to 1000, got {self.n_holes}")
        if not 1 <= self.order <= 10:
            raise ValueError(f"order must be 1 to 10, got {self.order}")
        n_terms = len(polynomial_terms(self.order))
        if self.n_holes**2 < 2 * n_terms:
            raise ValueError(
                f"n_holes = {self.n_holes} cannot constrain a polynomial of order = "
                f"{self.order} ({n_terms} terms per axis); use more holes or a lower order"
            )
        for name in ("pitch", "mask_scale", "shift"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0")
        for name in ("hole_position_error", "centroid_noise", "translation_error"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be >= 0")
        if self.imaging not in ("analytic", "rendered"):
            raise ValueError(f"imaging must be 'analytic' or 'rendered', got {self.imaging!r}")
        if not -5 <= self.hole_magnitude <= 35:
            raise ValueError(f"hole_magnitude must be -5 to 35 mag, got {self.hole_magnitude}")
        if self.method not in ("differential", "direct"):
            raise ValueError(f"method must be 'differential' or 'direct', got {self.method!r}")
        if self.shift * self.mask_scale > 0.5 * SCIENCE_RADIUS:
            raise ValueError("shift must be under half the science radius on the sky")

    @property
    def pitch_arcsec(self) -> float:
        """Hole spacing on the sky [arcsec]."""
        return self.pitch * self.mask_scale


def polynomial_terms(order: int) -> list[tuple[int, int]]:
    """Powers ``(i, j)`` of ``u^i v^j`` with total degree 1 to ``order``, by degree.

    Parameters
    ----------
    order : int
        Highest total degree.

    Returns
    -------
    list of tuple of int
        The powers, degree by degree.
    """
    return [(d - j, j) for d in range(1, order + 1) for j in range(d + 1)]


def _design(x, y, terms) -> np.ndarray:
    """Columns ``u^i v^j`` at field positions (arcsec); shape (n, len(terms))."""
    u = np.asarray(x, float) / SCIENCE_RADIUS
    v = np.asarray(y, float) / SCIENCE_RADIUS
    return np.stack([u**i * v**j for i, j in terms], axis=-1)


@dataclass(frozen=True)
class PolynomialDistortion:
    """A displacement field ``d = sum c u^i v^j`` per axis [mas], ``u, v = x, y / 15"``.

    Parameters
    ----------
    terms : tuple of (int, int)
        Powers ``(i, j)``.
    coefficients_x, coefficients_y : numpy.ndarray
        Coefficients [mas], one per term.
    offset_x, offset_y : float
        Constant added to each axis [mas] (used to quote fields with zero mean).
    """

    terms: tuple[tuple[int, int], ...]
    coefficients_x: np.ndarray
    coefficients_y: np.ndarray
    offset_x: float = 0.0
    offset_y: float = 0.0

    def displacement_mas(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Displacement [mas] at field positions ``x, y`` [arcsec].

        Parameters
        ----------
        x, y : array_like
            Field positions [arcsec].

        Returns
        -------
        dx, dy : ndarray
            Displacements [mas], offsets included.
        """
        a = _design(x, y, self.terms)
        return a @ self.coefficients_x + self.offset_x, a @ self.coefficients_y + self.offset_y


@dataclass(frozen=True)
class CalibrationResult:
    """What the calibration recovered and what it leaves behind.

    Parameters
    ----------
    settings : CalibrationMaskSettings
    recovered : PolynomialDistortion
        The recovered distortion, zero mean over the science field.
    holes : dict of str to numpy.ndarray
        Per hole: ``x, y`` nominal position [arcsec], ``x_true, y_true`` machined
        position [arcsec], ``dx_meas, dy_meas`` the fitted quantity per axis [mas]
        (differential: mean of the two shifts' residual displacement; direct: measured
        minus nominal position).
    residual_rms : float
        RMS over the science field (r <= 15") of the residual displacement (both axes
        together, ``sqrt(<dx^2 + dy^2>)``) with its mean removed [mas].
    input_rms : float
        The same for the input distortion [mas].
    translation_errors : numpy.ndarray (2, 2)
        Errors of the x- and y-translations (rows), per axis (columns) [arcsec].
    """

    settings: CalibrationMaskSettings
    recovered: PolynomialDistortion
    holes: dict
    residual_rms: float
    input_rms: float
    translation_errors: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))


def mask_holes(settings: CalibrationMaskSettings) -> tuple[np.ndarray, np.ndarray]:
    """Nominal hole positions [arcsec] on the sky, centred on the field (flattened).

    Parameters
    ----------
    settings : CalibrationMaskSettings
        ``n_holes`` per side and ``pitch_arcsec``.

    Returns
    -------
    x, y : ndarray
        Positions [arcsec] of the square grid of holes.
    """
    n = settings.n_holes
    axis = (np.arange(n) - (n - 1) / 2.0) * settings.pitch_arcsec
    xx, yy = np.meshgrid(axis, axis)
    return xx.ravel(), yy.ravel()


def _science_grid(n: int = 61) -> tuple[np.ndarray, np.ndarray]:
    """A regular grid of points inside the science field (r <= 15")."""
    axis = np.linspace(-SCIENCE_RADIUS, SCIENCE_RADIUS, n)
    xx, yy = np.meshgrid(axis, axis)
    inside = np.hypot(xx, yy) <= SCIENCE_RADIUS
    return xx[inside], yy[inside]


def _rms_zero_mean(dx: np.ndarray, dy: np.ndarray) -> float:
    return float(np.sqrt(np.mean((dx - dx.mean()) ** 2 + (dy - dy.mean()) ** 2)))


def simulate_calibration(
    distortion: Distortion, settings: CalibrationMaskSettings, imager=None
) -> CalibrationResult:
    """Image the mask through ``distortion``, measure the holes and recover the distortion.

    Parameters
    ----------
    distortion : Distortion
        The distortion the mask sees (its ``displacement(x, y, epoch)`` in arcsec),
        evaluated at ``settings.epoch``.
    settings : CalibrationMaskSettings
    imager : callable, optional
        ``imager(x, y) -> (x_measured, y_measured)`` [arcsec]: measures one exposure of
        holes at true imaged positions ``x, y`` (NaN for a failed hole), e.g.
        :func:`~mavispm.simulate.optics.pinhole_imaging.rendered_hole_imager`. Default:
        the true positions plus Gaussian ``centroid_noise``.

    Returns
    -------
    CalibrationResult
    """
    rng = np.random.default_rng(settings.seed)
    x, y = mask_holes(settings)
    err_as = settings.hole_position_error * settings.mask_scale
    xq = x + err_as * rng.standard_normal(x.size)
    yq = y + err_as * rng.standard_normal(y.size)
    noise = settings.centroid_noise / 1000.0  # arcsec

    def image(sx: float, sy: float) -> tuple[np.ndarray, np.ndarray]:
        dx, dy = distortion.displacement(xq + sx, yq + sy, settings.epoch)
        if imager is not None:
            return imager(xq + sx + dx, yq + sy + dy)
        mx = xq + sx + dx + noise * rng.standard_normal(x.size)
        my = yq + sy + dy + noise * rng.standard_normal(y.size)
        return mx, my

    terms = tuple(polynomial_terms(settings.order))
    x0, y0 = image(0.0, 0.0)
    if settings.method == "direct":
        # measured minus nominal position; a constant column takes the mask offset
        a = np.column_stack([_design(x, y, terms), np.ones(x.size)])
        bx, by = (x0 - x) * 1000.0, (y0 - y) * 1000.0
        holes_dx, holes_dy = bx, by
    else:
        s = settings.shift * settings.mask_scale
        if settings.translation_error > 0:  # drawn only when set: same streams otherwise
            moved = settings.translation_error * settings.mask_scale
            moved = moved * rng.standard_normal((2, 2))
        else:
            moved = np.zeros((2, 2))
        x1, y1 = image(s + moved[0, 0], moved[0, 1])
        x2, y2 = image(moved[1, 0], s + moved[1, 1])
        # displacement of each hole between the images, less the known translation [mas]
        a = np.vstack(
            [
                _design(x + s, y, terms) - _design(x, y, terms),
                _design(x, y + s, terms) - _design(x, y, terms),
            ]
        )
        bx = np.concatenate([x1 - x0 - s, x2 - x0]) * 1000.0
        by = np.concatenate([y1 - y0, y2 - y0 - s]) * 1000.0
        holes_dx = 0.5 * (bx[: x.size] + bx[x.size :])
        holes_dy = 0.5 * (by[: x.size] + by[x.size :])
    # scale the columns for conditioning; lstsq is exact for a well-posed system
    # holes whose image could not be measured (imager NaN) drop out of the fit
    use = np.isfinite(bx) & np.isfinite(by)
    if np.count_nonzero(use) < a.shape[1]:
        raise ValueError(
            f"only {np.count_nonzero(use)} holes measured; order {settings.order} needs "
            f"at least {a.shape[1]}"
        )
    a, bx, by = a[use], bx[use], by[use]
    norm = np.sqrt(np.mean(a**2, axis=0))
    norm[norm == 0] = 1.0
    cx = np.linalg.lstsq(a / norm, bx, rcond=None)[0] / norm
    cy = np.linalg.lstsq(a / norm, by, rcond=None)[0] / norm
    cx, cy = cx[: len(terms)], cy[: len(terms)]

    gx, gy = _science_grid()
    raw = PolynomialDistortion(terms, cx, cy)
    rx, ry = raw.displacement_mas(gx, gy)
    recovered = PolynomialDistortion(terms, cx, cy, -float(rx.mean()), -float(ry.mean()))
    tx, ty = (d * 1000.0 for d in distortion.displacement(gx, gy, settings.epoch))
    return CalibrationResult(
        settings=settings,
        recovered=recovered,
        holes={
            "x": x,
            "y": y,
            "x_true": xq,
            "y_true": yq,
            "dx_meas": holes_dx,
            "dy_meas": holes_dy,
        },
        residual_rms=_rms_zero_mean(tx - rx, ty - ry),
        input_rms=_rms_zero_mean(tx, ty),
        translation_errors=moved if settings.method == "differential" else np.zeros((2, 2)),
    )


CALIBRATION_KIND = "calibration"


def write_calibration(path, result: CalibrationResult, distortion_config=None) -> None:
    """Write a ``calibration`` product (recovered polynomial, holes, residual map).

    Parameters
    ----------
    path : str or os.PathLike
        Output HDF5 file, written atomically.
    result : CalibrationResult
    distortion_config : mapping, optional
        The distortion settings that were calibrated (provenance).
    """
    import astropy.units as u

    from mavispm.core.config import to_mapping
    from mavispm.core.products import write_product

    rec = result.recovered
    gx, gy = np.meshgrid(*(np.linspace(-SCIENCE_RADIUS, SCIENCE_RADIUS, 31),) * 2)
    holes = result.holes
    write_product(
        path,
        CALIBRATION_KIND,
        tables={
            "holes": {
                "id": np.arange(holes["x"].size),
                "x": holes["x"] * u.arcsec,
                "y": holes["y"] * u.arcsec,
                "x_true": holes["x_true"] * u.arcsec,
                "y_true": holes["y_true"] * u.arcsec,
                "dx_meas": holes["dx_meas"] * u.mas,
                "dy_meas": holes["dy_meas"] * u.mas,
            }
        },
        arrays={
            "recovered_terms": np.asarray(rec.terms, dtype=np.int64),
            "recovered_coefficients_x": rec.coefficients_x * u.mas,
            "recovered_coefficients_y": rec.coefficients_y * u.mas,
            "map_x": gx * u.arcsec,
            "map_y": gy * u.arcsec,
            "recovered_map_dx": rec.displacement_mas(gx, gy)[0] * u.mas,
            "recovered_map_dy": rec.displacement_mas(gx, gy)[1] * u.mas,
        },
        attrs={
            "recovered_offset_x": rec.offset_x * u.mas,
            "recovered_offset_y": rec.offset_y * u.mas,
            "residual_rms": result.residual_rms * u.mas,
            "input_rms": result.input_rms * u.mas,
            "method": result.settings.method,
            "order": result.settings.order,
        },
        config={
            "calibration": to_mapping(result.settings),
            "distortion": dict(distortion_config or {}),
        },
        seed=result.settings.seed,
    )


def read_recovered_distortion(path) -> PolynomialDistortion:
    """The recovered distortion of a ``calibration`` product.

    Parameters
    ----------
    path : str or os.PathLike
        The ``calibration`` product.

    Returns
    -------
    PolynomialDistortion
        The recovered distortion.

    Raises
    ------
    InputError
        If the file is not a calibration product or its polynomial is malformed.
    """
    from mavispm.core.errors import InputError
    from mavispm.core.products import read_product

    prod = read_product(path, CALIBRATION_KIND)
    try:
        terms = tuple((int(i), int(j)) for i, j in np.asarray(prod.arrays["recovered_terms"]))
        cx = np.asarray(prod.arrays["recovered_coefficients_x"].to_value("mas"), float)
        cy = np.asarray(prod.arrays["recovered_coefficients_y"].to_value("mas"), float)
        ox = float(prod.attrs["recovered_offset_x"].to_value("mas"))
        oy = float(prod.attrs["recovered_offset_y"].to_value("mas"))
    except (KeyError, AttributeError, ValueError, TypeError) as exc:
        raise InputError(f"malformed recovered distortion ({exc})", path=path) from None
    if not (
        len(terms) == cx.size == cy.size and np.all(np.isfinite(cx)) and np.all(np.isfinite(cy))
    ):
        raise InputError("recovered distortion coefficients do not match its terms", path=path)
    return PolynomialDistortion(terms, cx, cy, ox, oy)
