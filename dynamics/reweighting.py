"""Importance reweighting of a nested-sampling run to a costlier likelihood.

A nested run with a cheap proposal likelihood ``L_q`` (the Gaussian velocity law) gives
its evidence ``Z_q`` and weighted posterior samples. For a target likelihood ``L``
(the line-of-sight mixture) on the same prior,

    Z = Z_q E_q[ L / L_q ],          p(theta | data) ~ p_q(theta | data) L / L_q,

so ``S`` draws from the proposal's posterior, each evaluated once with the target,
give the target's evidence and posterior (Tokdar & Kass 2010). It is reliable only where
the two posteriors overlap; the ratios' tail tells when they do not: the shape ``k`` of a
generalised Pareto distribution fitted to the largest ratios (Vehtari et al. 2024,
"Pareto smoothed importance sampling") is below 0.7 for a usable estimate. Above it the
caller runs the target directly.

The evidence error adds, in quadrature to the proposal run's, the importance-sampling
error ``sqrt(Var(r) / (S_eff E[r]^2))`` of the mean ratio ``r = L / L_q``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.special import logsumexp
from scipy.stats import genpareto

__all__ = [
    "K_MAX",
    "pareto_k",
    "reweight_samples",
]

#: Largest Pareto shape of the ratios' tail for which the reweighted result is used.
K_MAX = 0.7


def pareto_k(log_ratios: np.ndarray) -> float:
    """Shape of a generalised Pareto distribution fitted to the largest importance ratios.

    Parameters
    ----------
    log_ratios : ndarray (S,)
        ln of the importance ratios of ``S`` draws (``-inf`` allowed).

    Returns
    -------
    float
        ``k``: < 0.5 good, 0.5-0.7 usable, > 0.7 unreliable (infinite variance of the
        estimate in the limit); ``inf`` when no ratio is finite.
    """
    lr = np.asarray(log_ratios, dtype=float)
    lr = lr[np.isfinite(lr)]
    if lr.size < 20:
        return np.inf
    n_tail = int(min(0.2 * lr.size, 3.0 * np.sqrt(lr.size)))
    lr = np.sort(lr)
    r = np.exp(lr - lr[-1])
    cut = r[-n_tail - 1]
    exceed = r[-n_tail:] - cut
    if not np.any(exceed > 0):
        return 0.0  # a flat tail: every ratio equal
    shape, _, _ = genpareto.fit(exceed, floc=0.0)
    return float(shape)


def reweight_samples(
    samples: np.ndarray,
    log_like_proposal: np.ndarray,
    target: Callable[[np.ndarray], float],
    rng: np.random.Generator,
    n_out: int | None = None,
):
    """Target evidence ratio, equal-weight samples and diagnostics from proposal draws.

    Parameters
    ----------
    samples : ndarray (S, ndim)
        Draws from the proposal's posterior (physical parameters; repeats allowed).
    log_like_proposal : ndarray (S,)
        The proposal's ln L at them.
    target : callable
        The target's ln L of one parameter vector (evaluated once per distinct draw).
    rng : numpy.random.Generator
        For the resampling.
    n_out : int, optional
        Equal-weight samples returned (default ``S``).

    Returns
    -------
    dict
        ``log_mean_ratio`` (ln E_q[L / L_q]), ``log_mean_ratio_err``, ``pareto_k``,
        ``ess`` (effective sample size of the ratios), ``samples`` (equal-weight draws of
        the target posterior), ``max_log_like`` and ``best`` (the target's best draw),
        ``n_calls`` (target evaluations).
    """
    samples = np.asarray(samples, dtype=float)
    uniq, inverse = np.unique(samples, axis=0, return_inverse=True)
    inverse = np.ravel(inverse)
    target_ll = np.array([target(v) for v in uniq], dtype=float)
    target_ll = np.where(np.isfinite(target_ll), target_ll, -np.inf)[inverse]
    log_r = target_ll - np.asarray(log_like_proposal, dtype=float)
    log_r = np.where(np.isfinite(log_r), log_r, -np.inf)
    s = log_r.size
    log_mean = float(logsumexp(log_r) - np.log(s))
    w = np.exp(log_r - np.max(log_r))
    ess = float(w.sum() ** 2 / np.sum(w * w))
    r = np.exp(log_r - log_mean)  # ratios over their mean
    err = float(np.sqrt(np.var(r) / max(ess, 1.0)))
    pick = rng.choice(s, size=n_out or s, replace=True, p=w / w.sum())
    best = int(np.argmax(target_ll))
    return {
        "log_mean_ratio": log_mean,
        "log_mean_ratio_err": err,
        "pareto_k": pareto_k(log_r),
        "ess": ess,
        "samples": samples[pick],
        "max_log_like": float(target_ll[best]),
        "best": samples[best],
        "n_calls": int(uniq.shape[0]),
    }
