"""emcee sampling of a Jeans likelihood in order-unity scaled parameters.

* Walkers move in the scaled space of :class:`~mavispm.dynamics.parameters.ParameterSpace`
  (every parameter of order unity), started in a small ball around the
  maximum a posteriori point found with Powell's method.
* The chain is stored in an emcee HDF5 backend, so a killed fit resumes where
  it stopped (same file, same group name, same walker number).
* Convergence: the run continues in blocks until every parameter's integrated
  autocorrelation time ``tau`` satisfies ``steps >= tau_factor * tau`` (default
  50) and ``tau`` changed by less than 1 % over the last block, or until
  ``max_steps``. Burn-in (``burn_tau`` x tau) is dropped and the chain thinned by tau / 2.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import emcee
import numpy as np
from scipy.optimize import minimize


@dataclass
class ChainResult:
    """Posterior samples and diagnostics of one emcee run.

    Attributes
    ----------
    names : list of str
    samples : ndarray (n, ndim)
        Physical parameter values after burn-in and thinning.
    log_like : ndarray (n,)
        ln L of each sample.
    tau : ndarray (ndim,)
        Integrated autocorrelation time per parameter [steps].
    steps : int
        Steps per walker run in total.
    converged : bool
        Whether ``steps >= tau_factor * max(tau)`` was reached.
    map_params : ndarray (ndim,)
        Highest-posterior point found (optimiser or chain).
    max_log_like : float
        Highest ln L found.
    acceptance : float
        Mean acceptance fraction.
    """

    names: list
    samples: np.ndarray
    log_like: np.ndarray
    tau: np.ndarray
    steps: int
    converged: bool
    map_params: np.ndarray
    max_log_like: float
    acceptance: float


class _Posterior:
    """ln posterior in scaled space, with ln L as a blob (picklable)."""

    def __init__(self, loglike, space):
        self.loglike = loglike
        self.space = space

    def __call__(self, z):
        lp = self.space.log_prior_scaled(z)
        if not np.isfinite(lp):
            return -np.inf, -np.inf
        ll = self.loglike(self.space.from_scaled(z))
        if not np.isfinite(ll):
            return -np.inf, -np.inf
        return lp + ll, ll


def find_map(loglike, space, starts=None):
    """Maximum a posteriori point in scaled space (Powell, several starts).

    Parameters
    ----------
    loglike : callable
        ln L of a physical parameter vector.
    space : ParameterSpace
    starts : list of ndarray, optional
        Scaled starting points; by default the prior centre, all parameters at
        +-0.5, and (with a ``bh_mass`` parameter) the centre with ``bh_mass``
        at its lower prior edge, so a nested no-IMBH optimum is always reachable.

    Returns
    -------
    z_best : ndarray
        Scaled MAP point.
    """
    post = _Posterior(loglike, space)
    ndim = len(space)
    if starts is None:
        starts = [np.zeros(ndim)]
        for sign in (-0.5, 0.5):
            starts.append(np.full(ndim, sign))
        if "bh_mass" in space.names:
            z0 = np.zeros(ndim)
            z0[space.index("bh_mass")] = -0.999
            starts.append(z0)

    def neg(z):
        val = post(z)[0]
        return 1e30 if not np.isfinite(val) else -val

    best, best_val = None, np.inf
    for z0 in starts:
        res = minimize(neg, z0, method="Powell", options={"xtol": 1e-4, "ftol": 1e-8})
        if res.fun < best_val:
            best, best_val = res.x, res.fun
    # polish from the best point (Powell can stall on a prior edge)
    res = minimize(neg, best, method="Nelder-Mead", options={"xatol": 1e-5, "fatol": 1e-8})
    return res.x if res.fun < best_val else best


def run_emcee(
    loglike,
    space,
    seed: int,
    walkers: int = 32,
    max_steps: int = 20000,
    tau_factor: float = 50.0,
    check_every: int = 500,
    burn_tau: float = 5.0,
    backend_path: str | Path | None = None,
    backend_name: str = "mcmc",
    progress: bool = True,
) -> ChainResult:
    """Sample the posterior with emcee until the autocorrelation criterion holds.

    Parameters
    ----------
    loglike : callable
        ln L of a physical parameter vector (returns -inf when invalid).
    space : ParameterSpace
        Priors and scaling.
    seed : int
        Seeds the walker start and the emcee moves (deterministic).
    walkers : int
        Number of walkers (>= 2 * ndim + 2).
    max_steps : int
        Hard limit on steps per walker.
    tau_factor : float
        Required chain length in autocorrelation times.
    check_every : int
        Steps between convergence checks (and progress-bar updates).
    burn_tau : float
        Burn-in dropped, in autocorrelation times.
    backend_path : path, optional
        emcee HDF5 backend file; an existing chain with the same name and shape is resumed.
    backend_name : str
        Group name inside the backend file (one per model).
    progress : bool
        Show a tqdm progress bar.
    """
    ndim = len(space)
    walkers = max(int(walkers), 2 * ndim + 2)
    rng = np.random.default_rng(seed)
    post = _Posterior(loglike, space)
    backend = None
    resume = False
    if backend_path is not None:
        backend = emcee.backends.HDFBackend(str(backend_path), name=backend_name)
        try:
            resume = backend.iteration > 0 and backend.shape == (walkers, ndim)
        except (OSError, KeyError, AttributeError):
            resume = False
        if not resume:
            backend.reset(walkers, ndim)
    # differential-evolution moves: affine invariant like the stretch move, but
    # much shorter autocorrelation times for the banana-shaped M-a-M_bh posteriors
    moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    sampler = emcee.EnsembleSampler(walkers, ndim, post, backend=backend, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()
    if resume:
        state = None
    else:
        z_map = find_map(loglike, space)
        state = z_map + 1e-3 * rng.standard_normal((walkers, ndim))
        # keep starting walkers inside the prior support
        for i in range(walkers):
            while not np.isfinite(post(state[i])[0]):
                state[i] = z_map + 1e-4 * rng.standard_normal(ndim)
    old_tau = np.inf
    converged = False
    tau = np.full(ndim, np.nan)
    while sampler.iteration < max_steps:
        n = min(check_every, max_steps - sampler.iteration)
        state = sampler.run_mcmc(state, n, progress=progress)
        tau = sampler.get_autocorr_time(tol=0)
        it = sampler.iteration
        if np.all(np.isfinite(tau)) and np.all(tau_factor * tau < it):
            if np.all(np.abs(old_tau - tau) / tau < 0.01) or np.all(tau_factor * tau < 0.5 * it):
                converged = True
                break
        old_tau = tau
    tau_max = float(np.nanmax(tau)) if np.any(np.isfinite(tau)) else 1.0
    burn = min(int(burn_tau * tau_max), sampler.iteration // 2)
    thin = max(1, int(0.5 * tau_max))
    z = sampler.get_chain(discard=burn, thin=thin, flat=True)
    ll = sampler.get_blobs(discard=burn, thin=thin, flat=True)
    all_ll = sampler.get_blobs(flat=True)
    all_lp = sampler.get_log_prob(flat=True)
    all_z = sampler.get_chain(flat=True)
    best = int(np.argmax(all_lp))
    return ChainResult(
        names=list(space.names),
        samples=space.from_scaled(z),
        log_like=np.asarray(ll, dtype=float),
        tau=np.asarray(tau, dtype=float),
        steps=int(sampler.iteration),
        converged=converged,
        map_params=space.from_scaled(all_z[best]),
        max_log_like=float(np.nanmax(np.asarray(all_ll, dtype=float))),
        acceptance=float(np.mean(sampler.acceptance_fraction)),
    )


def summarise(samples, names, detection_ratio: float = 0.1) -> dict:
    """Posterior summaries per parameter.

    Parameters
    ----------
    samples : ndarray (n, ndim)
    names : list of str
    detection_ratio : float
        ``bh_mass`` counts as detected when its 2.5th percentile exceeds this
        fraction of its median (the posterior is then separated from zero);
        otherwise an upper limit is the relevant summary.

    Returns
    -------
    dict
        ``{name: {"median", "lo68", "hi68", "lo95", "hi95", "upper95"}}`` and,
        for ``bh_mass``, ``"detected"`` (bool).
    """
    out = {}
    for i, name in enumerate(names):
        col = samples[:, i]
        q = np.percentile(col, [2.5, 16, 50, 84, 97.5, 95])
        out[name] = {
            "median": q[2],
            "lo68": q[1],
            "hi68": q[3],
            "lo95": q[0],
            "hi95": q[4],
            "upper95": q[5],
        }
        if name == "bh_mass":
            out[name]["detected"] = bool(q[0] > detection_ratio * q[2])
    return out
