"""Post-fit rescue of the stars the batched fit left failed or unconverged.

After the fast engine's last pass, a star flagged 32 (SNR below ``min_snr``, or never
fitted) or 1 (not converged) is refitted together with its neighbours within
``radius`` (at most ``max_neighbours``, nearest first) on a square window around its
start: every group member's position and flux and a local sky plane free, the light of
every other star (their stamp models, the bright stars' halos) subtracted as the fit
left it. The group is fitted (Levenberg-Marquardt, model weights fixed at the fit's
light) from several starts for the star: its fitted position, its start-list position,
and the pair with its nearest neighbour split along their axis about the midpoint; and
once without the star. The best start is kept only when it converged, the star stays
within ``max_shift`` of its start, the window's reduced chi^2 stays below
``max_misfit``, its flux SNR (the group's Fisher matrix, every other
parameter marginalised) reaches ``min_snr``, and the star lowers the window's chi^2 by
at least ``min_gain`` against the group without it (a likelihood-ratio test: an extra
star a blend does not support is not kept). Otherwise the star keeps its flags.

Only the rescued star's own values change; its neighbours keep what the fit gave them
(their refits serve the star's solution only), so every star not rescued comes out of
the stage as it went in. Observer footing: nothing here reads the truth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from mavispm.measure.stars.batched_fit import FLAG_FAILED, FLAG_NOT_CONVERGED
from mavispm.measure.stars.crlb import safe_inverse
from mavispm.measure.stars.odd_residual import odd_chi2
from mavispm.measure.stars.variable_psf import StampGeometry, VariableEPSF

__all__ = ["RescueOptions", "Rescued", "rescue_stars"]

#: Flags that make a star a rescue candidate: not converged (1) or failed (32).
CANDIDATE_FLAGS = FLAG_NOT_CONVERGED | FLAG_FAILED

#: Candidates refitted at once (memory: ~2 MB each).
CHUNK = 512


@dataclass(frozen=True)
class RescueOptions:
    """Knobs of the rescue pass.

    Parameters
    ----------
    radius : float
        Neighbours closer than this to the star's start [pixel] are refitted with it.
    stamp_radius : int
        The fitter's stamp half-width [pixel]: the stars' models in the fit's light
        cover these stamps, and so does the refit window (``margin``).
    min_snr : float
        The star's flux SNR needed.
    max_shift : float
        Largest distance of the star from its start [pixel].
    min_gain : float
        Least chi^2 decrease the star must bring to its group's window.
    max_neighbours : int
        Neighbours refitted with the star, nearest first.
    iterations : int
        Levenberg-Marquardt iterations at most.
    tolerance : float
        Converged when every position step is below this [pixel].
    margin : int
        The window's half-width is ``stamp_radius + margin`` [pixel].
    max_misfit : float
        Largest reduced chi^2 of the window at the solution: above it the rest of the
        light is too mis-modelled for the group's Fisher errors to hold (on the 1e5-star
        frame the stars rescued in windows with chi^2 > 10 landed a median 0.5 px from
        the truth).
    inflate : bool
        The rescued stars' Fisher errors times ``sqrt(max(chi2_red, 1))`` of the window.
    """

    radius: float = 6.0
    stamp_radius: int = 5
    min_snr: float = 3.0
    max_shift: float = 2.0
    min_gain: float = 9.0
    max_neighbours: int = 3
    iterations: int = 20
    tolerance: float = 2e-3
    margin: int = 0
    max_misfit: float = 3.0
    inflate: bool = True


@dataclass
class Rescued:
    """The rescued stars' new values (arrays of length R, rows of ``index``).

    ``chi2`` and ``chi2_odd`` are the star's stamp's (radius ``stamp_radius`` about its
    new position) at the group's solution, ``crowding`` ``1 + (chi2 - 1) q`` with ``q``
    the neighbours' share of the model light there, as the fitter defines them.
    ``tried`` is the number of candidates, ``gain`` the chi^2 decrease of each.
    """

    index: np.ndarray
    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    sky: np.ndarray
    x_err: np.ndarray
    y_err: np.ndarray
    flux_err: np.ndarray
    sky_err: np.ndarray
    chi2: np.ndarray
    chi2_odd: np.ndarray
    crowding: np.ndarray
    gain: np.ndarray
    tried: int


def _own_models(psf, fx, fy, flux, x0, y0, r):
    """Each star's stamp model as the fitter deposited it: flux times the ePSF at the
    fitted position, on the stamp about its rounded start, mixed at its start."""
    geom = StampGeometry(np.rint(x0).astype(np.intp), np.rint(y0).astype(np.intp), r)
    v = psf.evaluate(fx, fy, geom, mix=psf.mixing(x0, y0), derivatives=False)
    return np.nan_to_num(flux)[:, None, None] * v, geom


def rescue_stars(
    image: np.ndarray,
    light: np.ndarray,
    psf: VariableEPSF,
    fit,
    x0: np.ndarray,
    y0: np.ndarray,
    read_noise_var: float,
    sky0: float,
    bad: np.ndarray | None = None,
    saturated: np.ndarray | None = None,
    options: RescueOptions | None = None,
) -> Rescued:
    """Refit the stars flagged 1 or 32 with their neighbours; keep the supported ones.

    Parameters
    ----------
    image : ndarray, shape (ny, nx)
        The frame [electron].
    light : ndarray, shape (ny, nx)
        All the light the fit modelled (:attr:`FitResult.light_image`) [electron].
    psf : VariableEPSF
        The ePSF the fit used.
    fit : FitResult
        The fit (not changed).
    x0, y0 : ndarray
        The fit's start positions [pixel].
    read_noise_var : float
        Read-noise variance per pixel [electron^2].
    sky0 : float
        The frame's sky [electron/pixel], where a star's own is not finite.
    bad, saturated : ndarray of bool, optional
        Pixels left out.
    options : RescueOptions, optional

    Returns
    -------
    Rescued
    """
    opt = options or RescueOptions()
    ny, nx = image.shape
    r = int(opt.stamp_radius)
    w_half = r + opt.margin
    x0 = np.asarray(x0, float)
    y0 = np.asarray(y0, float)
    fx, fy = np.asarray(fit.x, float), np.asarray(fit.y, float)
    flux = np.asarray(fit.flux, float)
    cxw, cyw = np.rint(x0).astype(np.intp), np.rint(y0).astype(np.intp)
    inside = (
        np.isfinite(x0) & (cxw >= w_half) & (cxw < nx - w_half)
        & (cyw >= w_half) & (cyw < ny - w_half)
    )  # fmt: skip
    cand = np.flatnonzero(((np.asarray(fit.flag) & CANDIDATE_FLAGS) != 0) & inside)
    lit = np.isfinite(flux) & np.isfinite(fx) & np.isfinite(fy)
    lit_idx = np.flatnonzero(lit)
    kp = opt.max_neighbours + 1
    members = np.full((len(cand), kp), -1, np.intp)
    members[:, 0] = cand
    if len(cand) and len(lit_idx):
        tree = cKDTree(np.column_stack([fx[lit_idx], fy[lit_idx]]))
        dist, near = tree.query(
            np.column_stack([x0[cand], y0[cand]]), k=kp + 1, distance_upper_bound=opt.radius
        )
        for row, i in enumerate(cand):
            nb = lit_idx[near[row][np.isfinite(dist[row])]]
            nb = nb[nb != i][: opt.max_neighbours]
            members[row, 1 : 1 + len(nb)] = nb
    # a blend: at least one neighbour to refit with the star
    blend = members[:, 1] >= 0
    cand, members = cand[blend], members[blend]
    parts = [
        _rescue_chunk(
            image,
            light,
            psf,
            fit,
            x0,
            y0,
            read_noise_var,
            sky0,
            bad,
            saturated,
            opt,
            cand[lo : lo + CHUNK],
            members[lo : lo + CHUNK],
        )  # fmt: skip
        for lo in range(0, len(cand), CHUNK)
    ]
    if not parts:
        empty = np.zeros(0)
        return Rescued(np.zeros(0, np.intp), *([empty] * 12), tried=0)
    fields = {
        key: np.concatenate([getattr(q, key) for q in parts])
        for key in Rescued.__dataclass_fields__
        if key != "tried"
    }
    return Rescued(**fields, tried=len(cand))


def _rescue_chunk(image, light, psf, fit, x0, y0, read_noise_var, sky0, bad, saturated, opt,
                  cand, members):  # fmt: skip
    """:func:`rescue_stars` on the candidates ``cand`` with their group ``members``."""
    ny, nx = image.shape
    r = int(opt.stamp_radius)
    w_half = r + opt.margin
    fx, fy = np.asarray(fit.x, float), np.asarray(fit.y, float)
    flux = np.asarray(fit.flux, float)
    cxw, cyw = np.rint(x0).astype(np.intp), np.rint(y0).astype(np.intp)
    kp = members.shape[1]
    present = members >= 0
    c = len(cand)
    s = 2 * w_half + 1
    m = s * s
    # the window's data less every other star's light: the fit's light with the group's
    # own stamp models added back
    off = np.arange(-w_half, w_half + 1)
    rows = cyw[cand][:, None] + off[None, :]
    cols = cxw[cand][:, None] + off[None, :]
    flat = (rows[:, :, None] * nx + cols[:, None, :]).reshape(c, m)
    data = np.asarray(image).reshape(-1)[flat].astype(float)
    rest = np.asarray(light).reshape(-1)[flat].astype(float)
    # the fit modelled the light on its stamps only (NaN elsewhere)
    valid = np.isfinite(data) & np.isfinite(rest)
    for mask in (bad, saturated):
        if mask is not None:
            valid &= ~np.asarray(mask, bool).reshape(-1)[flat]
    mem = members[present]
    own, geom = _own_models(psf, fx[mem], fy[mem], flux[mem], x0[mem], y0[mem], r)
    srow, scol = np.nonzero(present)
    for k in range(len(mem)):
        row = srow[k]
        oy = geom.cy[k] - r - (cyw[cand[row]] - w_half)
        ox = geom.cx[k] - r - (cxw[cand[row]] - w_half)
        y_lo, y_hi = max(oy, 0), min(oy + 2 * r + 1, s)
        x_lo, x_hi = max(ox, 0), min(ox + 2 * r + 1, s)
        if y_lo >= y_hi or x_lo >= x_hi:
            continue
        block = rest[row].reshape(s, s)
        block[y_lo:y_hi, x_lo:x_hi] -= own[k, y_lo - oy : y_hi - oy, x_lo - ox : x_hi - ox]
    rest = np.where(valid, rest, 0.0)
    target = np.where(valid, data - rest, 0.0)
    sky_i = np.asarray(fit.sky, float)[cand]
    sky_i = np.where(np.isfinite(sky_i), sky_i, sky0)
    variance = np.maximum(np.nan_to_num(np.asarray(light).reshape(-1)[flat]), 0.0) + sky_i[:, None]
    weight = np.where(valid, 1.0 / np.maximum(variance + read_noise_var, 1e-6), 0.0)

    # the problems: 0 without the star, 1 its fitted position, 2 its start, 3 the split
    # pair (nearest neighbour)
    n_start = 4
    px = np.repeat(np.where(present, fx[np.maximum(members, 0)], 0.0)[:, None], n_start, 1)
    py = np.repeat(np.where(present, fy[np.maximum(members, 0)], 0.0)[:, None], n_start, 1)
    pf = np.repeat(
        np.where(present, np.nan_to_num(flux[np.maximum(members, 0)]), 0.0)[:, None], n_start, 1
    )
    px[:, 2, 0], py[:, 2, 0] = x0[cand], y0[cand]
    has_nb = present[:, 1]
    jx, jy = px[:, 3, 1], py[:, 3, 1]
    mx, my = (x0[cand] + jx) / 2, (y0[cand] + jy) / 2
    sep = np.hypot(x0[cand] - jx, y0[cand] - jy)
    ux = np.where(sep > 1e-6, (x0[cand] - jx) / np.maximum(sep, 1e-6), 1.0)
    uy = np.where(sep > 1e-6, (y0[cand] - jy) / np.maximum(sep, 1e-6), 0.0)
    half = np.maximum(sep, 1.5) / 2
    px[:, 3, 0] = np.where(has_nb, mx + half * ux, x0[cand])
    py[:, 3, 0] = np.where(has_nb, my + half * uy, y0[cand])
    px[:, 3, 1] = np.where(has_nb, mx - half * ux, jx)
    py[:, 3, 1] = np.where(has_nb, my - half * uy, jy)
    # the star's own flux starts from the linear solve at fixed positions
    pf[:, 1:, 0] = 0.0
    act = np.repeat(present[:, None, :], n_start, 1)
    act[:, 0, 0] = False  # the problem without the star
    shape = (c, n_start)
    sol = _fit_groups(
        psf, px.reshape(c * n_start, kp), py.reshape(c * n_start, kp),
        pf.reshape(c * n_start, kp), act.reshape(c * n_start, kp),
        np.repeat(target, n_start, 0), np.repeat(weight, n_start, 0),
        np.repeat(valid, n_start, 0), np.repeat(cxw[cand], n_start),
        np.repeat(cyw[cand], n_start), w_half, opt,
    )  # fmt: skip
    chi2 = sol["chi2"].reshape(shape)
    conv = sol["converged"].reshape(shape)
    sx, sy, sf = (sol[k].reshape(c, n_start, kp)[:, :, 0] for k in ("x", "y", "flux"))
    ex, ey, ef = (sol[k].reshape(c, n_start, kp)[:, :, 0] for k in ("x_err", "y_err", "flux_err"))
    # the window's reduced chi^2 scales the tests: where the rest of the light is
    # mis-modelled, its misfit is noise to them (an F-test)
    n_free = 3 * act.reshape(c, n_start, kp).sum(axis=2) + 3
    dof = np.maximum(valid.sum(axis=1)[:, None] - n_free, 1)
    misfit = np.maximum(chi2 / dof, 1.0)
    shift = np.hypot(sx - x0[cand, None], sy - y0[cand, None])
    ok = conv & (shift <= opt.max_shift) & np.isfinite(ex) & np.isfinite(ey)
    ok &= (sf > 0) & (sf >= opt.min_snr * ef * np.sqrt(misfit))
    ok[:, 0] = False
    ok[:, 3] &= has_nb
    best = np.argmin(np.where(ok, chi2, np.inf), axis=1)
    rows_c = np.arange(c)
    gain = (chi2[:, 0] - chi2[rows_c, best]) / misfit[rows_c, best]
    keep = ok[rows_c, best] & np.isfinite(chi2[:, 0]) & (gain >= opt.min_gain)
    keep &= misfit[rows_c, best] <= opt.max_misfit
    sel = np.flatnonzero(keep)
    # the group's Fisher errors times the window's misfit (the rest of the light's
    # mis-modelling is noise to the group)
    inflate = np.sqrt(misfit[sel, best[sel]]) if opt.inflate else np.ones(len(sel))
    b = best[sel]
    flat_p = sel * n_start + b
    star = cand[sel]
    out_x, out_y = sx[sel, b], sy[sel, b]
    # the star's stamp at the solution: its chi^2, odd chi^2 and neighbours' share
    stamp = _stamp_terms(sol, flat_p, weight[sel], valid[sel], out_x, out_y,
                         cxw[star], cyw[star], w_half, r)  # fmt: skip
    return Rescued(
        index=star,
        x=out_x,
        y=out_y,
        flux=sf[sel, b],
        sky=sol["sky"][flat_p, 0],
        x_err=ex[sel, b] * inflate,
        y_err=ey[sel, b] * inflate,
        flux_err=ef[sel, b] * inflate,
        sky_err=sol["sky_err"][flat_p] * inflate,
        chi2=stamp[0],
        chi2_odd=stamp[1],
        crowding=stamp[2],
        gain=gain[sel],
        tried=c,
    )


def _stamp_terms(sol, p, weight, valid, x, y, cxw, cyw, w_half, r):
    """chi^2, odd chi^2 and crowding of each rescued star's stamp within its window."""
    s = 2 * w_half + 1
    n = len(p)
    resid = sol["resid"][p].reshape(n, s, s)
    own = sol["own"][p].reshape(n, s, s)
    total = sol["model"][p].reshape(n, s, s)
    w = weight.reshape(n, s, s)
    v = valid.reshape(n, s, s)
    cx, cy = np.rint(x).astype(np.intp), np.rint(y).astype(np.intp)
    chi2 = np.full(n, np.nan)
    odd = np.full(n, np.nan)
    crowd = np.full(n, np.nan)
    for k in range(n):
        oy = cy[k] - r - (cyw[k] - w_half)
        ox = cx[k] - r - (cxw[k] - w_half)
        if oy < 0 or ox < 0 or oy + 2 * r + 1 > s or ox + 2 * r + 1 > s:
            continue
        sl = (slice(oy, oy + 2 * r + 1), slice(ox, ox + 2 * r + 1))
        e2 = w[k][sl] * resid[k][sl] ** 2 * v[k][sl]
        dof = max(int(v[k][sl].sum()) - 6, 1)
        chi2[k] = e2.sum() / dof
        odd[k] = odd_chi2(
            (np.sqrt(w[k][sl]) * resid[k][sl])[None], v[k][sl][None],
            np.array([x[k] - cx[k]]), np.array([y[k] - cy[k]]), 4,
        )[0]  # fmt: skip
        others = np.sum(np.maximum(total[k][sl] - own[k][sl], 0.0) * v[k][sl])
        mine = np.sum(np.abs(own[k][sl]) * v[k][sl])
        q = others / max(others + mine, 1e-300)
        crowd[k] = max(1.0 + (chi2[k] - 1.0) * q, 1.0)
    return chi2, odd, crowd


