"""Relative astrometry: fit the transformation from one epoch's frame to the reference frame.

Each epoch's measured positions (arcsec, field frame of that epoch) are mapped
onto the reference epoch's frame by a polynomial transformation fitted to
well-measured cluster stars:

* ``order=1, conformal=True``: shift + plate scale + rotation (4 parameters),
* ``order=1``: full linear (shift, two scales, rotation, skew; 6 parameters),
* ``order=2`` / ``order=3``: quadratic / cubic polynomials (12 / 20 parameters),
  which also absorb a low-order *dynamic distortion* between the epochs.

The fit is a weighted least-squares fit in normalised coordinates ``u = x / L``,
``v = y / L`` (``L`` the largest reference-star distance from the origin, for
conditioning). The weights are ``1 / (sigma_epoch^2 + sigma_ref^2 + s^2)``
where ``s`` is the *intrinsic* scatter of the reference stars' displacements
(their internal motions times the baseline), estimated at each iteration so that
the weighted chi-square equals the degrees of freedom. Stars whose normalised
displacement exceeds ``clip_sigma`` (high-velocity stars, mismatches) are
clipped iteratively.

Because the transformation absorbs the reference stars' mean motion (and any
motion pattern the polynomial can represent), proper motions are relative to
the cluster's mean motion, as on sky.

Two parameter covariances are kept:

* ``covariance``: the full covariance ``(A^T W A)^-1``, including the sampling
  noise of the reference stars' internal motions. This is the uncertainty of
  the fitted transformation against a true (motion-free) transformation.
* ``measurement_covariance``: the part due to the measurement errors only (the
  sandwich ``G A^T W V W A G``). The reference stars' internal motions shift
  the frame of *all* stars together (a common, fully correlated offset); that
  is a change of reference frame, not a per-star error, so it is reported once
  (``frame_error``) and only the measurement part is propagated into per-star
  proper-motion errors.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import linalg, optimize, stats

from mavispm.core.errors import InputError

__all__ = [
    "AlignmentFit",
    "DEGENERATE_RCOND",
    "GEOMETRY_RCOND",
    "JITTER_RTOL",
    "TransformModel",
    "clip_threshold",
    "fit_transform",
    "higher_order_p_value",
    "normalisation_length",
    "project_displacements",
]

#: Smallest ratio of singular values of the (column-scaled) weighted design matrix
#: accepted (numerical rank; the normal equations square it).
DEGENERATE_RCOND = 1e-7
#: Smallest ratio of singular values of the *unweighted* design matrix (normalised
#: coordinates) before the reference stars' geometry is declared degenerate, for
#: example stars on a line with a little measurement scatter. Random fields give
#: ratios above ~1e-3 even for a cubic with 12 stars.
GEOMETRY_RCOND = 1e-4
#: Relative convergence of the jitter variance (it only sets the weights).
JITTER_RTOL = 1e-4


@dataclass(frozen=True)
class TransformModel:
    """A polynomial epoch-to-reference transformation family.

    Parameters
    ----------
    order : int
        Polynomial order, 1, 2 or 3.
    conformal : bool
        With ``order=1``: restrict to shift + plate scale + rotation.
    length : float
        Normalisation length ``L`` [arcsec]; coordinates enter as ``x / L``.
    """

    order: int = 1
    conformal: bool = False
    length: float = 1.0

    def __post_init__(self):
        if self.order not in (1, 2, 3):
            raise ValueError(f"transformation order must be 1, 2 or 3, got {self.order}")
        if self.conformal and self.order != 1:
            raise ValueError("a conformal (shift+scale+rotation) transformation has order 1")
        if not (np.isfinite(self.length) and self.length > 0):
            raise ValueError(f"normalisation length must be positive, got {self.length}")

    @property
    def terms(self) -> list[tuple[int, int]]:
        """Exponents ``(i, j)`` of the monomials ``u**i v**j`` (general polynomial)."""
        return [(i, n - i) for n in range(self.order + 1) for i in range(n, -1, -1)]

    @property
    def n_params(self) -> int:
        """Number of free parameters."""
        return 4 if self.conformal else 2 * len(self.terms)

    @property
    def name(self) -> str:
        """Human-readable name of the family."""
        if self.conformal:
            return "shift+scale+rotation"
        return {1: "linear", 2: "quadratic", 3: "cubic"}[self.order]

    def design(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Stacked design matrix: rows ``[X equations; Y equations]``.

        Parameters
        ----------
        x, y : ndarray
            Positions [arcsec] in the epoch frame.

        Returns
        -------
        ndarray, shape (2 n, n_params)
        """
        u_ = np.asarray(x, float) / self.length
        v_ = np.asarray(y, float) / self.length
        n = u_.size
        if self.conformal:
            a = np.zeros((2 * n, 4))
            # X = a + s u - r v ;  Y = b + r u + s v   (times L for arcsec)
            a[:n, 0] = 1.0
            a[n:, 1] = 1.0
            a[:n, 2], a[n:, 2] = u_, v_
            a[:n, 3], a[n:, 3] = -v_, u_
            return a
        basis = self.basis(u_, v_)
        m = basis.shape[1]
        a = np.zeros((2 * n, 2 * m))
        a[:n, :m] = basis
        a[n:, m:] = basis
        return a

    def basis(self, u_: np.ndarray, v_: np.ndarray) -> np.ndarray:
        """Monomials ``u**i v**j`` in normalised coordinates, shape (n, n_terms).

        Parameters
        ----------
        u_, v_ : ndarray
            Positions divided by the conditioning length ``length`` (dimensionless).

        Returns
        -------
        ndarray (n, n_terms)
        """
        up = [np.ones_like(u_), u_]
        vp = [np.ones_like(v_), v_]
        for _ in range(2, self.order + 1):
            up.append(up[-1] * u_)
            vp.append(vp[-1] * v_)
        return np.stack([up[i] * vp[j] for i, j in self.terms], axis=1)

    def identity_params(self) -> np.ndarray:
        """Parameters of the identity transformation."""
        p = np.zeros(self.n_params)
        if self.conformal:
            p[2] = self.length
            return p
        m = len(self.terms)
        p[self.terms.index((1, 0))] = self.length
        p[m + self.terms.index((0, 1))] = self.length
        return p

    def features(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Precomputed position features: the basis (n, n_terms), or (n, 2) ``u, v`` if conformal.

        Computing them once and passing them to :meth:`apply` and
        :meth:`normal_equations` avoids rebuilding the basis in iterative fits.

        Parameters
        ----------
        x, y : array-like
            Epoch-frame positions [arcsec].
        """
        u_ = np.asarray(x, float) / self.length
        v_ = np.asarray(y, float) / self.length
        if self.conformal:
            return np.column_stack([u_, v_])
        return self.basis(u_, v_)

    def apply(
        self,
        params: np.ndarray,
        x: np.ndarray | None = None,
        y: np.ndarray | None = None,
        features: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Map epoch-frame positions [arcsec] (or their :meth:`features`) to the reference frame.

        Parameters
        ----------
        params : array-like
            Transformation parameters.
        x, y : array-like, optional
            Epoch-frame positions [arcsec].
        features : ndarray, optional
            Precomputed :meth:`features` (instead of x, y).

        Returns
        -------
        X, Y : ndarray
            Reference-frame positions [arcsec].
        """
        params = np.asarray(params, float)
        f = self.features(x, y) if features is None else features
        if self.conformal:
            a, b, sc, rot = params
            return a + sc * f[:, 0] - rot * f[:, 1], b + rot * f[:, 0] + sc * f[:, 1]
        m = f.shape[1]
        return f @ params[:m], f @ params[m:]

    def normal_equations(
        self, features: np.ndarray, wx: np.ndarray, wy: np.ndarray, bx: np.ndarray, by: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Weighted normal equations ``A^T W A`` and ``A^T W b`` of the stacked problem.

        Parameters
        ----------
        features : ndarray
            From :meth:`features` of the epoch-frame positions.
        wx, wy : ndarray
            Weights of the X and Y equations.
        bx, by : ndarray
            Targets (reference-frame positions) [arcsec].
        """
        wx = np.asarray(wx, float)
        wy = np.asarray(wy, float)
        if self.conformal:
            a = self.design(features[:, 0] * self.length, features[:, 1] * self.length)
            w = np.concatenate([wx, wy])
            aw = a * w[:, None]
            return aw.T @ a, aw.T @ np.concatenate([bx, by])
        m = features.shape[1]
        gram = np.zeros((2 * m, 2 * m))
        gram[:m, :m] = (features * wx[:, None]).T @ features
        if np.array_equal(wx, wy):
            gram[m:, m:] = gram[:m, :m]
        else:
            gram[m:, m:] = (features * wy[:, None]).T @ features
        rhs = np.concatenate([features.T @ (wx * bx), features.T @ (wy * by)])
        return gram, rhs

    def jacobian(self, params: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Jacobian ``d(X, Y) / d(x, y)`` at each position (analytic), shape (n, 2, 2).

        Parameters
        ----------
        params : array-like
            Transformation parameters.
        x, y : array-like
            Epoch-frame positions [arcsec].

        Returns
        -------
        ndarray (n, 2, 2)
            Dimensionless.
        """
        params = np.asarray(params, float)
        u_ = np.asarray(x, float) / self.length
        v_ = np.asarray(y, float) / self.length
        jac = np.empty((u_.size, 2, 2))
        if self.conformal:
            sc, rot = params[2] / self.length, params[3] / self.length
            jac[:] = [[sc, -rot], [rot, sc]]
            return jac
        up = [np.zeros_like(u_), np.ones_like(u_)]  # up[k + 1] = u**k
        vp = [np.zeros_like(v_), np.ones_like(v_)]
        for _ in range(self.order):
            up.append(up[-1] * u_)
            vp.append(vp[-1] * v_)
        d_du = np.stack([i * up[i] * vp[j + 1] for i, j in self.terms], axis=1) / self.length
        d_dv = np.stack([j * up[i + 1] * vp[j] for i, j in self.terms], axis=1) / self.length
        m = d_du.shape[1]
        jac[:, 0, 0] = d_du @ params[:m]
        jac[:, 0, 1] = d_dv @ params[:m]
        jac[:, 1, 0] = d_du @ params[m:]
        jac[:, 1, 1] = d_dv @ params[m:]
        return jac

    def position_covariance(
        self, cov: np.ndarray, x: np.ndarray, y: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Variance of the mapped positions due to a parameter covariance.

        Parameters
        ----------
        cov : ndarray (n_params, n_params)
            Parameter covariance.
        x, y : array-like
            Epoch-frame positions [arcsec].

        Returns
        -------
        var_x, var_y, cov_xy : ndarray
            [arcsec^2] at each position.
        """
        cov = np.asarray(cov, float)
        if self.conformal:
            a = self.design(x, y)
            n = np.size(x)
            ax, ay = a[:n], a[n:]
            cx = ax @ cov
            var_x = np.sum(cx * ax, axis=1)
            var_y = np.sum((ay @ cov) * ay, axis=1)
            cov_xy = np.sum(cx * ay, axis=1)
        else:
            basis = self.basis(
                np.asarray(x, float) / self.length, np.asarray(y, float) / self.length
            )
            m = basis.shape[1]
            var_x = np.sum((basis @ cov[:m, :m]) * basis, axis=1)
            var_y = np.sum((basis @ cov[m:, m:]) * basis, axis=1)
            cov_xy = np.sum((basis @ cov[:m, m:]) * basis, axis=1)
        return np.maximum(var_x, 0.0), np.maximum(var_y, 0.0), cov_xy


@dataclass
class AlignmentFit:
    """Result of fitting one epoch's transformation.

    Parameters
    ----------
    model : TransformModel
    params : ndarray
        Fitted parameters (arcsec; see :meth:`TransformModel.design`).
    covariance : ndarray
        Full parameter covariance, including the reference stars' internal motions.
    measurement_covariance : ndarray
        Parameter covariance due to the measurement errors only.
    jitter : float
        Intrinsic scatter ``s`` of the reference stars' displacements [arcsec].
    used : ndarray of bool
        Which of the candidate stars were kept as reference stars.
    weights : ndarray
        Final per-star weights per axis, shape (n, 2) [arcsec^-2] (0 for unused stars).
    n_clipped : int
        Candidates rejected by sigma clipping.
    chi2, dof : float, int
        Final weighted chi-square (with the jitter) and degrees of freedom.
    rms : float
        Unweighted rms residual of the reference stars [arcsec].
    """

    model: TransformModel
    params: np.ndarray
    covariance: np.ndarray
    measurement_covariance: np.ndarray
    jitter: float
    used: np.ndarray
    weights: np.ndarray
    n_clipped: int
    chi2: float
    dof: int
    rms: float
    iterations: int = 0
    notes: list[str] = field(default_factory=list)

    def apply(self, x: np.ndarray, y: np.ndarray):
        """Map epoch-frame positions [arcsec] onto the reference frame [arcsec].

        Parameters
        ----------
        x, y : array-like
            Epoch-frame positions [arcsec].

        Returns
        -------
        X, Y : ndarray
            Reference-frame positions [arcsec].
        """
        return self.model.apply(self.params, x, y)

    @property
    def n_ref(self) -> int:
        """Number of reference stars in the final fit."""
        return int(np.count_nonzero(self.used))

    @property
    def param_errors(self) -> np.ndarray:
        """1-sigma errors of the parameters (full covariance)."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0, None))

    def frame_error(self) -> float:
        """Uncertainty of the frame's zero point (the shift) [arcsec], rms of both axes."""
        x0, y0 = self.model.position_covariance(self.covariance, np.zeros(1), np.zeros(1))[:2]
        return float(np.sqrt(0.5 * (x0[0] + y0[0])))

    def to_dict(self) -> dict:
        """JSON-ready summary (stored in the product's ``transform`` attribute)."""
        return {
            "model": self.model.name,
            "order": self.model.order,
            "conformal": self.model.conformal,
            "length_arcsec": self.model.length,
            "terms": [list(t) for t in self.model.terms] if not self.model.conformal else None,
            "params_arcsec": self.params.tolist(),
            "param_errors_arcsec": self.param_errors.tolist(),
            "jitter_arcsec": self.jitter,
            "n_ref": self.n_ref,
            "n_clipped": self.n_clipped,
            "chi2": self.chi2,
            "dof": self.dof,
            "rms_arcsec": self.rms,
        }


def clip_threshold(clip_sigma: float) -> float:
    """Chi-square (2 dof) threshold with the two-sided tail probability of ``clip_sigma``.

    Parameters
    ----------
    clip_sigma : float
        Gaussian-equivalent clipping threshold [sigma].

    Returns
    -------
    float
        Chi-square threshold (2 degrees of freedom).
    """
    return float(stats.chi2.isf(2.0 * stats.norm.sf(clip_sigma), df=2))


def _solve_jitter(res2: np.ndarray, var: np.ndarray, dof: int) -> float:
    """Intrinsic variance ``s^2`` with ``sum(res^2 / (var + s^2)) = dof`` (0 if none needed)."""
    if dof <= 0:
        return 0.0

    def excess(s2):
        return float(np.sum(res2 / (var + s2))) - dof

    if excess(0.0) <= 0:
        return 0.0
    hi = float(np.sum(res2) / dof + np.max(var))
    while excess(hi) > 0:
        hi *= 4.0
    return float(optimize.brentq(excess, 0.0, hi, xtol=1e-30, rtol=1e-10))


def _singular_ratio(gram: np.ndarray) -> float:
    """Smallest/largest singular value of ``A`` from its column-scaled Gram matrix ``A^T A``."""
    d = np.sqrt(np.diag(gram))
    if gram.size == 0 or not np.all(np.isfinite(gram)) or np.any(d <= 0):
        return 0.0
    eig = np.linalg.eigvalsh(gram / np.outer(d, d))
    return float(np.sqrt(max(eig[0], 0.0) / eig[-1]))


def _check_geometry(model, features, what):
    ones = np.ones(features.shape[0])
    gram, _ = model.normal_equations(features, ones, ones, ones, ones)
    if _singular_ratio(gram) <= GEOMETRY_RCOND:
        raise InputError(
            f"{what}: the reference stars' geometry is degenerate for a {model.name} "
            "transformation (for example all on a line); use a lower order, "
            "conformal = true, or more widely spread stars"
        )


def _weighted_solve(gram, rhs, what):
    """Solve normal equations by Cholesky of the column-scaled matrix.

    Returns the parameters and their covariance ``(A^T W A)^-1``.
    """
    if _singular_ratio(gram) <= DEGENERATE_RCOND:
        raise InputError(
            f"{what}: the reference stars' geometry is degenerate for this transformation "
            "(for example all on a line); use a lower order or more widely spread stars"
        )
    d = np.sqrt(np.diag(gram))
    try:
        factor = linalg.cho_factor(gram / np.outer(d, d))
    except linalg.LinAlgError:
        raise InputError(f"{what}: the alignment normal equations are singular") from None
    params = linalg.cho_solve(factor, rhs / d) / d
    cov = linalg.cho_solve(factor, np.eye(d.size)) / np.outer(d, d)
    return params, 0.5 * (cov + cov.T)


def fit_transform(
    x: np.ndarray,
    y: np.ndarray,
    x_ref: np.ndarray,
    y_ref: np.ndarray,
    var_x: np.ndarray,
    var_y: np.ndarray,
    model: TransformModel,
    candidates: np.ndarray | None = None,
    clip_sigma: float = 4.0,
    max_iter: int = 10,
    what: str = "alignment",
) -> AlignmentFit:
    """Fit the transformation mapping ``(x, y)`` onto ``(x_ref, y_ref)``.

    Parameters
    ----------
    x, y : ndarray
        Positions of the matched stars in the epoch frame [arcsec].
    x_ref, y_ref : ndarray
        Their positions in the reference frame [arcsec].
    var_x, var_y : ndarray
        Variance of the displacement per axis, ``sigma_epoch^2 + sigma_ref^2`` [arcsec^2].
    model : TransformModel
    candidates : ndarray of bool, optional
        Stars allowed as reference stars (well measured, unflagged).
    clip_sigma : float
        Clipping threshold (Gaussian sigma equivalent for the 2-D displacement).
    max_iter : int
        Maximum number of fit-clip iterations.
    what : str
        Label used in error messages (for example "epoch 10.0 yr").

    Returns
    -------
    AlignmentFit

    Raises
    ------
    InputError
        Too few reference stars, a degenerate geometry, or clipping that rejects everything.
    """
    x, y, x_ref, y_ref = (np.asarray(v, float) for v in (x, y, x_ref, y_ref))
    var_x = np.asarray(var_x, float)
    var_y = np.asarray(var_y, float)
    n = x.size
    cand = np.ones(n, bool) if candidates is None else np.asarray(candidates, bool).copy()
    cand &= np.isfinite(x) & np.isfinite(y) & np.isfinite(x_ref) & np.isfinite(y_ref)
    cand &= np.isfinite(var_x) & np.isfinite(var_y) & (var_x > 0) & (var_y > 0)
    p = model.n_params
    need = p // 2 + 1
    if np.count_nonzero(cand) < need:
        raise InputError(
            f"{what}: {np.count_nonzero(cand)} usable reference star(s), but a {model.name} "
            f"transformation needs at least {need} (and many more for a good fit)"
        )
    thresh = clip_threshold(clip_sigma)
    feats = model.features(np.where(cand, x, 0.0), np.where(cand, y, 0.0))
    used = cand.copy()
    s2 = 0.0
    n_iter = 0
    for n_iter in range(1, max_iter + 1):  # noqa: B007
        idx = np.flatnonzero(used)
        if idx.size < need:
            raise InputError(
                f"{what}: sigma clipping left {idx.size} reference star(s); a {model.name} "
                f"transformation needs at least {need} (raise clip_sigma or check the match)"
            )
        fi, bx, by = feats[idx], x_ref[idx], y_ref[idx]
        vxi, vyi = var_x[idx], var_y[idx]
        if n_iter == 1:  # clipping removes outliers, it does not create a line
            _check_geometry(model, fi, what)
        var = np.concatenate([vxi, vyi])
        dof = 2 * idx.size - p
        for _ in range(20):  # converge the jitter for this reference set
            gram, rhs = model.normal_equations(fi, 1 / (vxi + s2), 1 / (vyi + s2), bx, by)
            params, cov = _weighted_solve(gram, rhs, what)
            mx, my = model.apply(params, features=fi)
            res2 = np.concatenate([(bx - mx) ** 2, (by - my) ** 2])
            s2_new = _solve_jitter(res2, var, dof)
            done = abs(s2_new - s2) <= JITTER_RTOL * (s2 + np.median(var))
            s2 = s2_new
            if done:
                break
        mx, my = model.apply(params, features=feats)
        z2 = (x_ref - mx) ** 2 / (var_x + s2) + (y_ref - my) ** 2 / (var_y + s2)
        new_used = cand & (z2 <= thresh)
        if np.array_equal(new_used, used):
            break
        used = new_used
    idx = np.flatnonzero(used)
    fi, bx, by = feats[idx], x_ref[idx], y_ref[idx]
    vxi, vyi = var_x[idx], var_y[idx]
    wx, wy = 1 / (vxi + s2), 1 / (vyi + s2)
    gram, rhs = model.normal_equations(fi, wx, wy, bx, by)
    params, cov = _weighted_solve(gram, rhs, what)
    mx, my = model.apply(params, features=fi)
    res = np.concatenate([bx - mx, by - my])
    w = np.concatenate([wx, wy])
    # measurement-only covariance: G (A^T W V W A) G with V the measurement variances
    gram_v, _ = model.normal_equations(fi, wx**2 * vxi, wy**2 * vyi, bx, by)
    meas_cov = cov @ gram_v @ cov
    weights = np.zeros((n, 2))
    weights[idx, 0] = wx
    weights[idx, 1] = wy
    return AlignmentFit(
        model=model,
        params=params,
        covariance=cov,
        measurement_covariance=meas_cov,
        jitter=float(np.sqrt(s2)),
        used=used,
        weights=weights,
        n_clipped=int(np.count_nonzero(cand & ~used)),
        chi2=float(np.sum(res**2 * w)),
        dof=int(2 * idx.size - p),
        rms=float(np.sqrt(np.mean(res**2))),
        iterations=n_iter,
    )


def higher_order_p_value(
    fit: AlignmentFit, x: np.ndarray, y: np.ndarray, x_ref: np.ndarray, y_ref: np.ndarray
) -> float | None:
    """Probability that the next polynomial order improves the fit only by chance.

    Refits the final reference stars with the same weights (the jitter
    included) and order + 1; the chi-square drop is chi-square distributed with
    the number of added parameters if the order is adequate. A tiny value means
    a distortion the chosen order cannot represent (it then inflates the
    jitter instead of being removed). None for cubic fits.

    Parameters
    ----------
    fit : AlignmentFit
        The final fit.
    x, y : ndarray
        Epoch-frame positions of all stars [arcsec].
    x_ref, y_ref : ndarray
        Their reference-epoch positions [arcsec].

    Returns
    -------
    float or None
    """
    if fit.model.order >= 3:
        return None
    higher = TransformModel(order=fit.model.order + 1, length=fit.model.length)
    idx = np.flatnonzero(fit.used)
    if 2 * idx.size <= higher.n_params:
        return None
    f = higher.features(x[idx], y[idx])
    wx, wy = fit.weights[idx, 0], fit.weights[idx, 1]
    try:
        gram, rhs = higher.normal_equations(f, wx, wy, x_ref[idx], y_ref[idx])
        params, _ = _weighted_solve(gram, rhs, "order test")
    except InputError:
        return None
    mx, my = higher.apply(params, features=f)
    chi2 = float(np.sum(wx * (x_ref[idx] - mx) ** 2 + wy * (y_ref[idx] - my) ** 2))
    return float(stats.chi2.sf(fit.chi2 - chi2, higher.n_params - fit.model.n_params))


def normalisation_length(x: np.ndarray, y: np.ndarray) -> float:
    """Conditioning length ``L`` [arcsec]: the largest distance of a star from the origin.

    Parameters
    ----------
    x, y : array-like
        Positions [arcsec].

    Returns
    -------
    float
        [arcsec], at least 1e-3.
    """
    r = np.hypot(np.asarray(x, float), np.asarray(y, float))
    r = r[np.isfinite(r)]
    return float(max(np.max(r) if r.size else 1.0, 1e-3))


def project_displacements(
    fit: AlignmentFit,
    x: np.ndarray,
    y: np.ndarray,
    dx: np.ndarray,
    dy: np.ndarray,
    x_eval: np.ndarray,
    y_eval: np.ndarray,
):
    """The part of a displacement field a transformation fit with ``fit``'s weights absorbs.

    Fits the model's linear part (the transformation minus identity has the same
    basis) to ``(dx, dy)`` at the epoch-frame positions ``(x, y)`` of the stars,
    with the final reference stars and weights of ``fit``, and evaluates it at
    ``(x_eval, y_eval)``. Used to express true motions in the same relative frame
    as the measured ones.

    Parameters
    ----------
    fit : AlignmentFit
        Supplies the model, reference stars and weights.
    x, y : ndarray
        Epoch-frame positions of the stars [arcsec].
    dx, dy : ndarray
        Displacements at those positions (any unit).
    x_eval, y_eval : ndarray
        Where to evaluate the absorbed part [arcsec].

    Returns
    -------
    ndarray, ndarray
        Absorbed displacement [same unit as ``dx``] at the evaluation positions.
    """
    idx = np.flatnonzero(fit.used)
    gram, rhs = fit.model.normal_equations(
        fit.model.features(x[idx], y[idx]),
        fit.weights[idx, 0],
        fit.weights[idx, 1],
        np.asarray(dx, float)[idx],
        np.asarray(dy, float)[idx],
    )
    params, _ = _weighted_solve(gram, rhs, "truth projection")
    return fit.model.apply(params, x_eval, y_eval)
