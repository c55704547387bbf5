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


def run_dynesty(
    loglike: Callable[[np.ndarray], float],
    space: ParameterSpace,
    seed: int,
    nlive: int = 250,
    dlogz: float = 0.1,
    progress: bool = False,
):
    """Evidence of one model with dynesty's static nested sampler.

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
    """
    import dynesty

    def ll(v):
        val = loglike(v)
        return val if np.isfinite(val) else -1e300

    sampler = dynesty.NestedSampler(
        ll,
        space.from_unit,
        len(space),
        nlive=nlive,
        rstate=np.random.default_rng(seed),
    )
    sampler.run_nested(dlogz=dlogz, print_progress=progress)
    res = sampler.results
    return EvidenceResult(
        log_z=float(res.logz[-1]),
        log_z_err=float(res.logzerr[-1]),
        n_calls=int(np.sum(res.ncall)),
        max_log_like=float(np.max(res.logl)),
        samples=np.asarray(res.samples_equal(rstate=np.random.default_rng(seed))),
        best=np.asarray(res.samples[int(np.argmax(res.logl))]),
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
