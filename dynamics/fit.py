"""Fit the IMBH and no-IMBH Jeans models to a star sample and compare them.

Pure orchestration of :mod:`likelihood`, :mod:`sampling` and :mod:`evidence`:
no file input or output here (see :mod:`mavispm.dynamics.cli`).
"""

from __future__ import annotations

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
        Parameter(
            "log_scale_radius", lo=s.log_scale_radius_range[0], hi=s.log_scale_radius_range[1]
        ),
    ]
    if with_bh:
        params.append(Parameter("bh_mass", lo=0.0, hi=s.bh_mass_max))
    params.append(Parameter("beta", lo=s.beta_range[0], hi=s.beta_range[1]))
    if s.distance_error > 0:
        params.append(Parameter("distance", prior="gaussian", mean=distance, sd=s.distance_error))
    if s.fit_gamma or s.cusp:
        params.append(Parameter("gamma", lo=s.gamma_range[0], hi=s.gamma_range[1]))
    if s.cusp:
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


def fit_model(stars, settings, distance, with_bh, seed, backend_path=None) -> ModelFit:
    """Sample one model with emcee (and its evidence with dynesty if enabled)."""
    name = "imbh" if with_bh else "no_imbh"
    space = parameter_space(settings, distance, with_bh)
    like = make_likelihood(stars, space, settings, distance)
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
    )
    max_ll = chain.max_log_like
    evid = None
    if settings.evidence:
        evid = run_dynesty(like, space, seed + 1, nlive=settings.nlive, dlogz=settings.dlogz)
        max_ll = max(max_ll, evid.max_log_like)
    return ModelFit(
        name=name,
        space=space,
        likelihood=like,
        chain=chain,
        summary=summarise(chain.samples, chain.names),
        evidence=evid,
        criteria={"max_log_like": max_ll, **information_criteria(max_ll, len(space), stars.R.size)},
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
