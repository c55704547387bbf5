"""Fit the IMBH and no-IMBH Jeans models to a star sample and compare them.

Pure orchestration of :mod:`likelihood`, :mod:`sampling` and :mod:`evidence`:
no file input or output here (see :mod:`mavispm.dynamics.cli`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mavispm.dynamics.evidence import (
    EvidenceResult,
    bayes_factor,
    information_criteria,
    run_dynesty,
    savage_dickey,
)
from mavispm.dynamics.likelihood import DiscreteLikelihood, StarSample
from mavispm.dynamics.parameters import Parameter, ParameterSpace
from mavispm.dynamics.sampling import ChainResult, run_emcee, summarise
from mavispm.dynamics.settings import DynamicsSettings

LABELS = {
    "log_mass": r"$\log_{10} M/M_\odot$",
    "log_scale_radius": r"$\log_{10} a/''$",
    "bh_mass": r"$M_{\rm BH}/M_\odot$",
    "beta": r"$\beta$",
    "distance": r"$d$/kpc",
    "gamma": r"$\gamma$",
    "log_cusp_radius": r"$\log_{10} r_c/''$",
}


def _scale_radius_parameter(s: DynamicsSettings) -> Parameter:
    """Uniform on ``log_scale_radius_range``, or Gaussian (``log_scale_radius_prior``)."""
    if s.log_scale_radius_prior is not None:
        mean, sd = s.log_scale_radius_prior
        return Parameter("log_scale_radius", prior="gaussian", mean=mean, sd=sd)
    lo, hi = s.log_scale_radius_range
    return Parameter("log_scale_radius", lo=lo, hi=hi)


def parameter_space(settings: DynamicsSettings, distance: float, with_bh: bool) -> ParameterSpace:
    """Priors of the IMBH (``with_bh``) or no-IMBH model.

    Parameters
    ----------
    settings : DynamicsSettings
    distance : float
        Distance [kpc] (prior mean when ``settings.distance_error > 0``).
    with_bh : bool
    """
    s = settings
    params = [
        Parameter("log_mass", lo=s.log_mass_range[0], hi=s.log_mass_range[1]),
        _scale_radius_parameter(s),
    ]
    if with_bh:
        params.append(Parameter("bh_mass", lo=0.0, hi=s.bh_mass_max))
    params.append(Parameter("beta", lo=s.beta_range[0], hi=s.beta_range[1]))
    if s.distance_error > 0:
        params.append(Parameter("distance", prior="gaussian", mean=distance, sd=s.distance_error))
    linked = s.cusp and s.cusp_link == "influence"
    if s.fit_gamma or (s.cusp and (with_bh or not linked)):
        params.append(Parameter("gamma", lo=s.gamma_range[0], hi=s.gamma_range[1]))
    if s.cusp and not linked:
        lo, hi = s.log_cusp_radius_range
        params.append(Parameter("log_cusp_radius", lo=lo, hi=hi))
    return ParameterSpace([Parameter(**{**p.__dict__, "label": LABELS[p.name]}) for p in params])


def make_likelihood(
    stars: StarSample, space: ParameterSpace, settings: DynamicsSettings, distance: float
):
    """The discrete likelihood for one model's parameter order."""
    s = settings
    return DiscreteLikelihood(
        stars,
        space.names,
        tracer=s.tracer,
        gamma=s.dehnen_gamma,
        concentration=s.king_concentration,
        cusp_link=s.cusp_link if s.cusp else None,
        distance=distance,
        scale_radius_range=tuple(10.0 ** np.asarray(s.log_scale_radius_range)),
        min_radius=s.min_radius,
        grid_size=s.grid_size,
        n_panels=s.projection_panels,
        n_gl=s.projection_nodes,
        x_max=s.truncation,
        star_counts=s.star_counts,
    )


