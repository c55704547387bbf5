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
spectrum). Lengths in m, frequencies in m^-1, angles in rad, PSDs in rad^2 m^2.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "cone_psd",
    "footprint_coverage",
    "pupil_coherence",
]


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
    if not 0 <= obscuration < 1:
        raise ValueError(f"obscuration ratio must be in [0, 1), got {obscuration}")

    from scipy.special import j1  # ~0.3-0.5 s to import: only when computed

    def jinc(x):
        small = np.abs(x) < 1e-6
        safe = np.where(small, 1.0, x)
        return np.where(small, 1.0 - x**2 / 8, 2 * j1(safe) / safe)

    x = np.pi * diameter * np.asarray(q, float)
    eps = obscuration
    return (jinc(x) - eps**2 * jinc(eps * x)) / (1 - eps**2)


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

    Returns
    -------
    ndarray, shape (F,)
        ``sum_l A_l c_l W(f) [1 - gamma(s_l f)^2]`` with ``s_l = 2 g_l / D``
        (rad^2 m^2); the area factor A_l is 1 for one on-axis LGS.
    """
    shrink = np.clip(2.0 * np.asarray(gaps, float) / diameter, 0.0, 1.0)
    area = np.clip(np.asarray(area, float), 0.0, 1.0)
    gamma = pupil_coherence(np.asarray(f, float)[:, None] * shrink[None, :], diameter, obscuration)
    return np.sum(layer_psd * (1.0 - gamma**2) * area[None, :], axis=1)
