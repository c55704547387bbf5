"""Centre each ePSF node on all well-measured stars near it.

An ePSF and the positions fitted with it are degenerate: move a node's ePSF by
``s`` and every star it models moves by ``-s``. The builder
(:func:`mavispm.measure.stars.epsf.build_epsf_fast`) fixes the centre of each
node on the mean start position of that node's PSF stars, so the node's centre
carries the mean start-position error of ~100 stars (start error / sqrt(stars
per node)) and, between nodes, the part of the field variation the bilinear
interpolation does not follow.

Here every star the fit measured well takes part instead: the corrections
``fitted - start`` of all usable stars are modelled as the node shifts mixed with
the ePSF's own interpolation weights (``d_i = sum_k w_ik s_k``), solved by
weighted least squares (weights ``1 / (fisher_i^2 + start^2)``; the start-position
scatter is estimated from the residuals of the best-measured stars, so no
setting or truth enters), and each node's ePSF is moved by its shift. The
stars' fitted positions then move by the interpolated shift (first order in the
shift, a few hundredths of a pixel). The convention stays the start list's: the
mean correction over the stars near each node is zero, as it was over its PSF
stars, now averaged over ~10 x more stars.

The reference list is the epoch's own start: a first epoch's input list (forced,
or the detections), or, at a later epoch in observer mode, the start refined on
this frame with the earlier epoch's ePSF
(:func:`mavispm.measure.stars.measure_frame.refined_start`). Those refined
positions are measured at this epoch, so the stars' motions are in both the
reference and the fit and no proper motion is absorbed, not even a node's mean
motion; what the centring takes up is the difference between the earlier and the
new ePSF's centre as the stars' fits see it (a bilinear field over the nodes), so
the later epoch keeps the first epoch's convention star by star. A carried start
that was not refined with the earlier ePSF (``refine_start = false``, or
``epsf_anchor = "start"``) holds the motions (0.3 px rms over 10 yr on the NGC 3201
field: 0.3 / sqrt(~350) ~ 0.016 px per node) and is not used. The centring's own
error (:meth:`NodeCentring.error_at`) enters the error model; a later epoch adds
the earlier epoch's (its convention's error, :func:`centring_from_summary`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import replace

import numpy as np

from mavispm.measure.stars.batched_fit import (
    FLAG_FAILED,
    FLAG_NOT_CONVERGED,
    FLAG_SATURATED,
    crowding_flags,
)
from mavispm.measure.stars.epsf_anchor import shift_epsf
from mavispm.measure.stars.error_model import epsf_difference_shifts
from mavispm.measure.stars.variable_psf import VariableEPSF, constant_epsf, gridded_epsf

__all__ = [
    "NodeCentring",
    "centred_on_all_stars",
    "centring_from_summary",
    "centring_summary",
    "node_shifts",
    "recentred_epsf",
    "reference_list_id",
]

#: Rejection threshold of the corrections [sigma].
CLIP_SIGMA = 5.0


class NodeCentring:
    """The node shifts of one ePSF and the start-position scatter they were solved with.

    Parameters
    ----------
    shifts : ndarray, shape (K, 2)
        Per-node mean correction ``fitted - start`` (x, y) [pixel].
    start_sigma : float
        Estimated start-position scatter per axis [pixel].
    n_used : int
        Stars used.
    cov : ndarray, shape (K, K), optional
        Covariance of the node shifts per axis [pixel^2] (the least-squares inverse
        normal matrix scaled by the residuals' reduced chi^2); None: unknown.
    reference_id : str, optional
        Names the reference list the nodes were registered to
        (:func:`reference_list_id`); epochs whose errors hold this registration share
        it. None: not known (products written before 2026-12-02).
    """

    def __init__(
        self, shifts: np.ndarray, start_sigma: float, n_used: int, cov=None, reference_id=None
    ):
        self.shifts = np.asarray(shifts, float)
        self.start_sigma = float(start_sigma)
        self.n_used = int(n_used)
        self.cov = None if cov is None else np.asarray(cov, float)
        self.reference_id = reference_id

    def error_at(self, psf: VariableEPSF, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Per-axis error [pixel] of the interpolated shift at ``x, y`` (zeros without ``cov``).

        Parameters
        ----------
        psf : VariableEPSF
            The ePSF whose interpolation weights mix the nodes.
        x, y : ndarray
            Pixel positions.

        Returns
        -------
        ndarray, shape (N,)
        """
        if self.cov is None:
            return np.zeros(np.shape(x))
        idx, w = psf.mixing(np.nan_to_num(x), np.nan_to_num(y))
        block = self.cov[idx[:, :, None], idx[:, None, :]]
        return np.sqrt(np.maximum(np.einsum("nm,nml,nl->n", w, block, w), 0.0))

    def at(self, psf: VariableEPSF, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Interpolated shift (N, 2) [pixel] at pixel positions ``x, y`` (NaN stays NaN)."""
        idx, w = psf.mixing(np.nan_to_num(x), np.nan_to_num(y))
        out = np.einsum("nm,nmc->nc", w, self.shifts[idx])
        out[~(np.isfinite(x) & np.isfinite(y))] = np.nan
        return out


def _solve(idx, w, d, weight, k):
    """Weighted least squares for node shifts ``s`` (K, 2) in ``d = W_mix s``."""
    n = len(d)
    design = np.zeros((n, k))
    np.add.at(design, (np.repeat(np.arange(n), idx.shape[1]), idx.ravel()), w.ravel())
    a = design.T @ (design * weight[:, None])
    b = design.T @ (d * weight[:, None])
    # a node without stars keeps its centre: a small ridge to zero shift
    a += np.eye(k) * 1e-9 * max(np.trace(a) / k, 1e-30)
    return np.linalg.solve(a, b), a


def node_shifts(
    psf: VariableEPSF,
    x: np.ndarray,
    y: np.ndarray,
    x_start: np.ndarray,
    y_start: np.ndarray,
    fisher_err: np.ndarray,
    usable: np.ndarray,
) -> NodeCentring:
    """Per-node mean correction ``fitted - start`` over all usable stars.

    Parameters
    ----------
    psf : VariableEPSF
        The ePSF of the fit (its ``mixing`` gives the interpolation weights).
    x, y : ndarray
        Fitted positions [pixel].
    x_start, y_start : ndarray
        Start positions [pixel].
    fisher_err : ndarray
        Per-axis Fisher position error of each star [pixel].
    usable : ndarray of bool
        Stars to use (converged, not crowded, finite).

    Returns
    -------
    NodeCentring
    """
    d = np.column_stack([x - x_start, y - y_start])
    ok = usable & np.all(np.isfinite(d), axis=1) & np.isfinite(fisher_err) & (fisher_err > 0)
    k = psf.n_basis
    if ok.sum() < 2 * k:
        return NodeCentring(np.zeros((k, 2)), np.nan, 0)
    sel = np.flatnonzero(ok)
    idx, w = psf.mixing(x[sel], y[sel])
    fe2 = fisher_err[sel] ** 2
    start_var = 0.0
    keep = np.ones(len(sel), bool)
    for _ in range(3):
        s, _ = _solve(idx[keep], w[keep], d[sel][keep], 1.0 / (fe2[keep] + start_var), k)
        resid = d[sel] - _mix(idx, w, s)
        # start-position scatter: the residual scatter of the best-measured quarter
        # less their Fisher variance (robust)
        best = keep & (fe2 <= np.quantile(fe2[keep], 0.25))
        mad = 1.4826 * np.median(np.abs(resid[best] - np.median(resid[best], axis=0)))
        start_var = max(mad**2 - float(np.median(fe2[best])), 0.0)
        sigma = np.sqrt(fe2 + start_var)
        keep = np.all(np.abs(resid) < CLIP_SIGMA * sigma[:, None], axis=1)
    weight = 1.0 / (fe2[keep] + start_var)
    s, normal = _solve(idx[keep], w[keep], d[sel][keep], weight, k)
    resid = (d[sel] - _mix(idx, w, s))[keep]
    dof = max(2 * (int(keep.sum()) - k), 1)
    reduced = float(np.sum(resid**2 * weight[:, None]) / dof)
    cov = np.linalg.inv(normal) * max(reduced, 1.0)
    return NodeCentring(s, np.sqrt(start_var), int(keep.sum()), cov)


def _mix(idx, w, s):
    return np.einsum("nm,nmc->nc", w, s[idx])


def recentred_epsf(psf: VariableEPSF, centring: NodeCentring) -> VariableEPSF:
    """``psf`` with each node's ePSF moved by its shift (grid or constant ePSFs).

    A star modelled with the moved ePSF fits at its old position less the
    interpolated shift, so the mean correction near every node becomes zero.

    Parameters
    ----------
    psf : VariableEPSF
        A ``"grid"`` or ``"constant"`` ePSF.
    centring : NodeCentring
        Its node shifts.

    Returns
    -------
    VariableEPSF
    """
    os_ = psf.oversampling
    # shift_epsf moves by minus its arguments: the ePSF moves by +shift, the fitted
    # positions by -shift
    basis = np.asarray(
        [shift_epsf(b, os_, -sx, -sy) for b, (sx, sy) in zip(psf.basis, centring.shifts)]
    )
    if psf.kind == "constant":
        return constant_epsf(basis[0], os_)
    return gridded_epsf(
        basis, np.asarray(psf.meta["nodes_x"]), np.asarray(psf.meta["nodes_y"]), os_
    )


def centred_on_all_stars(frame, frame_psf, fit, x0, y0, settings):
    """Centre every ePSF node on all well-measured stars near it (``epsf_centring = "all"``).

    The per-node shifts of the corrections ``fit - start``
    (:func:`mavispm.measure.stars.node_centring.node_shifts`) move the node ePSFs,
    and the fitted positions move by the interpolated shift (first order). Each
    half-set ePSF of the error model is centred in the same way on the same stars
    (its positions are the fit's moved by the linearised change of fitting with that
    half's ePSF), so the half difference holds the ePSF's shape noise and not the
    centring's, which :meth:`NodeCentring.error_at` gives. Gridded ePSFs only;
    others are returned unchanged (a constant ePSF follows no field variation, and
    its errors keep the ``max(chi2, 1)`` inflation that stands for it).

    Parameters
    ----------
    frame : mavispm.core.frame.Frame
        The frame [electron].
    frame_psf : mavispm.measure.stars.measure_frame.FramePSF
        The ePSF (and half-set ePSFs) of the fit.
    fit : mavispm.measure.stars.batched_fit.FitResult
        The fit of all stars with ``frame_psf.psf``.
    x0, y0 : ndarray
        Start positions [pixel].
    settings : mavispm.measure.stars.settings.MeasureSettings
        The stage settings (crowding cuts, stamp radius).

    Returns
    -------
    frame_psf : mavispm.measure.stars.measure_frame.FramePSF
        With the centred ePSF and halves, and ``centring`` (the full ePSF's
        :class:`NodeCentring` first, then the halves'); unchanged for other kinds.
    fit : mavispm.measure.stars.batched_fit.FitResult
        With the fitted positions moved.
    """
    psf = frame_psf.psf
    if psf.kind != "grid":
        return frame_psf, fit
    usable = (fit.flag & (FLAG_FAILED | FLAG_SATURATED | FLAG_NOT_CONVERGED)) == 0
    usable &= ~crowding_flags(
        fit.x, fit.y, fit.flux, settings.crowding_radius, settings.crowding_ratio
    )
    fisher = np.hypot(fit.x_err, fit.y_err) / np.sqrt(2.0)
    full = node_shifts(psf, fit.x, fit.y, x0, y0, fisher, usable)
    if full.n_used == 0:
        return frame_psf, fit
    shift = full.at(psf, fit.x, fit.y)
    moved = replace(fit, x=fit.x - shift[:, 0], y=fit.y - shift[:, 1])
    centrings = [full]
    halves = frame_psf.halves
    if halves is not None:
        sky = np.where(np.isfinite(fit.sky), fit.sky, frame.sky)
        centred = []
        for half_psf in halves:
            change = epsf_difference_shifts(
                psf, psf, half_psf, np.where(usable, fit.x, np.nan), fit.y, fit.flux, sky,
                frame.read_noise_var, settings.stamp_radius, settings.chunk,
                sky_gradient=settings.sky_gradient and settings.engine == "fast",
            )  # fmt: skip
            # the step takes a model made with psf to one made with the half as the
            # data: fitting the same data with the half moves a star the other way
            c = node_shifts(
                half_psf, fit.x - change[:, 0], fit.y - change[:, 1], x0, y0, fisher, usable
            )
            centrings.append(c)
            centred.append(recentred_epsf(half_psf, c) if c.n_used else half_psf)
        halves = tuple(centred)
    frame_psf = replace(
        frame_psf, psf=recentred_epsf(psf, full), halves=halves, centring=tuple(centrings)
    )
    return frame_psf, moved


def reference_list_id(label: str, epoch: float, ids, x, y) -> str:
    """Name of a reference list: ``"<label>@<epoch>yr:<digest>"``, the digest (SHA-256,
    16 hex digits) of its ids and pixel positions.

    Two measurements centred on the same list share its registration error, and only
    then (the proper-motion stage cancels it between epochs that name the same list).

    Parameters
    ----------
    label : str
        Where the list came from (the measured product's ``start``: ``"truth"``,
        ``"detected"``, ``"measured"``).
    epoch : float
        Epoch of the frame it was used on [yr].
    ids : ndarray of int
        Star ids.
    x, y : ndarray
        Positions [pixel].

    Returns
    -------
    str
    """
    digest = hashlib.sha256()
    for a, dtype in ((ids, np.int64), (x, np.float64), (y, np.float64)):
        digest.update(np.ascontiguousarray(a, dtype).tobytes())
    return f"{label}@{epoch:g}yr:{digest.hexdigest()[:16]}"


def centring_summary(
    centring, pixel_scale: float, reference: str = "start", reference_id: str | None = None
) -> str:
    """JSON of the node centring: ``"psf_stars"``, or ``"all"`` with the rms node shift
    [mas], the stars used, the estimated scatter of the reference positions [mas], the
    reference (``"start"``: the input list; ``"refined"``: a later epoch's start
    refined with the earlier ePSF), its name ``reference_id``
    (:func:`reference_list_id`) and the node shifts' covariance per axis
    ``cov_pix2`` [pixel^2] (a later epoch anchored to this one adds its error).

    Parameters
    ----------
    centring : tuple of NodeCentring or None
        :func:`centred_on_all_stars`'s centrings (full ePSF first).
    pixel_scale : float
        [arcsec / pixel].
    reference : {"start", "refined"}
        The positions the nodes were centred on.
    reference_id : str, optional
        Their name (:func:`reference_list_id`).

    Returns
    -------
    str
    """
    if not centring:
        return json.dumps({"centring": "psf_stars"})
    full = centring[0]
    mas = pixel_scale * 1000.0
    rms = np.sqrt(np.mean(full.shifts**2, axis=0)) * mas
    out = {
        "centring": "all",
        "reference": reference,
        "reference_id": reference_id,
        "n_stars": full.n_used,
        "rms_shift_mas": [float(v) for v in rms],
        "start_sigma_mas": float(full.start_sigma * mas),
    }
    if full.cov is not None:
        out["cov_pix2"] = full.cov.tolist()
    return json.dumps(out)


def centring_from_summary(text: str | None) -> NodeCentring | None:
    """The node centring's error of an earlier product (its ``epsf_centring`` attribute).

    Parameters
    ----------
    text : str or None
        The attribute (JSON, :func:`centring_summary`).

    Returns
    -------
    NodeCentring or None
        Zero shifts (the earlier ePSF is already centred), the covariance
        ``cov_pix2`` and the ``reference_id`` (None where not written); None where the nodes were not centred on all stars or no
        covariance was written.

    Raises
    ------
    ValueError
        A covariance that is not square.
    """
    if not text:
        return None
    meta = json.loads(text)
    if meta.get("centring") != "all" or "cov_pix2" not in meta:
        return None
    cov = np.asarray(meta["cov_pix2"], float)
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
        raise ValueError(f"epsf_centring: cov_pix2 of shape {cov.shape} is not square")
    # the start scatter is kept in mas there; the covariance is what a later epoch needs
    return NodeCentring(
        np.zeros((cov.shape[0], 2)),
        np.nan,
        int(meta.get("n_stars", 0)),
        cov,
        reference_id=meta.get("reference_id"),
    )
