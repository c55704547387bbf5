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

Several LGS (MCAO). A tomographic reconstructor that knows the cone geometry
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

__all__ = [
    "cone_filter",
    "cone_psd",
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
