"""LGS cone effect (focal anisoplanatism) as a residual-phase PSD.

A laser guide star at range H sees a turbulent layer at distance h through a
cone: its beam crosses the layer over a disc of diameter ``a D`` with
``a = 1 - h / H``, centred on ``h theta_g``, while a science star in direction
alpha crosses it over a disc of diameter D centred on ``h alpha``.

Single LGS, classical focal anisoplanatism (Fried & Belsher 1994; Tyler 1994).
The LGS measures the layer phase compressed by ``a``: a layer mode
``exp(2 pi i f.x)`` seen by the science beam is seen by the LGS as
``exp(2 pi i a f.x)``. Their pupil-averaged coherence is the normalised pupil
transform at the mismatch ``(1 - a) f``,
``gamma = <exp(2 pi i (1 - a) f.x)>_pupil``, and the best (MMSE) correction
from the LGS leaves ``(1 - gamma^2) W_l(f)`` of the layer spectrum. Integrated
over f this is the focal-anisoplanatism variance ``(D / d0)^(5/3)``; for small
``h / H`` it is within ~15% of Fried's closed form and ~8% of the exact
piston-removed pupil integral (tests/test_optics_cone.py).

Several LGS (MCAO), the former footprint-gap model (``cone_model = "gap"``, a
cross-check). A tomographic reconstructor that knows the cone geometry
registers each LGS footprint on the layer correctly, so the compression itself
costs nothing where the layer is sensed; what is lost is the part of the
science footprint that no LGS footprint covers. We take the farthest reach of
the science disc beyond the union of the LGS discs, the *gap* ``g_l(alpha)``
(0 when the science footprint is covered), and use it as the single-LGS
mismatch at the pupil edge: with one on-axis LGS the gap is ``(1 - a) D / 2``,
so the shrink ``s = 2 g / D`` equals ``1 - a`` and the single-LGS result above
is recovered exactly. A sliver beyond the LGS footprints spoils a smaller part
of the pupil than the single-LGS annulus of the same width, so each layer's
term is weighted by the uncovered area relative to that annulus, ``A_l`` (1 for
one on-axis LGS, 0 when covered). The PSD of direction alpha is

``W_cone(f, alpha) = sum_l A_l(alpha) c_l W(f) [1 - gamma(s_l(alpha) f)^2]``

inside the control region (outside it the fitting error already holds the whole
spectrum).

Several LGS, extrapolation (kriging) variance (``cone_model = "kriging"``, the
default). The science footprint's part outside every LGS footprint is not sensed
at all; the best a reconstructor that knows the layer on the sensed region can do
there is the MMSE (kriging) extrapolation with the turbulence covariance. Its
error, piston and tilt removed over the science pupil, is computed per layer
and direction by :func:`extrapolation_variance`: the layer is known on the LGS
footprint discs, represented by their exact edges (two rings of points) and an
interior grid, and only known points within ``KRIGING_SCREEN`` of the unsensed
region enter (the screening of the nearer points makes farther ones irrelevant:
at 0.25 m sampling, 1 m and the whole 2 m neighbourhood give the same variance to
1e-4, tests/test_optics_cone.py). The variance is the pupil quadrature of the
conditional covariance over the unsensed points, less its piston and tilt
projections. It is tested against a brute-force kriging on fine grids (the
sensed region's grid points as the data, whose edges lie up to a step inside
the footprints, so it overestimates and converges slowly from above). The
spectrum of each layer's term is the azimuthally averaged, pupil-averaged power
spectrum of that error field (:func:`extrapolation_spectrum`, from the same
conditional covariance), tested against an FFT of the error field's eigenmodes.
The real error lives in thin crescents at the pupil edge: its power sits at
0.5-2 m^-1, 10-20% of it beyond the control radius. The former gap-and-area
model (``"gap"``, above: :func:`footprint_coverage`, :func:`cone_psd`) is 2-8x
that variance, with its power at lower frequencies, and stays as a
cross-check. The variance is invariant under the symmetries of the
LGS asterism, so a grid of directions needs it only for one direction per
symmetry orbit (:func:`canonical_direction`).

Piston and tilt. The LGS cannot sense tip-tilt (its launch jitter hides it): in
MCAO the tilt of every direction comes from the NGS through the tip-tilt model
(``simulate.optics.tiptilt``), and piston does not matter. The residual of a
layer mode is not a plane wave, ``r_f(x) = exp(2 pi i f.x) - c exp(2 pi i a f.x)``
with the reconstructor coefficient ``c = gamma(s f)``, and its pupil piston and
tilt are known in closed form from the pupil transform and its derivative:
piston ``gamma(f) - c gamma(a f)``, tilt (both axes, unit-RMS modes)
``[gamma'(f) - c gamma'(a f)]^2 / (4 pi^2 <x^2>)``, ``<x^2>`` the pupil's second
moment along one axis. Since the turbulence modes are independent, removing them
mode by mode gives the exact piston-and-tilt-removed variance (with c = 1 it is
the brute-force pupil integral of ``phi(x) - phi(a x)`` with tilt fitted out,
tests/test_optics_cone.py). The low-frequency part of the cone error is pure
tilt (``r_f ~ 2 pi i s f.x`` for ``f << 1/D``), so without the removal the HO PSD
would blur the PSF by a tilt the NGS loop corrects. ``remove_tilt = False``
keeps the former filter ``1 - gamma(s f)^2`` (piston and tilt included) as a
cross-check. Lengths in m, frequencies in m^-1, angles in rad, PSDs in rad^2 m^2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from mavispm.simulate.optics.atmosphere import von_karman_covariance

#: sampling of the fast extrapolation (kriging) variance, in m: science quadrature
#: grid, interior grid of the sensed region, spacing of the two boundary rings
#: (on the LGS footprint edges and one spacing inside), screening distance
KRIGING_SCIENCE_STEP = 0.1
KRIGING_KNOWN_STEP = 0.25
KRIGING_BOUNDARY_STEP = 0.04
KRIGING_SCREEN = 0.6

__all__ = [
    "asterism_symmetries",
    "canonical_direction",
    "cone_filter",
    "cone_psd",
    "extrapolation_spectrum",
    "extrapolation_variance",
    "footprint_coverage",
    "pupil_coherence",
    "pupil_coherence_slope",
]


def _check_obscuration(obscuration: float) -> None:
    if not 0 <= obscuration < 1:
        raise ValueError(f"obscuration ratio must be in [0, 1), got {obscuration}")


def pupil_coherence(q: ArrayLike, diameter: float, obscuration: float = 0.0) -> np.ndarray:
    """Normalised Fourier transform of the annular pupil, ``<exp(2 pi i q.x)>_pupil``.

    Parameters
    ----------
    q : array_like
        Spatial-frequency modulus (m^-1).
    diameter : float
        Pupil diameter D (m).
    obscuration : float
        Central obstruction ratio eps (fraction of D), 0 <= eps < 1.

    Returns
    -------
    ndarray
        ``[jinc(pi D q) - eps^2 jinc(pi eps D q)] / (1 - eps^2)`` with
        ``jinc(x) = 2 J1(x) / x``; exactly 1 at q = 0.
    """
    _check_obscuration(obscuration)
    from scipy.special import j1  # ~0.3-0.5 s to import: only when computed

    def jinc(x):
        small = np.abs(x) < 1e-6
        safe = np.where(small, 1.0, x)
        return np.where(small, 1.0 - x**2 / 8, 2 * j1(safe) / safe)

    x = np.pi * diameter * np.asarray(q, float)
    eps = obscuration
    return (jinc(x) - eps**2 * jinc(eps * x)) / (1 - eps**2)


def pupil_coherence_slope(q: ArrayLike, diameter: float, obscuration: float = 0.0) -> np.ndarray:
    """Derivative of :func:`pupil_coherence` with respect to q (m).

    ``<x exp(2 pi i q.x)>_pupil = gamma'(|q|) cos(theta_q) / (2 pi i)``, so this
    gives the tilt content of a plane wave over the pupil.

    Parameters
    ----------
    q : array_like
        Spatial-frequency modulus (m^-1).
    diameter : float
        Pupil diameter D (m).
    obscuration : float
        Central obstruction ratio eps, 0 <= eps < 1.

    Returns
    -------
    ndarray
        ``pi D [djinc(pi D q) - eps^3 djinc(pi eps D q)] / (1 - eps^2)`` with
        ``djinc(x) = -2 J2(x) / x`` (m); 0 at q = 0.
    """
    _check_obscuration(obscuration)
    from scipy.special import j0, j1  # J2 = 2 J1 / x - J0: 10x faster than jv(2, x)

    def djinc(x):
        small = np.abs(x) < 1e-2  # series where the recurrence cancels
        safe = np.where(small, 1.0, x)
        series = -x / 4 + x**3 / 48 - x**5 / 1536
        return np.where(small, series, -2 * (2 * j1(safe) / safe - j0(safe)) / safe)

    x = np.pi * diameter * np.asarray(q, float)
    eps = obscuration
    return np.pi * diameter * (djinc(x) - eps**3 * djinc(eps * x)) / (1 - eps**2)


def cone_filter(
    f: ArrayLike,
    shrink: ArrayLike,
    diameter: float,
    obscuration: float = 0.0,
    remove_tilt: bool = True,
    coefficient: ArrayLike | None = None,
) -> np.ndarray:
    """Fraction of a layer's spectrum the cone effect leaves, per frequency.

    Parameters
    ----------
    f : array_like
        Spatial-frequency modulus (m^-1).
    shrink : array_like
        Footprint mismatch ``s = 1 - a`` (dimensionless), broadcast against ``f``.
    diameter, obscuration : float
        Pupil diameter (m) and obstruction ratio.
    remove_tilt : bool
        Remove the residual's pupil piston and tilt (default); False: the
        former ``1 - gamma(s f)^2``.
    coefficient : array_like or None
        Reconstructor coefficient c of the compressed mode; None: the MMSE
        ``gamma(s f)``. ``c = 1`` is the plain LGS correction ``phi(x) - phi(a x)``.

    Returns
    -------
    ndarray
        ``<|r_f|^2> - |piston|^2 - |tilt|^2`` (>= 0, dimensionless), with
        ``<|r_f|^2> = 1 - 2 c gamma(s f) + c^2``.
    """
    f = np.asarray(f, float)
    shrink = np.asarray(shrink, float)
    g_s = pupil_coherence(shrink * f, diameter, obscuration)
    c = g_s if coefficient is None else np.asarray(coefficient, float)
    out = 1.0 - 2.0 * c * g_s + c**2
    if remove_tilt:
        a_f = (1.0 - shrink) * f
        piston = pupil_coherence(f, diameter, obscuration) - c * pupil_coherence(
            a_f, diameter, obscuration
        )
        slope = pupil_coherence_slope(f, diameter, obscuration) - c * pupil_coherence_slope(
            a_f, diameter, obscuration
        )
        x2 = (diameter / 4) ** 2 * (1 + obscuration**2)  # <x^2> over the annulus
        out = out - piston**2 - slope**2 / (4 * np.pi**2 * x2)
    return np.maximum(out, 0.0)


def _disc_points(diameter: float, n_ring: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Uniform-density sample points of a disc (P, 2) and points on its edge (E, 2) (m).

    Rings of equal width with a number of points proportional to their radius.
    """
    pts = []
    for k in range(n_ring):
        r = (k + 0.5) / n_ring
        n = max(3, int(round(2 * np.pi * r * n_ring)))
        ang = 2 * np.pi * (np.arange(n) + 0.5 * (k % 2)) / n
        pts.append(r * np.stack([np.cos(ang), np.sin(ang)], -1))
    ang = 2 * np.pi * np.arange(8 * n_ring) / (8 * n_ring)
    edge = np.stack([np.cos(ang), np.sin(ang)], -1)
    return 0.5 * diameter * np.concatenate(pts), 0.5 * diameter * edge


