"""Honest per-star uncertainties: the Fisher (Cramér-Rao) error plus the ePSF model error.

The inverse Fisher matrix of a star's fit knows photon and read noise only. With
an ePSF built from the frame, the bright stars are limited by the ePSF itself
(its noise from a finite number of PSF stars, its field variation, neighbour
residuals): on the NGC 3201 frames the per-epoch scatter of stars brighter than
m = 22 is 0.15-0.3 mas where the Fisher error says 0.001-0.02 mas.

The error model (``error_model = "epsf"``), per star and coordinate::

    sigma^2 = sigma_F^2 max(chi2, 1) + sigma_ePSF(F)^2 max(chi2 / chi2_typ(F), 1)

* ``sigma_F``: the Fisher error (kept as the ``x_err_fisher`` column);
* ``chi2``: the reduced chi^2 of the star's fit stamp (model weights);
* ``sigma_ePSF(F)``: the ePSF model error at the star's flux ``F``, measured on
  the frame from the PSF stars themselves: the PSF stars of every node are split
  into two halves, an ePSF is built from each, and every star's position (and
  flux) change between the two ePSFs is computed by one linearised
  Gauss-Newton step (:func:`epsf_difference_shifts`). With the ePSF noise
  scaling as ``1 / sqrt(N)`` the error of the full ePSF is half the rms
  difference of the two half-ePSFs; it is estimated robustly (MAD) in bins of
  flux (:func:`flux_trend`);
* ``chi2_typ(F)``: the typical (median) chi^2 at that flux (model mismatch grows
  with the flux): a star fitted worse than its peers (a neighbour's residual, a
  local ePSF error) gets its ePSF error inflated by the ratio.

The flux error is treated in the same way with the relative flux change. With
``error_model = "fisher"`` the errors are the Fisher errors alone (the Cramér-Rao
bound; right for a known PSF).

With the chi^2 taken against the star's peers (``relative_chi2``: the PSF-R model,
and the frame-built ePSF with its nodes centred on all stars) the position terms take the ratio of the
residual's part *odd* about the star (``chi2_odd``,
:func:`~mavispm.measure.stars.odd_residual.odd_chi2`) against its peers' instead of the
whole chi^2's: a misfit even about the star (a width or wing error of a centred
model) raises the chi^2 without moving the star, and with the 5 x 5 PSF-R grid the
whole ratio made the V 17-20 position errors 1.2-1.3 x too large on the 1e4-star
frame (normalised residuals 0.85 / 0.76; docs/measure-scale.md, twenty-fifth
pass). The flux keeps the whole chi^2 (an even misfit biases the flux).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from mavispm.measure.stars.chunk_pool import ChunkPool, resolve_threads
from mavispm.measure.stars.crlb import fisher_matrix, jacobian, safe_inverse
from mavispm.measure.stars.variable_psf import StampGeometry, VariableEPSF

__all__ = [
    "ErrorModel",
    "epsf_difference_shifts",
    "estimate_error_model",
    "flux_trend",
]

#: MAD to Gaussian sigma.
_MAD = 1.4826


def epsf_difference_shifts(
    psf: VariableEPSF,
    psf_a: VariableEPSF,
    psf_b: VariableEPSF,
    x: np.ndarray,
    y: np.ndarray,
    flux: np.ndarray,
    sky: np.ndarray,
    read_noise_var: float,
    radius: int,
    chunk: int = 512,
    sky_gradient: bool = False,
    threads: int = 1,
) -> np.ndarray:
    """Linearised change of each star's fit between two ePSFs.

    One Gauss-Newton step from the solution ``(x, y, flux, sky)`` found with
    ``psf``: the parameter change ``A^-1 J^T W F (P_b - P_a)`` that takes the
    model made with ``psf_a`` to the one made with ``psf_b`` (``A = J^T W J`` the
    Fisher matrix, weights ``1 / (sky + F P + RN^2)``). The data drop out: only
    the two ePSFs differ.

    Parameters
    ----------
    psf, psf_a, psf_b : VariableEPSF
        The ePSF of the fit and the two ePSFs to compare.
    x, y : ndarray, shape (N,)
        Fitted positions [pixel].
    flux : ndarray
        Fitted fluxes [electron].
    sky : ndarray
        Fitted local sky [electron/pixel].
    read_noise_var : float
        Read-noise variance per pixel [electron^2].
    radius : int
        Fit stamp half-width [pixel].
    chunk : int
        Stars evaluated at once.
    sky_gradient : bool
        The fit has a sky plane (its slopes take part in the step, as in the fit).
    threads : int
        Threads of the chunks (0: every core; :mod:`~mavispm.measure.stars.chunk_pool`);
        each chunk's rows are its own, the same on any number.

    Returns
    -------
    ndarray, shape (N, 4)
        Change of x, y [pixel], flux [electron] and sky [electron/pixel]; NaN
        for stars with a non-finite input or a singular Fisher matrix.
    """
    x, y, flux, sky = (np.atleast_1d(np.asarray(a, float)) for a in (x, y, flux, sky))
    out = np.full((len(x), 4), np.nan)
    good = np.flatnonzero(
        np.isfinite(x) & np.isfinite(y) & np.isfinite(flux) & np.isfinite(sky) & (flux > 0)
    )
    s = 2 * int(radius) + 1

    def shifts(start):
        idx = good[start : start + chunk]
        geom = StampGeometry(
            np.rint(x[idx]).astype(np.intp), np.rint(y[idx]).astype(np.intp), int(radius)
        )
        v, dvx, dvy = psf.evaluate(x[idx], y[idx], geom)
        va = psf_a.evaluate(x[idx], y[idx], geom, derivatives=False)
        vb = psf_b.evaluate(x[idx], y[idx], geom, derivatives=False)
        f = flux[idx, None]
        var = np.maximum(f * v.reshape(len(idx), -1) + sky[idx, None], 0.0) + read_noise_var
        w = 1.0 / var
        jac = jacobian(flux[idx], v, dvx, dvy, sky_gradient=sky_gradient)
        a = fisher_matrix(jac, w)
        diff = (f * (vb - va).reshape(len(idx), -1)).reshape(len(idx), s * s)
        b = np.einsum("nkm,nm->nk", jac, w * diff)
        cov, ok = safe_inverse(a)
        step = np.einsum("nkl,nl->nk", np.nan_to_num(cov), b)
        step[~ok] = np.nan
        out[idx] = step[:, :4]

    with ChunkPool(resolve_threads(threads)) as pool:
        pool.map(shifts, range(0, len(good), chunk))
    return out


def flux_trend(
    flux: np.ndarray,
    values: np.ndarray,
    statistic: Callable[[np.ndarray], float],
    min_per_bin: int = 20,
    max_bins: int = 12,
    log_values: bool = False,
) -> Callable[[np.ndarray], np.ndarray]:
    """A statistic of ``values`` as a function of flux, from equal-count flux bins.

    Parameters
    ----------
    flux : ndarray, shape (N,)
        Fluxes [electron] (> 0).
    values : ndarray, shape (N,) or (N, K)
        Per-star values (rows pooled per bin).
    statistic : callable
        Reduces the values of one bin to a number.
    min_per_bin : int
        Stars per bin at least (fewer stars: one bin).
    max_bins : int
    log_values : bool
        Interpolate the logarithm of the statistic and extrapolate it linearly in
        log flux beyond the brightest bin (for a statistic growing as a power of
        the flux, like the chi^2 of bright stars); otherwise interpolate linearly
        and hold the end values.

    Returns
    -------
    callable
        ``trend(flux) -> ndarray``.
    """
    flux = np.asarray(flux, float)
    values = np.asarray(values, float)
    order = np.argsort(flux)
    nbins = int(np.clip(len(flux) // max(min_per_bin, 1), 1, max_bins))
    groups = np.array_split(order, nbins)
    centre = np.array([np.median(np.log10(flux[g])) for g in groups])
    stat = np.array([statistic(values[g].ravel()) for g in groups])
    if log_values:
        stat = np.log(np.maximum(stat, 1e-300))
    slope = 0.0
    if log_values and nbins > 1 and centre[-1] > centre[-2]:
        slope = float(np.clip((stat[-1] - stat[-2]) / (centre[-1] - centre[-2]), 0.0, 3.0))

    def trend(f):
        lf = np.log10(np.maximum(np.asarray(f, float), 1e-300))
        out = np.interp(lf, centre, stat)
        beyond = lf > centre[-1]
        out[beyond] += slope * (lf[beyond] - centre[-1])
        return np.exp(out) if log_values else out

    return trend


def _half_rms(v: np.ndarray) -> float:
    """Robust sigma of a difference of two half-set estimates, scaled to the full set."""
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return 0.0
    return float(_MAD * np.median(np.abs(v)) / 2.0)


@dataclass
class ErrorModel:
    """Per-star error terms beyond the Fisher matrix (arrays of length N).

    Parameters
    ----------
    position : ndarray
        ePSF model error of the position [pixel], per coordinate.
    flux : ndarray
        ePSF model error of the flux [electron].
    chi2_ratio : ndarray
        ``max(chi2 / chi2_typ(F), 1)``: the star's fit against its peers'.
    chi2_inflation : ndarray
        ``max(chi2, 1)``, applied to the Fisher variances.
    position_ratio, position_inflation : ndarray, optional
        The same two terms for the positions where they differ from the flux's (the
        residual's odd part, ``chi2_odd`` of :func:`estimate_error_model`); None: the
        flux's.
    kind : {"epsf", "chi2", "fisher"}
        What the terms hold: the ePSF model error and the chi^2 terms, the
        chi^2 terms only, or nothing beyond the Fisher errors.
    registration : ndarray, optional
        The part of ``position`` [pixel] that is the ePSF's registration to a reference
        list (the node centring's error), shared by every epoch registered to the same
        list; None: none.
    """

    position: np.ndarray
    flux: np.ndarray
    chi2_ratio: np.ndarray
    chi2_inflation: np.ndarray
    kind: str = "epsf"
    registration: np.ndarray | None = None
    correlated: np.ndarray | None = None
    position_ratio: np.ndarray | None = None
    position_inflation: np.ndarray | None = None

    def _position_terms(self) -> tuple[np.ndarray, np.ndarray]:
        """The (ratio, inflation) pair of the position terms: ``position_ratio`` and
        ``position_inflation`` where set (the odd part's), else the flux's."""
        ratio = self.chi2_ratio if self.position_ratio is None else self.position_ratio
        infl = self.chi2_inflation if self.position_inflation is None else self.position_inflation
        return ratio, infl

    def position_total(self, fisher_err: np.ndarray, axis: int) -> np.ndarray:
        """Total position error [pixel] of one coordinate: :meth:`total` with the
        position term and the position's chi^2 terms (``position_ratio``,
        ``position_inflation`` where set), plus the correlated-misfit variance of that
        axis (if any).

        Parameters
        ----------
        fisher_err : ndarray
            Fisher errors of the coordinate [pixel].
        axis : int
            0: x, 1: y.

        Returns
        -------
        ndarray
        """
        ratio, infl = self._position_terms()
        base = np.sqrt(fisher_err**2 * infl + self.position**2 * ratio)
        if self.correlated is None:
            return base
        return np.sqrt(base**2 + np.nan_to_num(self.correlated[:, axis]))

    @classmethod
    def fisher_only(
        cls, n: int, chi2_ratio: np.ndarray | None = None, chi2_inflation: np.ndarray | None = None
    ) -> ErrorModel:
        """No model terms (the Fisher errors), optionally with chi^2 terms.

        Parameters
        ----------
        n : int
            Number of stars.
        chi2_ratio, chi2_inflation : ndarray, optional
            The chi^2 terms (default: ones).

        Returns
        -------
        ErrorModel
            Zero model errors; ``kind`` is ``"fisher"`` without chi^2 terms, else ``"chi2"``.
        """
        ones = np.ones(n)
        plain = chi2_ratio is None and chi2_inflation is None
        return cls(
            np.zeros(n),
            np.zeros(n),
            ones if chi2_ratio is None else chi2_ratio,
            ones if chi2_inflation is None else chi2_inflation,
            "fisher" if plain else "chi2",
        )

    def total(self, fisher_err: np.ndarray, model_err: np.ndarray) -> np.ndarray:
        """Total 1-sigma error from a Fisher error and the matching model error.

        ``sqrt(fisher_err^2 chi2_inflation + model_err^2 chi2_ratio)``.

        Parameters
        ----------
        fisher_err : ndarray
            Fisher (Cramer-Rao) errors of the fit.
        model_err : ndarray
            ePSF model errors of the same quantity, same unit.

        Returns
        -------
        ndarray
            Total errors, same unit.
        """
        return np.sqrt(fisher_err**2 * self.chi2_inflation + model_err**2 * self.chi2_ratio)

    def shared_position(self) -> np.ndarray:
        """The registration part of the total position error [pixel] as it enters
        :meth:`total` (``registration sqrt(chi2_ratio)``; zeros without one), so that
        ``total^2 - shared^2`` is the rest.

        Returns
        -------
        ndarray
        """
        if self.registration is None:
            return np.zeros(len(self.position))
        return self.registration * np.sqrt(self._position_terms()[0])


def estimate_error_model(
    flux: np.ndarray,
    chi2: np.ndarray,
    usable: np.ndarray,
    shifts: np.ndarray | None,
    cells: np.ndarray | None = None,
    min_per_bin: int = 20,
    relative_chi2: bool = False,
    floor_fraction: float = 0.0,
    fisher_position: np.ndarray | None = None,
    crowding: np.ndarray | None = None,
    correlated_gain: np.ndarray | None = None,
    halo_share: np.ndarray | None = None,
    chi2_dof: int = 115,
    chi2_odd: np.ndarray | None = None,
) -> ErrorModel:
    """The ePSF error and chi^2 terms of every star.

    Parameters
    ----------
    flux : ndarray, shape (N,)
        Fitted fluxes [electron].
    chi2 : ndarray, shape (N,)
        Reduced chi^2 of each star's fit stamp.
    usable : ndarray of bool
        Stars whose fit succeeded (they set the trends).
    shifts : ndarray, shape (N, 4) or None
        :func:`epsf_difference_shifts` between the two half-ePSFs; None: no ePSF
        term (too few PSF stars to split), chi^2 inflation only.
    cells : ndarray of int, optional
        ePSF grid cell of each star: the median shift of each cell is removed
        first (each half-ePSF's centre is anchored to its own PSF stars, an
        offset common to a cell that the full ePSF does not have).
    min_per_bin : int
        Stars per flux bin at least.
    relative_chi2 : bool
        Inflate the Fisher variances by ``max(chi2 / chi2_typ(F), 1)`` (the star's fit
        against its peers') instead of ``max(chi2, 1)``. For a model whose mismatch
        is centro-symmetric (the PSF-R model: a prior and a Gaussian kernel, both
        centred on the optical axis), a bright star's chi^2 grows with its flux without
        moving it: ``max(chi2, 1)`` made its error 2-4 x too large (normalised residuals
        0.2-0.3 at V 17-20), while stars fitted worse than their peers (blends) are
        still inflated.
    floor_fraction : float
        ``beta`` of the model-error floor added to the position term,
        ``beta sigma_F^2 max(chi2_typ(F) - 1, 0)`` (``sigma_F``: ``fisher_position``):
        the part of a model's misfit (its typical excess chi^2 at the star's flux) that
        moves the star. 0: none.
    fisher_position : ndarray, optional
        Fisher position error per coordinate [pixel] (needed with ``floor_fraction``).
    crowding : ndarray, optional
        With ``relative_chi2``: each star's stamp misfit that its neighbours' light
        explains, ``1 + (chi2 - 1) q`` (:attr:`~mavispm.measure.stars.batched_fit.FitResult.crowding`).
        The Fisher variances are also multiplied by its typical (median) value at the
        star's flux, ``c_typ(F)``: ``chi2_typ(F)`` holds the light of the crowd that
        every peer has, which the ratio divides out although it moves the stars
        (normalised residuals 2.2-2.8 at V 17-25 on the 1e5-star MAVIS frame; with
        the term 1.15-1.4; docs/measure-scale.md). The star's own excess is in the
        ratio already (the per-star value would count it twice).
    correlated_gain : ndarray, shape (N, 2), optional
        :attr:`~mavispm.measure.stars.batched_fit.FitResult.correlated_gain`: the
        position variance [pixel^2] per axis per unit excess reduced chi^2 of a residual
        field at the PSF's scale on the stamp (the part the fit absorbs accounted for).
        The bright stars' mis-modelled light (halo profile, ring corrections, prior
        shape) is such a field: ``correlated = gain max(chi2 - chi2_typ(F) - s(F), 0) h``
        is added to the position variances, ``h`` the halo's share (``halo_share``) of
        the model light on the stamp, ``s(F) = chi2_typ(F) sqrt(2 / dof)`` the noise
        of a reduced chi^2 (only a significant excess counts). As white noise (the chi^2 ratio alone) the same
        misfit moved the stars within 60 px of a V < 15 star ~7x more than their
        errors said on the 1e5-star frame (docs/measure-scale.md, fourteenth pass).
        None: no such term.
    halo_share : ndarray, shape (N,), optional
        :attr:`~mavispm.measure.stars.batched_fit.FitResult.halo_share` (needed with
        ``correlated_gain``; None: no correlated term).
    chi2_dof : int
        Degrees of freedom of a stamp's reduced chi^2 (pixels less fitted parameters).
    chi2_odd : ndarray, shape (N,), optional
        With ``relative_chi2``: the reduced chi^2 of the stamp residual's part odd about
        the star (:func:`~mavispm.measure.stars.odd_residual.odd_chi2`). The position
        terms then take ``max(chi2_odd / chi2_odd_typ(F), 1)`` (its peers' median at the
        star's flux) in place of the ratio of the whole chi^2, which stays the flux's: a
        misfit even about the star (a wrong width or wing of a centred model) raises the
        whole chi^2 without moving it. None: the whole chi^2 for both.

    Returns
    -------
    ErrorModel
    """
    flux = np.asarray(flux, float)
    chi2 = np.asarray(chi2, float)
    n = len(flux)
    inflation = np.where(np.isfinite(chi2), np.maximum(chi2, 1.0), 1.0)
    ref = usable & np.isfinite(flux) & (flux > 0) & np.isfinite(chi2) & (chi2 > 0)
    if shifts is not None:
        ref &= np.all(np.isfinite(shifts[:, :3]), axis=1)
    if ref.sum() < 2:
        return ErrorModel.fisher_only(n, chi2_inflation=inflation)
    f = np.where(np.isfinite(flux) & (flux > 0), flux, np.min(flux[ref]))
    typical = flux_trend(flux[ref], chi2[ref], np.median, min_per_bin, log_values=True)(f)
    ratio = np.where(np.isfinite(chi2), np.maximum(chi2 / typical, 1.0), 1.0)
    correlated = None
    if correlated_gain is not None and halo_share is not None:
        # only an excess beyond the noise of a reduced chi^2 (sqrt(2 / dof) of the
        # typical): a noise-only excess clipped at 0 has a positive mean (0.4 sigma),
        # which inflated every faint star a little. The peers' own scatter would hold
        # the stars near bright ones, the ones to be inflated
        spread = typical * np.sqrt(2.0 / max(chi2_dof, 1))
        excess = np.where(np.isfinite(chi2), np.maximum(chi2 - typical - spread, 0.0), 0.0)
        excess *= np.clip(np.nan_to_num(np.asarray(halo_share, float)), 0.0, 1.0)
        correlated = np.nan_to_num(np.asarray(correlated_gain, float)) * excess[:, None]
    if relative_chi2:
        inflation = ratio
        if crowding is not None:
            crowding = np.asarray(crowding, float)
            peers = ref & np.isfinite(crowding)
            if peers.sum() >= 2:
                typical_crowd = flux_trend(flux[peers], crowding[peers], np.median, min_per_bin)
                inflation = ratio * np.maximum(typical_crowd(f), 1.0)
    pos_ratio = pos_inflation = None
    if relative_chi2 and chi2_odd is not None:
        odd = np.asarray(chi2_odd, float)
        peers = ref & np.isfinite(odd) & (odd > 0)
        if peers.sum() >= 2:
            typical_odd = flux_trend(
                flux[peers], odd[peers], np.median, min_per_bin, log_values=True
            )
            pos_ratio = np.where(np.isfinite(odd), np.maximum(odd / typical_odd(f), 1.0), 1.0)
            # the crowd's typical misfit (c_typ) as for the whole chi^2
            pos_inflation = pos_ratio * inflation / ratio
    floor = np.zeros(n)
    if floor_fraction > 0 and fisher_position is not None:
        sig = np.nan_to_num(np.asarray(fisher_position, float))
        floor = np.sqrt(floor_fraction * np.maximum(typical - 1.0, 0.0)) * sig
    if shifts is None:
        if floor_fraction > 0:
            model = ErrorModel(floor, np.zeros(n), ratio, inflation, "chi2", correlated=correlated)
        else:
            model = replace(ErrorModel.fisher_only(n, ratio, inflation), correlated=correlated)
        return replace(model, position_ratio=pos_ratio, position_inflation=pos_inflation)
    delta = np.column_stack([shifts[:, :2], shifts[:, 2] / f])
    cells = np.zeros(n, np.intp) if cells is None else np.asarray(cells)
    for cell in np.unique(cells[ref]):
        mine = cells == cell
        delta[mine] -= np.median(delta[mine & ref], axis=0)
    position = flux_trend(flux[ref], delta[ref, :2], _half_rms, min_per_bin)(f)
    position = np.hypot(position, floor)
    relative = flux_trend(flux[ref], delta[ref, 2], _half_rms, min_per_bin)(f)
    return ErrorModel(
        position,
        relative * f,
        ratio,
        inflation,
        correlated=correlated,
        position_ratio=pos_ratio,
        position_inflation=pos_inflation,
    )
