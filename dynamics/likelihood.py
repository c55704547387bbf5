"""Discrete (per-star) likelihood of a Jeans model with a star-count term.

For star ``i`` at projected radius ``R_i`` with proper-motion components
``v_R, v_T`` (radial and tangential about the centre, relative to the cluster
mean motion) and errors ``e_R, e_T``:

    ln L = sum_i  ln N(v_R,i | 0, sigma_R(R_i)^2 + e_R,i^2) + ln N(v_T,i | 0, sigma_T(R_i)^2 + e_T,i^2)
         + sum_i  ln [ Sigma(R_i) / N(< R_field) ]            (star counts)

The star-count term is the probability of each star's position under the
tracer surface density inside the (circular) field of radius ``R_field``; it
constrains the scale radius and the cusp, which the kinematics of a small field
cannot (they constrain mainly ``M / a`` and ``M_bh``). It assumes the sample's
completeness does not depend on radius inside the field.

Model parameters (physical): ``log_mass`` (log10 solMass), ``log_scale_radius``
(log10 arcsec), ``bh_mass`` (solMass; IMBH model only), ``beta``, and
optionally ``distance`` (kpc, Gaussian prior), ``gamma`` (Dehnen inner slope, or
the cusp slope with ``log_cusp_radius``, log10 arcsec, for a cusped Plummer/King62).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mavispm.core.errors import InputError
from mavispm.dynamics.interpolation import cubic_weights, interpolate
from mavispm.dynamics.jeans import G_PC_KMS2_MSUN, KMS_PER_MASYR_KPC, JeansProjector
from mavispm.dynamics.star_sums import star_sums
from mavispm.dynamics.tracers import make_tracer

#: parsec per (arcsec * kpc)
PC_PER_ARCSEC_KPC = 1e3 * np.pi / (180.0 * 3600.0)
_LN_2PI = np.log(2.0 * np.pi)


@dataclass(frozen=True)
class StarSample:
    """Stars used in the fit (plain floats in fixed units).

    Attributes
    ----------
    R : ndarray
        Projected radius [arcsec] (already clipped to ``min_radius``).
    v_r, v_t : ndarray
        Radial / tangential proper motions [mas/yr].
    e_r, e_t : ndarray
        Their errors [mas/yr].
    field_radius : float
        Radius of the circular field the stars were selected in [arcsec].
    """

    R: np.ndarray
    v_r: np.ndarray
    v_t: np.ndarray
    e_r: np.ndarray
    e_t: np.ndarray
    field_radius: float

    def __post_init__(self):
        n = len(self.R)
        for name in ("R", "v_r", "v_t", "e_r", "e_t"):
            arr = np.asarray(getattr(self, name), dtype=float)
            if arr.shape != (n,):
                raise InputError(f"expected {n} values, got shape {arr.shape}", column=name)
            if not np.all(np.isfinite(arr)):
                raise InputError("non-finite values (NaN or inf)", column=name)
            if name in ("R", "e_r", "e_t") and np.any(arr < 0):
                raise InputError("negative values", column=name)
        if n == 0:
            raise InputError("no stars to fit")
        if not (np.isfinite(self.field_radius) and self.field_radius > 0):
            raise InputError(f"field radius must be > 0, got {self.field_radius}")


class DiscreteLikelihood:
    """Per-star Jeans likelihood, evaluated on a radial grid and interpolated.

    Parameters
    ----------
    stars : StarSample
    names : sequence of str
        Parameter order of the vectors passed to :meth:`__call__`.
    tracer : str
        Tracer/mass profile name ("plummer", "dehnen", "king62").
    gamma, concentration : float
        Fixed Dehnen slope / King62 concentration (``gamma`` may instead be a parameter).
    cusp_link : {None, "free", "influence"}
        Cusped Plummer/King62 tracer: ``"free"`` fits ``gamma`` and ``log_cusp_radius``;
        ``"influence"`` fits ``gamma`` with the cusp radius set to the BH influence
        radius (where the cored profile encloses ``2 M_bh``; no cusp without a BH).
    distance : float
        Distance [kpc] used when ``distance`` is not a parameter.
    scale_radius_range : (float, float)
        Prior range of the scale radius [arcsec]; sets the grid in ``R / a``.
    min_radius : float
        Radii are clipped to at least this [arcsec] (guards ``R = 0``).
    grid_size, n_panels, n_gl, x_max
        Radial grid points and projection quadrature (see JeansProjector).
    star_counts : bool
        Include the star-count term.
    """

    def __init__(
        self,
        stars: StarSample,
        names,
        tracer: str = "plummer",
        gamma: float = 1.0,
        concentration: float = 1.5,
        cusp_link: str | None = None,
        distance: float = 5.0,
        scale_radius_range=(1.0, 1000.0),
        min_radius: float = 0.01,
        grid_size: int = 64,
        n_panels: int = 16,
        n_gl: int = 6,
        x_max: float = 1e4,
        star_counts: bool = True,
    ):
        self.stars = stars
        self.names = list(names)
        self.tracer_name = tracer
        self.gamma = gamma
        self.concentration = concentration
        self.cusp_link = cusp_link
        self.distance = distance
        self.star_counts = star_counts
        self._fixed_tracer = make_tracer(tracer, gamma, concentration)
        a_lo, a_hi = scale_radius_range
        self._log_a_range = (np.log10(a_lo) - 1e-9, np.log10(a_hi) + 1e-9)
        r_lo = max(min_radius, 1e-6)
        self.lnR = np.log(np.maximum(stars.R, r_lo))
        x_lo = r_lo / a_hi / 1.5
        x_hi = stars.field_radius / a_lo * 1.5
        if x_hi >= x_max / 10:
            raise InputError(
                f"field radius / smallest scale radius = {x_hi:.3g} is too close to the "
                f"projection truncation x_max = {x_max:g}; raise the scale-radius prior minimum"
            )
        if grid_size < 8:
            raise InputError(f"grid_size must be >= 8, got {grid_size}")
        self.lnX_grid = np.linspace(np.log(x_lo), np.log(x_hi), grid_size)
        self.step = self.lnX_grid[1] - self.lnX_grid[0]
        self.projector = JeansProjector(
            np.exp(self.lnX_grid), x_max=x_max, n_panels=n_panels, n_gl=n_gl
        )
        self._v2 = np.ascontiguousarray(np.stack([stars.v_r**2, stars.v_t**2]), dtype=float)
        self._e2 = np.ascontiguousarray(np.stack([stars.e_r**2, stars.e_t**2]), dtype=float)
        self._ln_field = np.log(stars.field_radius)
        self.n_stars = len(stars.R)

    def _value(self, theta, name, default):
        return theta[self.names.index(name)] if name in self.names else default

    def model_on_grid(self, theta):
        """Grid quantities for physical parameter vector ``theta``.

        Returns
        -------
        lnX : ndarray
            ln(R / a) grid.
        sigma2 : ndarray, shape (2, n)
            Radial and tangential model PM dispersion squared [(mas/yr)^2].
        ln_sigma, ln_proj : ndarray
            ln surface density (a = 1, unit mass) and ln projected mass fraction.
        """
        log_m = theta[self.names.index("log_mass")]
        ln_a = np.log(10.0) * theta[self.names.index("log_scale_radius")]
        bh = self._value(theta, "bh_mass", 0.0)
        beta = theta[self.names.index("beta")]
        dist = self._value(theta, "distance", self.distance)
        mom = self.projector.moments(self.tracer_at(theta), beta)
        a_pc = np.exp(ln_a) * dist * PC_PER_ARCSEC_KPC
        conv = (KMS_PER_MASYR_KPC * dist) ** 2
        scale = G_PC_KMS2_MSUN / a_pc / conv
        mass = 10.0**log_m
        s2 = scale * np.stack(
            [
                mass * mom.radial_cluster + bh * mom.radial_bh,
                mass * mom.tangential_cluster + bh * mom.tangential_bh,
            ]
        )
        tiny = np.finfo(float).tiny
        return (
            self.lnX_grid,
            np.maximum(s2, tiny),
            np.log(np.maximum(mom.surface_density, tiny)),
            np.log(np.maximum(mom.projected_enclosed, tiny)),
        )

    def tracer_at(self, theta):
        """The dimensionless tracer (= cluster mass) profile for parameter vector ``theta``."""
        tracer = self._fixed_tracer
        if self.cusp_link == "influence":
            mass = 10.0 ** theta[self.names.index("log_mass")]
            tracer = self._influence_cusp(theta, self._value(theta, "bh_mass", 0.0), mass)
        elif "log_cusp_radius" in self.names:
            ln_a = np.log(10.0) * theta[self.names.index("log_scale_radius")]
            x_c = 10.0 ** (theta[self.names.index("log_cusp_radius")]) / np.exp(ln_a)
            g = theta[self.names.index("gamma")]
            tracer = make_tracer(self.tracer_name, g, self.concentration, cusp_radius=x_c)
        elif "gamma" in self.names:
            tracer = make_tracer("dehnen", theta[self.names.index("gamma")])
        return tracer

    def _influence_cusp(self, theta, bh_mass, mass):
        """Cusped tracer whose cusp radius is the BH influence radius (base without a BH).

        The influence radius encloses ``2 M_bh`` of the cored profile (capped at half
        its mass); below 1e-6 scale radii the cusp has no effect and is dropped.
        """
        base = self._fixed_tracer
        if bh_mass <= 0:
            return base
        x_infl = base.radius_enclosing(min(2.0 * bh_mass / mass, 0.5))
        if x_infl < 1e-6:
            return base
        g = theta[self.names.index("gamma")]
        return make_tracer(self.tracer_name, g, self.concentration, cusp_radius=x_infl)

    def dispersion_at(self, theta, R):
        """Model radial and tangential PM dispersions [mas/yr] at radii ``R`` [arcsec]."""
        lnX, s2, _, _ = self.model_on_grid(theta)
        ln_a = np.log(10.0) * theta[self.names.index("log_scale_radius")]
        idx, w = cubic_weights(lnX[0], self.step, lnX.size, np.log(np.asarray(R)) - ln_a)
        return np.sqrt(np.exp(interpolate(np.log(s2), idx, w)))

    def __call__(self, theta) -> float:
        """ln L for physical parameter vector ``theta`` (finite, or -inf if invalid)."""
        beta = theta[self.names.index("beta")]
        if not beta < 1.0 or self._value(theta, "bh_mass", 0.0) < 0:
            return -np.inf
        if "distance" in self.names and not theta[self.names.index("distance")] > 0:
            return -np.inf
        if "gamma" in self.names and not 0 <= theta[self.names.index("gamma")] < 2.5:
            return -np.inf
        log_a = theta[self.names.index("log_scale_radius")]
        if not self._log_a_range[0] <= log_a <= self._log_a_range[1]:
            return -np.inf  # outside the radial grid (Gaussian prior tails)
        lnX, s2, ln_sig, ln_proj = self.model_on_grid(theta)
        ln_a = np.log(10.0) * log_a
        chi, ln_sigma_stars = star_sums(
            self.lnR - ln_a, lnX[0], self.step, np.log(s2), ln_sig, self._v2, self._e2
        )
        lnl = -0.5 * chi - self.n_stars * _LN_2PI
        if self.star_counts:
            i_f, w_f = cubic_weights(lnX[0], self.step, lnX.size, [self._ln_field - ln_a])
            ln_norm = float(interpolate(ln_proj, i_f, w_f)[0])
            lnl += ln_sigma_stars - self.n_stars * (2.0 * ln_a + ln_norm)
        return lnl if np.isfinite(lnl) else -np.inf