def _distance_outside(points: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """Distance (m) of each point (P, 2) to the union of discs (G, 2) of ``radius``; 0 inside."""
    d = points[:, None, :] - centres[None, :, :]
    return np.maximum(np.hypot(d[..., 0], d[..., 1]) - radius, 0.0).min(axis=1)


def footprint_coverage(
    direction: np.ndarray,
    lgs_directions: np.ndarray,
    heights: np.ndarray,
    lgs_range: float,
    diameter: float,
) -> tuple[np.ndarray, np.ndarray]:
    """How far and how much of the science footprint lies outside the LGS footprints.

    Parameters
    ----------
    direction : ndarray, shape (2,)
        Science direction (rad).
    lgs_directions : ndarray, shape (G, 2)
        LGS directions (rad).
    heights : ndarray, shape (L,)
        Layer distances along the line of sight (m), all below ``lgs_range``.
    lgs_range : float
        LGS distance along the line of sight (m).
    diameter : float
        Pupil diameter (m).

    Returns
    -------
    gaps : ndarray, shape (L,)
        Largest distance from a point of the science disc to the union of the LGS
        discs (m), 0 where the footprint is covered.
    area : ndarray, shape (L,)
        Area of the science disc outside every LGS disc relative to the annulus
        of width ``gap`` at its rim (what one on-axis LGS with that gap leaves
        uncovered), clipped to [0, 1]; both areas from the same sample points,
        so one on-axis LGS gives exactly 1.
    """
    heights = np.asarray(heights, float)
    if np.any(heights >= lgs_range):
        raise ValueError("every turbulent layer must lie below the LGS")
    inner, edge = _disc_points(diameter)
    radius_inner = np.hypot(inner[:, 0], inner[:, 1])
    gaps = np.zeros(heights.size)
    area = np.zeros(heights.size)
    for i, h in enumerate(heights):
        centres = h * np.asarray(lgs_directions, float)  # (G, 2)
        radius = 0.5 * diameter * (1.0 - h / lgs_range)
        shift = h * np.asarray(direction, float)[None, :]

        gaps[i] = _distance_outside(edge + shift, centres, radius).max()
        if gaps[i] > 0:
            uncovered = np.count_nonzero(_distance_outside(inner + shift, centres, radius) > 0)
            annulus = np.count_nonzero(radius_inner > 0.5 * diameter - gaps[i])
            area[i] = min(1.0, uncovered / max(annulus, 1))
    return gaps, area


def cone_psd(
    f: np.ndarray,
    layer_psd: np.ndarray,
    gaps: np.ndarray,
    area: np.ndarray,
    diameter: float,
    obscuration: float = 0.0,
    remove_tilt: bool = True,
) -> np.ndarray:
    """Cone-effect residual PSD for one science direction.

    Parameters
    ----------
    f : ndarray, shape (F,)
        Spatial-frequency modulus (m^-1).
    layer_psd : ndarray, shape (F, L)
        Phase PSD of each layer, c_l W(f) (rad^2 m^2).
    gaps, area : ndarray, shape (L,)
        Footprint gaps (m) and relative uncovered areas from :func:`footprint_coverage`.
    diameter, obscuration : float
        Pupil diameter (m) and obstruction ratio.
    remove_tilt : bool
        Leave out the residual's pupil piston and tilt (sensed by the NGS, see the
        module notes); False keeps them (the former model, a cross-check).

    Returns
    -------
    ndarray, shape (F,)
        ``sum_l A_l c_l W(f) F(f, s_l)`` with ``s_l = 2 g_l / D`` and F the
        :func:`cone_filter` (rad^2 m^2); the area factor A_l is 1 for one on-axis LGS.
    """
    shrink = np.clip(2.0 * np.asarray(gaps, float) / diameter, 0.0, 1.0)
    area = np.clip(np.asarray(area, float), 0.0, 1.0)
    f = np.asarray(f, float)
    seen = (area > 0) & (shrink > 0)  # covered layers leave nothing
    if not seen.any():
        return np.zeros(f.shape)
    filt = cone_filter(f[:, None], shrink[None, seen], diameter, obscuration, remove_tilt)
    return np.sum(np.asarray(layer_psd)[:, seen] * filt * area[None, seen], axis=1)


_D4 = tuple(
    np.array(m, float)
    for m in (
        ((1, 0), (0, 1)),
        ((0, -1), (1, 0)),
        ((-1, 0), (0, -1)),
        ((0, 1), (-1, 0)),
        ((1, 0), (0, -1)),
        ((-1, 0), (0, 1)),
        ((0, 1), (1, 0)),
        ((0, -1), (-1, 0)),
    )
)


def asterism_symmetries(lgs_directions: np.ndarray, tol: float = 1e-9) -> tuple[np.ndarray, ...]:
    """The rotations by multiples of 90 deg and axis / diagonal reflections mapping the LGS set
    onto itself.

    Parameters
    ----------
    lgs_directions : ndarray, shape (G, 2)
        LGS directions [rad].
    tol : float
        Relative tolerance of the match.

    Returns
    -------
    tuple of ndarray, each (2, 2)
        The symmetries (the identity always).
    """
    g = np.asarray(lgs_directions, float)
    scale = max(float(np.abs(g).max()), 1e-300)
    out = []
    for m in _D4:
        d = np.hypot(*((g @ m.T)[:, None, :] - g[None, :, :]).transpose(2, 0, 1))
        if np.all(d.min(axis=1) <= tol * scale):
            out.append(m)
    return tuple(out)


def canonical_direction(direction: np.ndarray, symmetries: tuple[np.ndarray, ...]) -> tuple:
    """One representative of a direction's orbit under the asterism's symmetries.

    Parameters
    ----------
    direction : ndarray, shape (2,)
        Science direction [rad].
    symmetries : tuple of ndarray
        From :func:`asterism_symmetries`.

    Returns
    -------
    tuple of float
        The image with the largest (x, y), rounded to 1e-11 rad (a key for a cache).
    """
    d = np.asarray(direction, float)
    return max(tuple(np.round(m @ d, 11) + 0.0) for m in symmetries)


def _distance_to_union(points: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    """Signed distance (m) of points (P, 2) to the union of discs (G, 2): < 0 inside."""
    d = points[:, None, :] - centres[None, :, :]
    return (np.hypot(d[..., 0], d[..., 1]) - radius).min(axis=1)


def _covariance_table(r0: float, outer_scale: float, r_max: float):
    r = np.concatenate([[0.0], np.geomspace(1e-5, r_max, 4000)])
    return r, von_karman_covariance(r, r0, outer_scale)


def _pairwise(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.hypot(a[:, None, 0] - b[None, :, 0], a[:, None, 1] - b[None, :, 1])


def _kriging_setup(diameter, obscuration, r0, outer_scale, remove_tilt):
    """Pupil quadrature points (P, 2) [m], their unit-RMS modes to remove (P, J), the
    interior known grid [m] and the covariance function of point sets [rad^2]."""
    su, sk, rho = KRIGING_SCIENCE_STEP, KRIGING_KNOWN_STEP, KRIGING_SCREEN
    n = int(np.ceil(diameter / su))
    g = (np.arange(n) + 0.5 - n / 2) * su
    pupil = np.stack([a.ravel() for a in np.meshgrid(g, g)], -1)
    r = np.hypot(pupil[:, 0], pupil[:, 1])
    pupil = pupil[(r <= diameter / 2) & (r >= obscuration * diameter / 2)]
    x2 = (diameter / 4) ** 2 * (1 + obscuration**2)  # <x^2> over the annulus
    modes = pupil / np.sqrt(x2) if remove_tilt else pupil[:, :0]
    modes = np.column_stack([np.ones(len(pupil)), modes])  # unit-RMS piston (and tilts)
    gk = np.arange(-(diameter / 2 + rho), diameter / 2 + rho + sk / 2, sk)
    grid = np.stack([a.ravel() for a in np.meshgrid(gk, gk)], -1)
    r_tab, c_tab = _covariance_table(r0, outer_scale, 2 * diameter + 4 * rho)

    def cov(a, b):
        return np.interp(_pairwise(a, b), r_tab, c_tab)

    return pupil, modes, grid, cov


def _check_layers(heights, lgs_range, obscuration):
    heights = np.asarray(heights, float)
    if np.any(heights >= lgs_range):
        raise ValueError("every turbulent layer must lie below the LGS")
    _check_obscuration(obscuration)
    return heights


def extrapolation_variance(
    direction: np.ndarray,
    lgs_directions: np.ndarray,
    heights: np.ndarray,
    lgs_range: float,
    diameter: float,
    obscuration: float,
    r0: float,
    outer_scale: float,
    remove_tilt: bool = True,
) -> np.ndarray:
    """MMSE extrapolation error of each layer beyond the LGS footprints, over the science pupil.

    Each layer's phase is taken as known on the union of the LGS footprints (discs of
    diameter ``(1 - h / H) D`` centred on ``h theta_g``) and extrapolated (kriged, with
    the von Karman covariance) onto the part of the science footprint (disc of diameter
    D centred on ``h alpha``) outside them. The known region is represented by its exact
    edges (rings of points every ``KRIGING_BOUNDARY_STEP`` on the footprint edges and one
    step inside) and an interior grid (``KRIGING_KNOWN_STEP``), screened to
    ``KRIGING_SCREEN`` from the unsensed points; the pupil is a quadrature grid of
    ``KRIGING_SCIENCE_STEP``.

    Parameters
    ----------
    direction : ndarray, shape (2,)
        Science direction [rad].
    lgs_directions : ndarray, shape (G, 2)
        LGS directions [rad].
    heights : ndarray, shape (L,)
        Layer distances along the line of sight [m], below ``lgs_range``.
    lgs_range : float
        LGS distance along the line of sight [m].
    diameter, obscuration : float
        Pupil diameter [m] and central obstruction ratio.
    r0, outer_scale : float
        Fried parameter of the whole atmosphere at the phase wavelength and outer scale
        [m]; a layer with Cn^2 fraction c_l has ``c_l`` times the returned variance.
    remove_tilt : bool
        Remove the residual's pupil piston and tilt (default); False: piston only.

    Returns
    -------
    ndarray, shape (L,)
        Pupil-averaged residual variance [rad^2] for the whole turbulence on each layer.
    """
    return extrapolation_spectrum(
        direction,
        lgs_directions,
        heights,
        lgs_range,
        diameter,
        obscuration,
        r0,
        outer_scale,
        None,
        remove_tilt,
    )[0]


def extrapolation_spectrum(
    direction: np.ndarray,
    lgs_directions: np.ndarray,
    heights: np.ndarray,
    lgs_range: float,
    diameter: float,
    obscuration: float,
    r0: float,
    outer_scale: float,
    f: np.ndarray | None,
    remove_tilt: bool = True,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Variance and azimuthally averaged power spectrum of the extrapolation error.

    The error field ``e`` (the kriging error on the unsensed part of the science pupil,
    0 elsewhere, with its pupil piston and tilt removed) has the pupil-averaged spectrum
    ``W(f) = E|FT(e)(f)|^2 / A``, A the pupil area, whose integral is the variance of
    :func:`extrapolation_variance`. Its azimuthal average follows from the conditional
    covariance ``C`` on the unsensed points u (pupil quadrature weight w):
    ``A W = w^2 sum_uv C_uv J0(2 pi f |u - v|) - 2 X(f) + M(f)``, where the cross term
    with the removed modes is ``X = A gamma(f) sum_u w b_0(u) J0(2 pi f |u|) - A gamma'(f)
    / (2 pi sigma) sum_u w (b_x u_x + b_y u_y) / |u| J1(2 pi f |u|)`` and the modes' own
    term ``M = A^2 [a_00 gamma^2 + (a_xx + a_yy) gamma'^2 / (8 pi^2 sigma^2)]``, with
    ``b_j = C Z_j / N``, ``a_jk = Z_j^T C Z_k / N^2`` (N pupil points, Z_j the unit-RMS
    piston and tilts, sigma^2 the pupil's second moment, gamma :func:`pupil_coherence`).
    The pair sum is taken over a histogram of the pair distances (0.005 m bins).

    Parameters
    ----------
    direction, lgs_directions, heights, lgs_range, diameter, obscuration, r0, outer_scale
        As in :func:`extrapolation_variance`.
    f : ndarray, shape (F,) or None
        Spatial-frequency moduli [1/m]; None: the variance only.
    remove_tilt : bool
        As in :func:`extrapolation_variance`.

    Returns
    -------
    variance : ndarray, shape (L,)
        [rad^2], for the whole turbulence on each layer.
    spectrum : ndarray, shape (L, F) or None
        Azimuthally averaged PSD [rad^2 m^2] (``int 2 pi f W df = variance``).
    """
    from threadpoolctl import threadpool_limits

    heights = _check_layers(heights, lgs_range, obscuration)
    pupil, modes, grid, cov = _kriging_setup(diameter, obscuration, r0, outer_scale, remove_tilt)
    var = np.zeros(heights.size)
    spec = None if f is None else np.zeros((heights.size, np.size(f)))
    lgs = np.asarray(lgs_directions, float)
    shift = np.asarray(direction, float)
    with threadpool_limits(limits=1, user_api="blas"):  # small matrices: threads only contend
        for i, h in enumerate(heights):
            radius = 0.5 * diameter * (1.0 - h / lgs_range)
            res = _layer_error_covariance(h * lgs, radius, h * shift, diameter, pupil, grid, cov)
            if res is None:
                continue
            outside, err = res
            z = modes[outside]
            n_pupil = len(pupil)
            projected = np.einsum("uj,uv,vj->", z, err, z) / n_pupil
            var[i] = max((np.trace(err) - projected) / n_pupil, 0.0)
            if spec is not None:
                spec[i] = _error_spectrum(
                    np.asarray(f, float), pupil[outside], err, z, n_pupil, diameter, obscuration
                )
    return var, spec


def _error_spectrum(f, u, err, z, n_pupil, diameter, obscuration) -> np.ndarray:
    """Azimuthally averaged spectrum [rad^2 m^2] of one layer's error (see
    :func:`extrapolation_spectrum`); ``u`` (U, 2) unsensed points [m] from the pupil
    centre, ``err`` (U, U) their conditional covariance, ``z`` (U, J) the modes."""
    from scipy.special import j0, j1

    area = np.pi * (diameter / 2) ** 2 * (1 - obscuration**2)
    w = area / n_pupil
    sigma = diameter / 4 * np.sqrt(1 + obscuration**2)
    two_pi_f = 2 * np.pi * f
    # pair sum over a histogram of the pair distances
    step = 0.005
    idx = np.rint(_pairwise(u, u) / step).astype(int).ravel()
    hist = np.bincount(idx, weights=err.ravel())
    r_bins = np.arange(hist.size) * step
    pairs = w**2 * (j0(np.outer(two_pi_f, r_bins)) @ hist)
    b = err @ z / n_pupil  # (U, J)
    a = z.T @ err @ z / n_pupil**2  # (J, J)
    r_u = np.hypot(u[:, 0], u[:, 1])
    arg = np.outer(two_pi_f, r_u)
    g = pupil_coherence(f, diameter, obscuration)
    cross = area * g * (j0(arg) @ (w * b[:, 0]))
    own = area**2 * a[0, 0] * g**2
    if z.shape[1] == 3:
        gs = pupil_coherence_slope(f, diameter, obscuration)
        radial = (b[:, 1] * u[:, 0] + b[:, 2] * u[:, 1]) / np.maximum(r_u, 1e-12)
        cross -= area * gs / (2 * np.pi * sigma) * (j1(arg) @ (w * radial))
        own += area**2 * (a[1, 1] + a[2, 2]) * gs**2 / (8 * np.pi**2 * sigma**2)
    return np.maximum((pairs - 2 * cross + own) / area, 0.0)


def _layer_error_covariance(centres, radius, shift, diameter, pupil, grid, cov):
    """The unsensed pupil points (mask) and their conditional covariance [rad^2] for one layer.

    ``centres`` (G, 2) and ``radius`` [m]: the LGS footprints on the layer; ``shift``
    [m]: the science footprint's centre; ``pupil`` (P, 2) quadrature points [m];
    ``grid`` the interior known grid around the origin [m]; ``cov(a, b)`` the phase
    covariance between point sets [rad^2]. None where the footprint is covered.
    """
    from scipy.linalg import cho_factor, cho_solve

    sb, rho = KRIGING_BOUNDARY_STEP, KRIGING_SCREEN
    outside = _distance_to_union(pupil + shift, centres, radius) > 0
    if not outside.any():
        return None
    sky = pupil[outside] + shift
    # known points: interior grid plus the exact edges (two rings), near the science disc
    m = int(np.ceil(2 * np.pi * radius / sb))
    ring = np.exp(2j * np.pi * np.arange(m) / m)
    ring = np.stack([ring.real, ring.imag], -1)
    cand = [grid + shift]
    depth = [np.full(len(grid), np.nan)]
    for dr in (0.0, sb):
        cand.append((centres[:, None, :] + (radius - dr) * ring[None]).reshape(-1, 2))
        depth.append(np.full(len(cand[-1]), dr))
    cand, depth = np.concatenate(cand), np.concatenate(depth)
    near = np.hypot(*(cand - shift).T) <= diameter / 2 + rho
    cand, depth = cand[near], depth[near]
    dist = _distance_to_union(cand, centres, radius)
    # grid points deeper than the inner ring; ring points not inside another disc
    keep = np.where(np.isnan(depth), dist < -sb, dist > -np.nan_to_num(depth) - 1e-9)
    known = cand[keep]
    known = known[_pairwise(sky, known).min(axis=0) <= rho]
    ckk = cov(known, known)
    cuk = cov(sky, known)
    for jitter in (1e-10, 1e-8, 1e-6):  # a tiny nugget where near points make ckk singular
        try:
            factor = cho_factor(ckk + jitter * ckk[0, 0] * np.eye(len(known)))
            break
        except np.linalg.LinAlgError:
            continue
    else:
        raise np.linalg.LinAlgError("extrapolation covariance is not positive definite")
    return outside, cov(sky, sky) - cuk @ cho_solve(factor, cuk.T)
