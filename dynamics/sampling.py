"""emcee sampling of a Jeans likelihood in order-unity scaled parameters.

* Walkers move in the scaled space of :class:`~mavispm.dynamics.parameters.ParameterSpace`
  (every parameter of order unity), started in a small ball around the
  maximum a posteriori point found with Powell's method.
* The chain is stored in an emcee HDF5 backend, so a killed fit resumes where
  it stopped. The backend is keyed (``backend_key``: a hash of the data and
  settings); a chain of other data, other settings or another walker number is
  never continued but started again. A resumed fit replays the convergence
  checks of the steps already stored and continues with the stored random
  state, so it gives the same samples as an uninterrupted fit.
* Convergence: the run continues in blocks until every parameter's integrated
  autocorrelation time ``tau`` satisfies ``steps >= tau_factor * tau`` (default
  50) and ``tau`` changed by less than 1 % over the last block, or until
  ``max_steps``. Burn-in (``burn_tau`` x tau) is dropped and the chain thinned by tau / 2.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import emcee
import numpy as np
from scipy.optimize import minimize

if TYPE_CHECKING:
    from mavispm.dynamics.parameters import ParameterSpace

__all__ = [
    "BACKEND_KEY_ATTR",
    "ChainResult",
    "checkpoints",
    "find_map",
    "h5py_readable",
    "run_emcee",
    "summarise",
]


@dataclass
class ChainResult:
    """Posterior samples and diagnostics of one emcee run.

    Parameters
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
    resumed_at: int = 0


#: Attribute of the backend group holding the key of the data and settings it samples.
BACKEND_KEY_ATTR = "mavispm_key"


def checkpoints(max_steps: int, check_every: int) -> list[int]:
    """Chain lengths at which convergence is checked: every ``check_every`` steps and at the end.

    Parameters
    ----------
    max_steps : int
        Longest chain [steps].
    check_every : int
        Steps between checks (at least 1).

    Returns
    -------
    list of int
        Ascending chain lengths, ending at ``max_steps`` (empty when it is 0).
    """
    every = max(1, int(check_every))
    out = list(range(every, max_steps + 1, every))
    if max_steps > 0 and (not out or out[-1] != max_steps):
        out.append(max_steps)
    return out


def _converged(tau, old_tau, it: int, tau_factor: float) -> bool:
    """The stopping rule: ``it > tau_factor * tau`` and tau stable to 1 % (or twice as long)."""
    if np.all(np.isfinite(tau)) and np.all(tau_factor * tau < it):
        return bool(
            np.all(np.abs(old_tau - tau) / tau < 0.01) or np.all(tau_factor * tau < 0.5 * it)
        )
    return False


def _open_backend(path, name: str, walkers: int, ndim: int, key: str | None):
    """The emcee backend and the number of steps it holds that may be continued (0 = fresh).

    A chain is continued only when its group exists with the same shape and the
    same key; otherwise (other data or settings, unreadable file) it is reset.
    """
    backend = emcee.backends.HDFBackend(str(path), name=name)
    try:
        with backend.open() as f:
            stored = f[name].attrs.get(BACKEND_KEY_ATTR) if name in f else None
        same = (stored.decode() if isinstance(stored, bytes) else stored) == key
        iteration = int(backend.iteration) if same and backend.shape == (walkers, ndim) else 0
    except (OSError, KeyError, AttributeError):
        iteration = 0
        if Path(path).exists() and not h5py_readable(path):
            Path(path).unlink()  # a damaged file (killed while writing): start again
    if iteration == 0:
        backend.reset(walkers, ndim)
        if key is not None:
            with backend.open("a") as f:
                f[name].attrs[BACKEND_KEY_ATTR] = key
    return backend, iteration


def h5py_readable(path: str | os.PathLike) -> bool:
    """Whether ``path`` opens as an HDF5 file.

    Parameters
    ----------
    path : str or os.PathLike
        The file.

    Returns
    -------
    bool
        True when h5py can open it for reading.
    """
    import h5py

    try:
        with h5py.File(path, "r"):
            return True
    except OSError:
        return False


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


def find_map(
    loglike: Callable[[np.ndarray], float],
    space: ParameterSpace,
    starts: Sequence[np.ndarray] | None = None,
):
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
    loglike: Callable[[np.ndarray], float],
    space: ParameterSpace,
    seed: int,
    walkers: int = 32,
    max_steps: int = 20000,
    tau_factor: float = 50.0,
    check_every: int = 500,
    burn_tau: float = 5.0,
    backend_path: str | Path | None = None,
    backend_name: str = "mcmc",
    progress: bool = True,
    backend_key: str | None = None,
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
        emcee HDF5 backend file; an existing chain with the same name, shape and
        ``backend_key`` is resumed (and gives the same result as an uninterrupted
        run), any other chain in that group is discarded.
    backend_name : str
        Group name inside the backend file (one per model).
    progress : bool
        Show a tqdm progress bar.
    backend_key : str, optional
        Hash of everything the chain depends on (data, settings, seed), stored
        with the chain: a chain is never continued for other data.
    """
    ndim = len(space)
    walkers = max(int(walkers), 2 * ndim + 2)
    rng = np.random.default_rng(seed)
    post = _Posterior(loglike, space)
    backend = None
    resumed_at = 0
    if backend_path is not None:
        backend, resumed_at = _open_backend(backend_path, backend_name, walkers, ndim, backend_key)
    # differential-evolution moves: affine invariant like the stretch move, but
    # much shorter autocorrelation times for the banana-shaped M-a-M_bh posteriors
    moves = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    sampler = emcee.EnsembleSampler(walkers, ndim, post, backend=backend, moves=moves)
    sampler.random_state = np.random.RandomState(seed).get_state()
    old_tau = np.inf
    converged = False
    tau = np.full(ndim, np.nan)
    plan = checkpoints(max_steps, check_every)
    if resumed_at:
        # the stored chain (and its random state) continues; replay the convergence
        # checks an uninterrupted run made at the checkpoints already passed
        state = None
        chain = sampler.get_chain()
        for c in [c for c in plan if c <= resumed_at]:
            tau = emcee.autocorr.integrated_time(chain[:c], tol=0)
            if _converged(tau, old_tau, c, tau_factor):
                converged = True
                break
            old_tau = tau
        if resumed_at not in plan and not converged:
            tau = sampler.get_autocorr_time(tol=0)
    else:
        z_map = find_map(loglike, space)
        state = z_map + 1e-3 * rng.standard_normal((walkers, ndim))
        # keep starting walkers inside the prior support
        for i in range(walkers):
            while not np.isfinite(post(state[i])[0]):
                state[i] = z_map + 1e-4 * rng.standard_normal(ndim)
    for c in plan:
        if converged or c <= sampler.iteration:
            continue
        state = sampler.run_mcmc(state, c - sampler.iteration, progress=progress)
        tau = sampler.get_autocorr_time(tol=0)
        if _converged(tau, old_tau, sampler.iteration, tau_factor):
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
        resumed_at=int(resumed_at),
    )


def summarise(samples: np.ndarray, names: Sequence[str], detection_ratio: float = 0.1) -> dict:
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