def _fit_groups(psf, x, y, f, act, target, weight, valid, cx, cy, w_half, opt):
    """Levenberg-Marquardt fits of many groups at once on their windows.

    ``x, y, f, act`` (G, K): members' starts and which take part; ``target, weight,
    valid`` (G, M) the windows' data less the rest of the light, weights, pixels used;
    ``cx, cy`` (G,) the windows' central pixels. Parameters per group: (x, y, flux) per
    member, then the sky plane (level, d/dcolumn, d/drow about the centre).
    """
    g, k = x.shape
    s = 2 * w_half + 1
    m = s * s
    npar = 3 * k + 3
    off = np.arange(-w_half, w_half + 1, dtype=float)
    plane = np.stack(
        [np.ones(m), np.tile(off, s) / w_half, np.repeat(off, s) / w_half]
    )  # (3, M): level, column, row slopes
    mix_i, mix_w = psf.mixing(np.repeat(cx, k).astype(float), np.repeat(cy, k).astype(float))
    geom = StampGeometry(np.repeat(cx, k), np.repeat(cy, k), w_half)
    x, y, f = x.copy(), y.copy(), f.copy()
    sky = np.zeros((g, 3))
    lam = np.full(g, 1e-3)
    done = np.zeros(g, bool)
    converged = np.zeros(g, bool)
    lo_x, hi_x = cx[:, None] - w_half + 0.5, cx[:, None] + w_half - 0.5
    lo_y, hi_y = cy[:, None] - w_half + 0.5, cy[:, None] + w_half - 0.5
    # inactive parameters are held: identity rows
    held = np.zeros((g, npar), bool)
    held[:, : 3 * k] = ~np.repeat(act, 3, axis=1)

    def evaluate(sel, xs, ys, derivatives):
        on = act[sel]  # only the members taking part
        idx = (sel[:, None] * k + np.arange(k)[None, :])[on]
        sub = StampGeometry(geom.cx[idx], geom.cy[idx], w_half)
        out = psf.evaluate(
            xs[on], ys[on], sub, mix=(mix_i[idx], mix_w[idx]), derivatives=derivatives
        )
        parts = out if derivatives else (out,)
        full = []
        for q in parts:
            z = np.zeros((len(sel), k, m))
            z[on] = q.reshape(len(idx), m)
            full.append(z)
        return tuple(full) if derivatives else full[0]

    def model_of(v, fs, sk, sel):
        return np.einsum("gk,gkm->gm", fs * act[sel], v) + sk @ plane

    def chi2_of(resid, sel):
        return np.sum(weight[sel] * resid**2, axis=1)

    def system(sel, fixed_positions):
        v, dvx, dvy = evaluate(sel, x[sel], y[sel], True)
        fs = f[sel] * act[sel]
        model = model_of(v, f[sel], sky[sel], sel)
        resid = np.where(valid[sel], target[sel] - model, 0.0)
        jac = np.zeros((len(sel), npar, m))
        jac[:, 0 : 3 * k : 3] = dvx * fs[:, :, None]
        jac[:, 1 : 3 * k : 3] = dvy * fs[:, :, None]
        jac[:, 2 : 3 * k : 3] = v * act[sel][:, :, None]
        jac[:, 3 * k :] = plane[None]
        jw = jac * weight[sel][:, None, :]
        a = jw @ jac.transpose(0, 2, 1)
        b = (jw @ resid[:, :, None])[:, :, 0]
        hold = held[sel].copy()
        if fixed_positions:
            hold[:, 0 : 3 * k : 3] = True
            hold[:, 1 : 3 * k : 3] = True
        return a, b, hold, chi2_of(resid, sel), v, resid, model

    def solve(a, b, hold, damping):
        a = a.copy()
        diag = np.einsum("gpp->gp", a)
        a[:, np.arange(npar), np.arange(npar)] = diag * (1 + damping[:, None]) + 1e-12
        a[hold[:, :, None] | hold[:, None, :]] = 0.0
        a[:, np.arange(npar), np.arange(npar)] = np.where(
            hold, 1.0, a[:, np.arange(npar), np.arange(npar)]
        )
        b = np.where(hold, 0.0, b)
        try:
            return np.linalg.solve(a, b[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            out = np.zeros_like(b)
            for q in range(len(b)):
                try:
                    out[q] = np.linalg.solve(a[q], b[q])
                except np.linalg.LinAlgError:
                    pass
            return out

    # fluxes and sky at fixed positions first (one linear solve)
    every = np.arange(g)
    a, bvec, hold, _, _, _, _ = system(every, True)
    step = solve(a, bvec, hold, np.zeros(g))
    f += step[:, 2 : 3 * k : 3]
    sky += step[:, 3 * k :]
    for _ in range(opt.iterations):
        sel = np.flatnonzero(~done)
        if len(sel) == 0:
            break
        a, bvec, hold, chi2_now, _, _, _ = system(sel, False)
        step = solve(a, bvec, hold, lam[sel])
        dx, dy = step[:, 0 : 3 * k : 3], step[:, 1 : 3 * k : 3]
        length = np.hypot(dx, dy).max(axis=1)
        scale = np.minimum(1.0, 0.5 / np.maximum(length, 1e-300))
        tx = np.clip(x[sel] + dx * scale[:, None], lo_x[sel], hi_x[sel])
        ty = np.clip(y[sel] + dy * scale[:, None], lo_y[sel], hi_y[sel])
        tf = f[sel] + step[:, 2 : 3 * k : 3] * scale[:, None]
        tsky = sky[sel] + step[:, 3 * k :] * scale[:, None]
        v = evaluate(sel, tx, ty, False)
        resid = np.where(valid[sel], target[sel] - model_of(v, tf, tsky, sel), 0.0)
        chi2_try = chi2_of(resid, sel)
        better = chi2_try <= chi2_now
        acc = sel[better]
        x[acc], y[acc], f[acc], sky[acc] = tx[better], ty[better], tf[better], tsky[better]
        lam[sel] = np.where(better, np.maximum(lam[sel] / 3, 1e-7), lam[sel] * 4)
        small = better & (length * scale < opt.tolerance)
        converged[sel[small]] = True
        done[sel[small | (lam[sel] > 1e6)]] = True
    # at the solution: chi^2, residuals and the undamped Fisher matrix's errors
    a, _, hold, chi2, v, resid, model = system(every, False)
    a = a.copy()
    a[hold[:, :, None] | hold[:, None, :]] = 0.0
    a[:, np.arange(npar), np.arange(npar)] += hold
    cov, ok = safe_inverse(a)
    var = np.where(ok[:, None], np.einsum("gpp->gp", cov), np.nan)
    err = np.sqrt(np.where(var > 0, var, np.nan))
    own = v[:, 0] * (f[:, 0] * act[:, 0])[:, None]
    return {
        "x": x, "y": y, "flux": f, "sky": sky,
        "x_err": err[:, 0 : 3 * k : 3], "y_err": err[:, 1 : 3 * k : 3],
        "flux_err": err[:, 2 : 3 * k : 3], "sky_err": err[:, 3 * k],
        "chi2": chi2, "converged": converged, "resid": resid, "model": model, "own": own,
    }  # fmt: skip
