"""Model comparison IMBH vs no-IMBH.

* Bayesian evidence of each model from nested sampling (dynesty), with the same
  priors as the emcee fit; ``ln B = ln Z_imbh - ln Z_no_imbh`` with the error
  from dynesty's ``logzerr`` added in quadrature.
* Maximum-likelihood ratio, AIC and BIC from the best ln L of each model.
* Savage-Dickey density ratio from the IMBH posterior: ``B_10 = p(M_bh=0) /
  p(M_bh=0 | data)`` (prior over posterior density at zero). It needs posterior
  support near ``M_bh = 0``; for a strong detection there are no samples there
  and the estimate is reported as not valid (NaN with the reason).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from mavispm.dynamics.parameters import ParameterSpace

__all__ = [
    "EvidenceResult",
    "bayes_factor",
    "information_criteria",
    "run_dynesty",
    "savage_dickey",
]


@dataclass
class EvidenceResult:
    """Nested-sampling evidence of one model.

    Parameters
    ----------
    log_z, log_z_err : float
    n_calls : int
        Likelihood evaluations used.
    max_log_like : float
    samples : ndarray (n, ndim) or None
        Equally weighted posterior samples (physical values).
    """

    log_z: float
    log_z_err: float
    n_calls: int
    max_log_like: float
    samples: np.ndarray | None = None
    #: physical parameters of the highest-likelihood point
    best: np.ndarray | None = None
    #: "direct", or "reweighted" (a proposal run importance-reweighted to the likelihood)
    method: str = "direct"
    #: Pareto shape of the importance ratios' tail (reweighted runs; NaN otherwise)
    pareto_k: float = float("nan")


def run_dynesty(
    loglike: Callable[[np.ndarray], float],
    space: ParameterSpace,
    seed: int,
    nlive: int = 250,
    dlogz: float = 0.1,
    progress: bool = False,
    target: Callable[[np.ndarray], float] | None = None,
    n_draws: int = 4000,
    walks: int = 0,
):
    """Evidence of one model with dynesty's static nested sampler.

    With ``target``, ``loglike`` is a cheap proposal: its run's posterior draws are
    importance-reweighted to ``target`` (:mod:`mavispm.dynamics.reweighting`), and where
    the ratios' Pareto shape exceeds 0.7 ``target`` is sampled directly instead.

    Parameters
    ----------
    loglike : callable
        ln L of a physical parameter vector.
    space : ParameterSpace
        Priors (the unit-cube transform).
    seed : int
    nlive : int
        Live points.
    dlogz : float
        Stopping criterion on the remaining evidence.
    progress : bool
        Print dynesty's progress line.
    target : callable, optional
        The likelihood wanted, when ``loglike`` is its cheap proposal.
    n_draws : int
        Proposal posterior draws reweighted to ``target``.
    walks : int
        Random-walk steps per new live point (up to 20 parameters, where the sampler is
        dynesty's random walk); 0: dynesty's default, ``ndim + 20``.

    Notes
    -----
    Up to 20 parameters new live points come from dynesty's random walk (``"rwalk"``,
    dynesty's own choice for 10-20); above 20 dynesty's own choice (slice sampling).
    Below 10 parameters dynesty would draw uniformly inside bootstrapped ellipsoids
    (``"unif"``), which on a small field's weakly constrained anisotropy profile took
    2-35 times the CPU for the same evidence (docs/dynamics.md, "Random walk below ten
    parameters").
    """
    import dynesty

    def ll(v):
        val = loglike(v)
        return val if np.isfinite(val) else -1e300

    ndim = len(space)
    # the random walk named up to 20 parameters (see Notes); walks None: dynesty's ndim + 20
    steps = {"sample": "rwalk", "walks": int(walks) or None} if ndim <= 20 else {}
    sampler = dynesty.NestedSampler(
        ll,
        space.from_unit,
        ndim,
        nlive=nlive,
        rstate=np.random.default_rng(seed),
        **steps,
    )
    sampler.run_nested(dlogz=dlogz, print_progress=progress)
    res = sampler.results
    if target is not None:
        return _reweighted(res, space, target, seed, nlive, dlogz, progress, n_draws, walks)
    return EvidenceResult(
        log_z=float(res.logz[-1]),
        log_z_err=float(res.logzerr[-1]),
        n_calls=int(np.sum(res.ncall)),
        max_log_like=float(np.max(res.logl)),
        samples=np.asarray(res.samples_equal(rstate=np.random.default_rng(seed))),
        best=np.asarray(res.samples[int(np.argmax(res.logl))]),
    )


def _reweighted(res, space, target, seed, nlive, dlogz, progress, n_draws, walks):
    """The proposal run ``res`` reweighted to ``target``, or a direct run of ``target`` when
    the reweighting is unreliable (Pareto shape > :data:`~mavispm.dynamics.reweighting.K_MAX`)."""
    from mavispm.dynamics.reweighting import K_MAX, reweight_samples

    rng = np.random.default_rng([seed, 71])
    logw = res.logwt - res.logz[-1]
    pick = rng.choice(logw.size, size=n_draws, replace=True, p=np.exp(logw) / np.exp(logw).sum())
    rw = reweight_samples(res.samples[pick], res.logl[pick], target, rng)
    if not rw["pareto_k"] <= K_MAX:
        direct = run_dynesty(
            target, space, seed, nlive=nlive, dlogz=dlogz, progress=progress, walks=walks
        )
        direct.n_calls += int(np.sum(res.ncall)) + rw["n_calls"]
        direct.pareto_k = rw["pareto_k"]
        return direct
    return EvidenceResult(
        log_z=float(res.logz[-1]) + rw["log_mean_ratio"],
        log_z_err=float(np.hypot(res.logzerr[-1], rw["log_mean_ratio_err"])),
        n_calls=int(np.sum(res.ncall)) + rw["n_calls"],
        max_log_like=rw["max_log_like"],
        samples=rw["samples"],
        best=rw["best"],
        method="reweighted",
        pareto_k=rw["pareto_k"],
    )


def bayes_factor(imbh: EvidenceResult, no_imbh: EvidenceResult):
    """``ln B`` (IMBH over no-IMBH) and its error.

    Parameters
    ----------
    imbh, no_imbh : EvidenceResult
        Nested-sampling evidences of the two models.

    Returns
    -------
    ln_b : float
        ``ln Z_imbh - ln Z_no_imbh``.
    ln_b_err : float
        The two evidence errors in quadrature.
    """
    return imbh.log_z - no_imbh.log_z, float(np.hypot(imbh.log_z_err, no_imbh.log_z_err))


def information_criteria(max_log_like: float, n_params: int, n_data: int) -> dict:
    """AIC and BIC from the maximum ln L (smaller is better).

    Parameters
    ----------
    max_log_like : float
        Maximum log likelihood.
    n_params : int
        Free parameters.
    n_data : int
        Data points (stars).

    Returns
    -------
    dict
        ``aic`` and ``bic``.
    """
    return {
        "aic": 2.0 * n_params - 2.0 * max_log_like,
        "bic": n_params * np.log(n_data) - 2.0 * max_log_like,
    }


def savage_dickey(bh_samples: ArrayLike, prior_max: float, min_samples: int = 50):
    """Savage-Dickey ln B_10 from IMBH posterior samples of ``bh_mass``.

    The posterior density at zero is the fraction of samples in ``[0, h]``
    divided by ``h`` (a one-sided histogram at the boundary of a uniform prior
    on ``[0, prior_max]``), with ``h`` 5 % of the 95 % upper quantile.

    Parameters
    ----------
    bh_samples : array_like
        Posterior samples of the IMBH mass [solMass].
    prior_max : float
        Upper end of the uniform prior [solMass].
    min_samples : int
        Fewest samples in ``[0, h]`` for a valid estimate.

    Returns
    -------
    ln_b : float
        ``ln B_10`` or NaN when not valid.
    note : str
        Why it is (not) valid.
    """
    x = np.asarray(bh_samples, dtype=float)
    if x.size == 0:
        return np.nan, "not valid: no posterior samples"
    h = 0.05 * np.percentile(x, 95)
    n0 = int(np.sum(x <= h)) if h > 0 else 0
    if n0 < min_samples:
        return np.nan, (
            f"not valid: only {n0} posterior samples near M_bh = 0 (< {min_samples}); too little "
            "posterior support at zero for a density estimate (as for a strong detection); "
            "use the nested-sampling ln B"
        )
    post0 = n0 / x.size / h
    prior0 = 1.0 / prior_max
    return float(np.log(prior0) - np.log(post0)), f"valid: {n0} samples within {h:.3g} of zero"