@dataclass
class ModelFit:
    """One model's fit: space, likelihood, chain, summary and evidence."""

    name: str
    space: ParameterSpace
    likelihood: DiscreteLikelihood
    chain: ChainResult
    summary: dict
    evidence: EvidenceResult | None = None
    criteria: dict = field(default_factory=dict)
    #: wall-clock seconds of the emcee run and of the nested sampling
    wall_s: dict = field(default_factory=dict)


@dataclass
class Comparison:
    """IMBH vs no-IMBH model comparison (``ln B > 0`` favours the IMBH)."""

    ln_bayes_factor: float = np.nan
    ln_bayes_factor_err: float = np.nan
    delta_ln_likelihood: float = np.nan
    delta_aic: float = np.nan
    delta_bic: float = np.nan
    savage_dickey_ln_b: float = np.nan
    savage_dickey_note: str = ""

    def as_attrs(self) -> dict:
        """Root attributes for the dynamics product."""
        return dict(self.__dict__)


def backend_key(stars, settings, distance, with_bh, seed) -> str:
    """Hash of everything an emcee chain depends on: the stars, the settings, distance, seed.

    Stored with the chain in its backend so that a chain is resumed only for the
    same data and settings, never continued for other data.
    """
    from dataclasses import asdict

    from mavispm.core.array_cache import content_key

    knobs = {k: v for k, v in asdict(settings).items() if k != "progress"}
    arrays = [np.asarray(getattr(stars, c), dtype=float) for c in ("R", "v_r", "v_t", "e_r", "e_t")]
    return content_key(
        *arrays,
        float(stars.field_radius),
        knobs,
        None if distance is None else float(distance),
        bool(with_bh),
        int(seed),
    )


def fit_model(stars, settings, distance, with_bh, seed, backend_path=None) -> ModelFit:
    """Sample one model with emcee (and its evidence with dynesty if enabled)."""
    name = "imbh" if with_bh else "no_imbh"
    space = parameter_space(settings, distance, with_bh)
    like = make_likelihood(stars, space, settings, distance)
    t0 = time.perf_counter()
    key = backend_key(stars, settings, distance, with_bh, seed)
    chain = run_emcee(
        like,
        space,
        seed,
        walkers=settings.walkers,
        max_steps=settings.max_steps,
        tau_factor=settings.tau_factor,
        check_every=settings.check_every,
        backend_path=backend_path,
        backend_name=name,
        progress=settings.progress,
        backend_key=key,
    )
    wall = {"emcee": time.perf_counter() - t0}
    max_ll = chain.max_log_like
    evid = None
    if settings.evidence:
        t0 = time.perf_counter()
        evid = run_dynesty(like, space, seed + 1, nlive=settings.nlive, dlogz=settings.dlogz)
        wall["evidence"] = time.perf_counter() - t0
        max_ll = max(max_ll, evid.max_log_like)
    return ModelFit(
        name=name,
        space=space,
        likelihood=like,
        chain=chain,
        summary=summarise(chain.samples, chain.names),
        evidence=evid,
        criteria={"max_log_like": max_ll, **information_criteria(max_ll, len(space), stars.R.size)},
        wall_s=wall,
    )


def compare(imbh: ModelFit, no_imbh: ModelFit, bh_mass_max: float) -> Comparison:
    """Bayes factor, likelihood ratio, AIC/BIC and Savage-Dickey for two fits."""
    out = Comparison()
    if imbh.evidence is not None and no_imbh.evidence is not None:
        out.ln_bayes_factor, out.ln_bayes_factor_err = bayes_factor(imbh.evidence, no_imbh.evidence)
    out.delta_ln_likelihood = imbh.criteria["max_log_like"] - no_imbh.criteria["max_log_like"]
    out.delta_aic = imbh.criteria["aic"] - no_imbh.criteria["aic"]
    out.delta_bic = imbh.criteria["bic"] - no_imbh.criteria["bic"]
    bh = imbh.chain.samples[:, imbh.space.index("bh_mass")]
    out.savage_dickey_ln_b, out.savage_dickey_note = savage_dickey(bh, bh_mass_max)
    return out
