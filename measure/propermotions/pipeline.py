"""Epochs in, proper-motion table out: match, align, fit (in memory, no I/O).

This is the work the ``propermotions`` stage does between reading the measured
products and writing the propermotions product; the CLI and the benchmark call
:func:`derive_proper_motions` directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.errors import InputError
from mavispm.measure.propermotions.alignment import (
    AlignmentFit,
    TransformModel,
    fit_transform,
    higher_order_p_value,
    normalisation_length,
    project_displacements,
)
from mavispm.measure.propermotions.epoch_match import EpochMatch, match_epochs
from mavispm.measure.propermotions.inputs import EpochCatalogue, check_epochs
from mavispm.measure.propermotions.motion_fit import (
    LinearMotion,
    fit_linear_motion,
    pm_to_velocity,
    radial_tangential,
)
from mavispm.measure.propermotions.settings import ProperMotionSettings
from mavispm.measure.propermotions.shared_errors import (
    independent_errors,
    shared_mask,
    shared_motion_covariance,
)

__all__ = [
    "ORDER_NOTE_P",
    "PMFlag",
    "ProperMotionResult",
    "derive_proper_motions",
    "extrapolated",
]

MAS = 1e3  # mas per arcsec


class PMFlag:
    """Bits of the propermotions ``flag`` column."""

    CLIPPED = 1  #: rejected as a reference star by sigma clipping (high velocity?)
    NOT_REFERENCE = 2  #: never a reference-star candidate (flagged, faint, ambiguous)
    MISSING_EPOCHS = 4  #: measured in fewer than all epochs
    INPUT_FLAGGED = 8  #: the measure stage flagged it in a used epoch
    AMBIGUOUS = 16  #: positional match had a competing candidate
    AT_CENTRE = 32  #: at the centre: radial/tangential directions undefined (x axis used)
    #: the transformation is extrapolated at the star in some epoch: outside the bounding
    #: box of the reference stars, or where the transformation's (measurement) variance
    #: exceeds its largest value at any reference star (:func:`extrapolated`)
    EXTRAPOLATED = 64
    POOR_FIT = 128  #: multi-epoch positions inconsistent with a straight line
    #: bits that make a proper motion unfit for science (written to the product as the
    #: ``flag_reject_mask`` attribute); 1, 2 and 32 only describe the star's part in the
    #: alignment or its place, and a clipped reference star is often just a fast one
    REJECT = MISSING_EPOCHS | INPUT_FLAGGED | AMBIGUOUS | EXTRAPOLATED | POOR_FIT


@dataclass
class ProperMotionResult:
    """What :func:`derive_proper_motions` returns.

    Parameters
    ----------
    stars : QTable
        The propermotions ``stars`` table (units attached).
    epochs : ndarray
        Epochs [yr], in time order.
    reference_epoch : float
        [yr]
    fits : list of AlignmentFit or None
        Per epoch (None for the reference epoch).
    match : EpochMatch
    motion : LinearMotion
    distance : float or None
        [kpc]
    notes : list of str
        Human-readable remarks (dropped stars, omitted columns).
    """

    stars: QTable
    epochs: np.ndarray
    reference_epoch: float
    fits: list[AlignmentFit | None]
    match: EpochMatch
    motion: LinearMotion
    distance: float | None
    n_dropped: int
    notes: list[str] = field(default_factory=list)

    def transform_summary(self) -> dict:
        """JSON-ready transformation summary per epoch (the product's ``transform`` attr)."""
        out = {"epochs": {}}
        for t, fit in zip(self.epochs, self.fits):
            key = f"{t:g}"
            out["epochs"][key] = "reference" if fit is None else fit.to_dict()
        first = next(f for f in self.fits if f is not None)
        out["order"] = first.model.order
        out["model"] = first.model.name
        out["direction"] = "epoch frame -> reference frame, X = sum p_k * basis_k(x/L, y/L)"
        return out


def _gather(epochs: list[EpochCatalogue], match: EpochMatch, name: str):
    n, n_ep = match.index.shape
    out = np.full((n, n_ep), np.nan)
    for k, ep in enumerate(epochs):
        values = getattr(ep, name)
        if values is None:
            continue
        rows = match.index[:, k]
        has = rows >= 0
        out[has, k] = values[rows[has]]
    return out


def _row_median(values: np.ndarray) -> np.ndarray:
    """Median of the finite values in each row (NaN for rows without any)."""
    out = np.full(values.shape[0], np.nan)
    has = np.any(np.isfinite(values), axis=1)
    if np.any(has):
        out[has] = np.nanmedian(values[has], axis=1)
    return out


def _reference_candidates(k, ref, valid, err, flag, mag, ambiguous, settings):
    cand = valid[:, k] & valid[:, ref] & (flag[:, k] == 0) & (flag[:, ref] == 0) & ~ambiguous
    if settings.ref_max_error is not None:
        lim = settings.ref_max_error / MAS
        cand &= (err[:, k] <= lim) & (err[:, ref] <= lim)
    if settings.ref_mag_max is not None:
        with np.errstate(invalid="ignore"):
            cand &= np.nan_to_num(mag, nan=np.inf) <= settings.ref_mag_max
    return cand


def derive_proper_motions(
    epochs: list[EpochCatalogue],
    settings: ProperMotionSettings,
    truth_pm: dict | None = None,
) -> ProperMotionResult:
    """Match the epochs, align them on the reference epoch and fit proper motions.

    Parameters
    ----------
    epochs : list of EpochCatalogue
        Two or more epochs (any order; sorted in time here).
    settings : ProperMotionSettings
    truth_pm : dict, optional
        ``{"id": ndarray, "pm_x": ndarray, "pm_y": ndarray}`` true proper motions
        [mas/yr] (from a catalogue). Without it, truth positions ``x_true``,
        ``y_true`` in the epochs are used when present.

    Returns
    -------
    ProperMotionResult

    Raises
    ------
    InputError
        No common stars, too few or degenerate reference stars, duplicate epochs,
        non-overlapping fields.
    """
    span = np.ptp([e.epoch for e in epochs]) if len(epochs) else 0.0
    radius = settings.max_pm / MAS * span + settings.match_tolerance
    epochs = check_epochs(list(epochs), margin=radius)
    n_ep = len(epochs)
    t = np.array([e.epoch for e in epochs])
    ref = settings.reference if settings.reference >= 0 else n_ep + settings.reference
    if not 0 <= ref < n_ep:
        raise InputError(f"reference epoch index {settings.reference} out of range for {n_ep}")
    method = settings.match
    if method == "auto" and any(e.blind for e in epochs):
        method = "position"  # blind ids are truth-match ids: an observer matches by position
    match = match_epochs(
        [e.ids for e in epochs],
        [(e.x, e.y) for e in epochs],
        reference=ref,
        radius=radius,
        method=method,
    )
    notes = list(match.notes)
    x, y = _gather(epochs, match, "x"), _gather(epochs, match, "y")
    sx, sy = _gather(epochs, match, "x_err"), _gather(epochs, match, "y_err")
    flag_in = np.where(match.index >= 0, _gather(epochs, match, "flag"), 0).astype(np.int64)
    mag_all = _gather(epochs, match, "mag")
    mag = _row_median(mag_all)
    mag_fit = _row_median(_gather(epochs, match, "mag_fit"))
    # reference stars are chosen by what the observer measured (mag_fit) when the
    # epochs have it; the input magnitudes only for catalogues without it
    mag_ref = mag_fit if np.any(np.isfinite(mag_fit)) else mag
    valid = (match.index >= 0) & np.isfinite(x) & np.isfinite(y)
    valid &= np.isfinite(sx) & np.isfinite(sy) & (sx > 0) & (sy > 0)
    err = np.fmax(sx, sy)
    # the registration to a reference list that epochs share cancels between them: the
    # alignment and the motion fit weigh by the rest, and its remainder is added after
    references = [
        e.registration_reference if e.x_err_registration is not None else None for e in epochs
    ]
    shared = shared_mask(references, valid)
    rx = _gather(epochs, match, "x_err_registration")
    ry = _gather(epochs, match, "y_err_registration")
    sx, sy = independent_errors(sx, rx, shared), independent_errors(sy, ry, shared)
    _note_shared(epochs, shared, rx, ry, notes)
    if settings.ref_mag_max is not None and not np.any(np.isfinite(mag_ref)):
        raise InputError("ref_mag_max is set but no epoch has a 'mag_fit' or 'mag' column")

    model = TransformModel(
        order=settings.order,
        conformal=settings.conformal,
        length=normalisation_length(x[valid[:, ref], ref], y[valid[:, ref], ref]),
    )
    ax = np.where(valid, x, 0.0)
    ay = np.where(valid, y, 0.0)
    vx = np.where(valid, sx**2, 1.0)
    vy = np.where(valid, sy**2, 1.0)
    vxy = np.zeros_like(vx)
    fits: list[AlignmentFit | None] = [None] * n_ep
    frame_sd = np.zeros((x.shape[0], n_ep, 2))
    jac = np.broadcast_to(np.eye(2), (x.shape[0], n_ep, 2, 2)).copy()
    flag = np.zeros(x.shape[0], np.int64)
    ever_candidate = np.zeros(x.shape[0], bool)
    for k in range(n_ep):
        if k == ref:
            continue
        cand = _reference_candidates(
            k, ref, valid, err, flag_in, mag_ref, match.ambiguous, settings
        )
        ever_candidate |= cand
        fit = fit_transform(
            np.where(valid[:, k], x[:, k], 0.0),
            np.where(valid[:, k], y[:, k], 0.0),
            np.where(valid[:, ref], x[:, ref], 0.0),
            np.where(valid[:, ref], y[:, ref], 0.0),
            vx[:, k] + vx[:, ref],
            vy[:, k] + vy[:, ref],
            model,
            candidates=cand,
            clip_sigma=settings.clip_sigma,
            max_iter=settings.clip_iterations,
            what=f"aligning {epochs[k].label} on {epochs[ref].label}",
        )
        fits[k] = fit
        _note_order(fit, x[:, k], y[:, k], x[:, ref], y[:, ref], t[k], notes)
        flag[cand & ~fit.used] |= PMFlag.CLIPPED
        ax[:, k], ay[:, k], vx[:, k], vy[:, k], vxy[:, k], tvar, jac[:, k] = _aligned(
            fit, x[:, k], y[:, k], sx[:, k], sy[:, k], valid[:, k]
        )
        flag[valid[:, k] & extrapolated(fit, x[:, k], y[:, k], *tvar)] |= PMFlag.EXTRAPOLATED
        frame_sd[:, k] = _frame_sd(fit, x[:, k], y[:, k], valid[:, k], t[k] - t[ref])

    keep = np.count_nonzero(valid, axis=1) >= 2
    n_dropped = int(np.count_nonzero(~keep))
    if n_dropped:
        notes.append(f"{n_dropped} star(s) without usable positions in two epochs were left out")
    if not np.any(keep):
        raise InputError("no star has usable positions (finite errors) in two epochs")
    motion = fit_linear_motion(
        t, ax[keep], ay[keep], vx[keep], vy[keep], vxy[keep], valid[keep], t_ref=t[ref]
    )
    if np.any(shared):
        extra = shared_motion_covariance(
            references, shared[keep], motion.coef_x, motion.coef_y, jac[keep], rx[keep], ry[keep]
        )
        motion = replace(
            motion,
            var_pm_x=motion.var_pm_x + extra[0],
            var_pm_y=motion.var_pm_y + extra[1],
            cov_pm_xy=motion.cov_pm_xy + extra[2],
        )
    flag = flag[keep]
    flag[~ever_candidate[keep]] |= PMFlag.NOT_REFERENCE
    flag[motion.n_epochs < n_ep] |= PMFlag.MISSING_EPOCHS
    flag[np.any((flag_in[keep] != 0) & valid[keep], axis=1)] |= PMFlag.INPUT_FLAGGED
    flag[match.ambiguous[keep]] |= PMFlag.AMBIGUOUS
    flag[motion.poor_fit(settings.poor_fit_p)] |= PMFlag.POOR_FIT
    # the frame error is fully correlated between epochs (the same reference stars'
    # motions, growing with the time from the reference epoch): add it linearly
    fsd = frame_sd[keep]
    frame_pm = np.column_stack(
        [
            np.abs(np.sum(motion.coef_x * fsd[:, :, 0], axis=1)),
            np.abs(np.sum(motion.coef_y * fsd[:, :, 1], axis=1)),
        ]
    )

    distance = settings.distance
    if distance is None:
        found = {e.distance for e in epochs if e.distance is not None}
        if len(found) > 1:
            notes.append(f"epochs disagree on the distance {sorted(found)} kpc; using the first")
        distance = next((e.distance for e in epochs if e.distance is not None), None)
    stars = _stars_table(match.ids[keep], motion, mag[keep], flag, settings, distance, notes)
    stars.add_column(
        frame_pm[:, 0] * MAS * u.mas / u.yr,
        name="pm_x_err_frame",
        index=stars.colnames.index("pm_t_err") + 1,
    )
    stars.add_column(
        frame_pm[:, 1] * MAS * u.mas / u.yr,
        name="pm_y_err_frame",
        index=stars.colnames.index("pm_x_err_frame") + 1,
    )
    truth_ids = _truth_ids(epochs, match, ref)
    if truth_ids is not None:  # scoring only (blind epochs: the detections' truth matches)
        stars.add_column(truth_ids[keep], name="id_true", index=1)
    if np.any(np.isfinite(mag_fit[keep])):  # measured magnitude: median over the epochs
        stars.add_column(
            mag_fit[keep] * u.mag, name="mag_fit", index=stars.colnames.index("flag") + 1
        )
    truth = _truth_motion(
        epochs, match, keep, t, ref, fits, valid, x, y, truth_pm, motion, vx, vy, vxy
    )
    if truth is not None:
        stars["pm_x_true"] = truth[0] * MAS * u.mas / u.yr
        stars["pm_y_true"] = truth[1] * MAS * u.mas / u.yr
    return ProperMotionResult(
        stars=stars,
        epochs=t,
        reference_epoch=float(t[ref]),
        fits=fits,
        match=match,
        motion=motion,
        distance=distance,
        n_dropped=n_dropped,
        notes=notes,
    )


#: Below this p-value of the next order's improvement a note recommends a higher order.
ORDER_NOTE_P = 1e-4


def _note_order(fit, x, y, x_ref, y_ref, epoch, notes) -> None:
    p = higher_order_p_value(fit, x, y, x_ref, y_ref)
    if p is not None and p < ORDER_NOTE_P:
        notes.append(
            f"epoch {epoch:g} yr: order {fit.model.order + 1} fits significantly better "
            f"(p = {p:.1e}); the {fit.model.name} transformation leaves an unmodelled "
            "distortion, so PM errors are underestimated - consider a higher order"
        )


def _note_shared(epochs, shared, rx, ry, notes) -> None:
    """A note naming the epochs whose shared registration cancels, and its median [mas]."""
    cols = np.flatnonzero(np.any(shared, axis=0))
    if len(cols) == 0:
        return
    r = np.concatenate([rx[:, cols][shared[:, cols]], ry[:, cols][shared[:, cols]]])
    r = r[np.isfinite(r)]
    median = float(np.median(r)) * MAS if len(r) else 0.0
    names = ", ".join(f"{epochs[k].epoch:g}" for k in cols)
    notes.append(
        f"epochs {names} yr share the registration to "
        f"'{epochs[cols[0]].registration_reference}' (median {median:.3g} mas per axis): "
        "it cancels in the motions and is left out of their errors"
    )


def extrapolated(fit: AlignmentFit, x, y, tx, ty) -> np.ndarray:
    """Where a star's position needs the transformation beyond what its reference stars tie down.

    The rule of flag 64 (:attr:`PMFlag.EXTRAPOLATED`): the position lies outside the
    bounding box of the fit's reference stars, or the variance the transformation's
    measurement covariance gives there (``tx``, ``ty``) exceeds its largest value at
    any reference star (in either axis) - a position of higher leverage than every
    star that constrains the fit, where the polynomial is extrapolated. The
    transformation's variance is part of every star's error; it is not compared with
    the star's own error (that flagged the best-measured stars, whose PMs are fine).

    Parameters
    ----------
    fit : AlignmentFit
        The epoch's transformation (its ``used`` reference stars).
    x, y : ndarray
        Epoch-frame positions [arcsec] of all stars (any value where not valid).
    tx, ty : ndarray
        The transformation's position variance at each star [arcsec^2]
        (:meth:`TransformModel.position_covariance` of ``measurement_covariance``).

    Returns
    -------
    ndarray of bool
    """
    used = fit.used
    xs, ys = x[used], y[used]
    out = (x < xs.min()) | (x > xs.max()) | (y < ys.min()) | (y > ys.max())
    lim_x, lim_y = np.max(tx[used]), np.max(ty[used])
    tol = 1.0 + 1e-9  # round-off at the reference star that sets the limit
    return out | (tx > lim_x * tol) | (ty > lim_y * tol)


def _aligned(fit: AlignmentFit, x, y, sx, sy, valid):
    """Aligned positions, their covariance (measurement + transformation), the
    transformation's own position variances ``(tx, ty)`` [arcsec^2] and its Jacobian
    (n, 2, 2)."""
    xx = np.where(valid, x, 0.0)
    yy = np.where(valid, y, 0.0)
    mx, my = fit.apply(xx, yy)
    jac = fit.model.jacobian(fit.params, xx, yy)
    s2x = np.where(valid, sx**2, 1.0)
    s2y = np.where(valid, sy**2, 1.0)
    var_x = jac[:, 0, 0] ** 2 * s2x + jac[:, 0, 1] ** 2 * s2y
    var_y = jac[:, 1, 0] ** 2 * s2x + jac[:, 1, 1] ** 2 * s2y
    cov = jac[:, 0, 0] * jac[:, 1, 0] * s2x + jac[:, 0, 1] * jac[:, 1, 1] * s2y
    tx, ty, txy = fit.model.position_covariance(fit.measurement_covariance, xx, yy)
    return mx, my, var_x + tx, var_y + ty, cov + txy, (tx, ty), jac


def _frame_sd(fit: AlignmentFit, x, y, valid, dt: float) -> np.ndarray:
    """Signed frame error at each star [arcsec], shape (n, 2).

    The part of the transformation's covariance from the sampling of the reference
    stars' internal motions (full minus measurement covariance) at the star's
    position; it grows with the epoch's distance ``dt`` [yr] from the reference
    epoch (the same stars' motions), so it carries the sign of ``dt`` for the
    fully correlated propagation into the proper motion.
    """
    frame_cov = fit.covariance - fit.measurement_covariance
    xx = np.where(valid, x, 0.0)
    yy = np.where(valid, y, 0.0)
    fx, fy, _ = fit.model.position_covariance(frame_cov, xx, yy)
    sign = np.sign(dt)
    return np.where(valid[:, None], sign * np.sqrt(np.column_stack([fx, fy])), 0.0)


def _stars_table(ids, motion, mag, flag, settings, distance, notes) -> QTable:
    center = (settings.center_x, settings.center_y)
    pm_r, pm_t, err_r, err_t, radius, at_centre = radial_tangential(
        motion.x0,
        motion.y0,
        motion.pm_x,
        motion.pm_y,
        motion.var_pm_x,
        motion.var_pm_y,
        motion.cov_pm_xy,
        center=center,
    )
    flag[at_centre] |= PMFlag.AT_CENTRE
    ex = np.sqrt(motion.var_pm_x)
    ey = np.sqrt(motion.var_pm_y)
    pmu = u.mas / u.yr
    stars = QTable()
    stars["id"] = np.asarray(ids, np.int64)
    stars["x"] = motion.x0 * u.arcsec
    stars["y"] = motion.y0 * u.arcsec
    stars["R"] = radius * u.arcsec
    stars["pm_x"] = motion.pm_x * MAS * pmu
    stars["pm_y"] = motion.pm_y * MAS * pmu
    stars["pm_x_err"] = ex * MAS * pmu
    stars["pm_y_err"] = ey * MAS * pmu
    stars["pm_xy_corr"] = np.clip(motion.cov_pm_xy / (ex * ey), -1.0, 1.0)
    stars["pm_r"] = pm_r * MAS * pmu
    stars["pm_t"] = pm_t * MAS * pmu
    stars["pm_r_err"] = err_r * MAS * pmu
    stars["pm_t_err"] = err_t * MAS * pmu
    stars["n_epochs"] = motion.n_epochs.astype(np.int64)
    stars["flag"] = flag
    if np.any(np.isfinite(mag)):
        stars["mag"] = mag * u.mag
    if distance is not None:
        d = distance * u.kpc
        for name in (
            "pm_x",
            "pm_y",
            "pm_x_err",
            "pm_y_err",
            "pm_r",
            "pm_t",
            "pm_r_err",
            "pm_t_err",
        ):
            stars["v" + name[2:]] = pm_to_velocity(stars[name], d)
    else:
        notes.append("no distance given or found in the products: km/s columns omitted")
    return stars


def _truth_ids(epochs: list[EpochCatalogue], match: EpochMatch, ref: int) -> np.ndarray | None:
    """Truth id of every matched star (scoring only), or None when no epoch has ``id_true``.

    The reference epoch's ``id_true`` where the star is there, else the first epoch's
    that has it; an epoch without the column contributes its ``id`` (forced
    photometry: the input list's ids are the truth ids); -1 where unknown.
    """
    if not any(e.ids_true is not None for e in epochs):
        return None
    n = match.index.shape[0]
    out = np.full(n, -1, np.int64)
    done = np.zeros(n, bool)
    for k in [ref] + [k for k in range(len(epochs)) if k != ref]:
        ep = epochs[k]
        true = ep.ids if ep.ids_true is None else ep.ids_true
        rows = match.index[:, k]
        take = (rows >= 0) & ~done
        out[take] = true[rows[take]]
        done |= take
    return out


def _truth_motion(epochs, match, keep, t, ref, fits, valid, x, y, truth_pm, motion, vx, vy, vxy):
    """True proper motions [arcsec/yr] expressed in the measured relative frame, or None.

    The true motion of every star is turned into displacements at each epoch;
    the part each epoch's transformation absorbs (re-fitted with that fit's
    reference stars and weights) is removed, and the rest goes through the same
    weighted least squares as the measurements.
    """
    n = match.index.shape[0]
    pm_true = np.full((n, 2), np.nan)
    if truth_pm is not None:
        truth_ids = _truth_ids(epochs, match, ref)
        ids = match.ids if truth_ids is None else truth_ids
        order = np.argsort(truth_pm["id"])
        sid = np.asarray(truth_pm["id"])[order]
        pos = np.clip(np.searchsorted(sid, ids), 0, max(sid.size - 1, 0))
        found = sid.size > 0
        hit = found & (sid[pos] == ids) & (ids >= 0)
        pm_true[hit, 0] = np.asarray(truth_pm["pm_x"])[order][pos[hit]] / MAS
        pm_true[hit, 1] = np.asarray(truth_pm["pm_y"])[order][pos[hit]] / MAS
    elif all(e.x_true is not None and e.y_true is not None for e in epochs):
        xt, yt = _gather(epochs, match, "x_true"), _gather(epochs, match, "y_true")
        ok = np.isfinite(xt) & np.isfinite(yt)
        n_ok = np.count_nonzero(ok, axis=1)
        w = ok.astype(float)
        has = n_ok >= 2
        tb = (w * t).sum(axis=1) / np.maximum(n_ok, 1)
        dt = np.where(ok, t - tb[:, None], 0.0)
        stt = (dt**2).sum(axis=1)
        stt = np.where(stt > 0, stt, np.nan)
        pm_true[has, 0] = (dt * np.where(ok, xt, 0.0)).sum(axis=1)[has] / stt[has]
        pm_true[has, 1] = (dt * np.where(ok, yt, 0.0)).sum(axis=1)[has] / stt[has]
    else:
        return None
    known = np.all(np.isfinite(pm_true), axis=1)
    if not np.any(known):
        return None
    dx = pm_true[:, 0:1] * (t - t[ref])[None, :]
    dy = pm_true[:, 1:2] * (t - t[ref])[None, :]
    for k, fit in enumerate(fits):
        if fit is None:
            continue
        used = fit.used & known
        sub = AlignmentFit(**{**fit.__dict__, "used": used})
        xk = np.where(valid[:, k], x[:, k], 0.0)
        yk = np.where(valid[:, k], y[:, k], 0.0)
        px, py = project_displacements(
            sub, xk, yk, np.nan_to_num(dx[:, k]), np.nan_to_num(dy[:, k]), xk, yk
        )
        dx[:, k] -= px
        dy[:, k] -= py
    rel = fit_linear_motion(
        t,
        np.nan_to_num(dx[keep]),
        np.nan_to_num(dy[keep]),
        vx[keep],
        vy[keep],
        vxy[keep],
        valid[keep],
        t_ref=t[ref],
    )
    out_x = np.where(known[keep], rel.pm_x, np.nan)
    out_y = np.where(known[keep], rel.pm_y, np.nan)
    return out_x, out_y
