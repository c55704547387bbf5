"""Fit the mass models (no dark centre, IMBH, extended dark component, both) and compare them.

Pure orchestration of :mod:`likelihood`, :mod:`sampling` and :mod:`evidence`:
no file input or output here (see :mod:`mavispm.dynamics.cli`).

``ln_bayes_factor`` is the evidence of the best model with an IMBH against the
best model without one; ``ln_bayes_factor_kinematic`` the same from the
kinematics alone (the star-count term off). The M_BH posterior is marginalised
over the IMBH models (their samples mixed in proportion to their evidences).
A fit whose chains have not converged gives no headline numbers (NaN) and says so.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.special import logsumexp, softmax

from mavispm.dynamics.evidence import (
    EvidenceResult,
    information_criteria,
    run_dynesty,
    savage_dickey,
)
from mavispm.dynamics.likelihood import DEPTH_MIXTURE_LAWS, DiscreteLikelihood, StarSample
from mavispm.dynamics.parameters import Parameter, ParameterSpace
from mavispm.dynamics.sampling import ChainResult, run_emcee, summarise
from mavispm.dynamics.settings import MODELS, WEIGHED, DynamicsSettings

__all__ = [
    "Comparison",
    "ModelFit",
    "backend_key",
    "compare",
    "evidence_strength",
    "fit_model",
    "make_likelihood",
    "marginal_bh_samples",
    "nested_chain",
    "parameter_space",
]

LABELS = {
    "log_mass": r"$\log_{10} M/M_\odot$",
    "log_scale_radius": r"$\log_{10} a/''$",
    "gamma": r"$\gamma$",
    "log_cusp_radius": r"$\log_{10} r_c/''$",
    "bh_mass": r"$M_{\rm BH}/M_\odot$",
    "dark_mass": r"$M_{\rm dark}/M_\odot$",
    "log_dark_radius": r"$\log_{10} b/''$",
    "beta": r"$\beta$",
    "beta_0": r"$\beta_0$",
    "beta_inf": r"$\beta_\infty$",
    "log_anisotropy_radius": r"$\log_{10} r_a/''$",
    "distance": r"$d$/kpc",
    "x0": r"$x_0/''$",
    "y0": r"$y_0/''$",
    "pm_x0": r"$\mu_{x,0}$",
    "pm_y0": r"$\mu_{y,0}$",
    "kappa": r"$\kappa$",
    "kappa_inner": r"$\kappa_{\rm in}$",
    "kappa_outer": r"$\kappa_{\rm out}$",
}


def _scale_radius_parameter(s: DynamicsSettings) -> Parameter:
    """Uniform on ``log_scale_radius_range``, or Gaussian (``log_scale_radius_prior``)."""
    if s.log_scale_radius_prior is not None:
        mean, sd = s.log_scale_radius_prior
        return Parameter("log_scale_radius", prior="gaussian", mean=mean, sd=sd)
    lo, hi = s.log_scale_radius_range
    return Parameter("log_scale_radius", lo=lo, hi=hi)


def _model_name(model) -> str:
    if isinstance(model, bool):  # older callers: with / without an IMBH
        return "imbh" if model else "none"
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; expected one of {sorted(MODELS)}")
    return model


def parameter_space(
    settings: DynamicsSettings, distance: float, model="imbh", positions: bool = True
) -> ParameterSpace:
    """Priors of one mass model.

    Parameters
    ----------
    settings : DynamicsSettings
    distance : float
        Distance [kpc] (prior mean when the distance is fitted).
    model : {"none", "imbh", "dark", "imbh_dark"} or bool
        Dark central components (``True``/``False`` mean "imbh"/"none").
    positions : bool
        Whether star positions are available (needed for the centre and systemic motion).
    """
    s = settings
    if s.velocity_law == WEIGHED:
        raise ValueError(
            "parameter_space is one velocity law's: set velocity_law to one law (the default "
            "'weighed' fits each law of compare_velocity_laws in turn, fit_models)"
        )
    parts = MODELS[_model_name(model)]
    params = [
        Parameter("log_mass", lo=s.log_mass_range[0], hi=s.log_mass_range[1]),
        _scale_radius_parameter(s),
    ]
    if s.cusp:
        params.append(Parameter("gamma", lo=s.gamma_range[0], hi=s.gamma_range[1]))
        if s.tracer != "dehnen":
            lo, hi = s.log_cusp_radius_range
            params.append(Parameter("log_cusp_radius", lo=lo, hi=hi))
    if parts["bh"]:
        params.append(Parameter("bh_mass", lo=0.0, hi=s.bh_mass_max))
    if parts["dark"]:
        params.append(Parameter("dark_mass", lo=0.0, hi=s.dark_mass_max))
        lo, hi = s.log_dark_radius_range
        params.append(Parameter("log_dark_radius", lo=lo, hi=hi))
    if s.anisotropy == "constant":
        params.append(Parameter("beta", lo=s.beta_range[0], hi=s.beta_range[1]))
    else:
        if s.anisotropy == "general":
            params.append(Parameter("beta_0", lo=s.beta_range[0], hi=s.beta_range[1]))
            lo, hi = s.beta_inf_range
            params.append(Parameter("beta_inf", lo=lo, hi=hi))
        lo, hi = s.log_anisotropy_radius_range
        params.append(Parameter("log_anisotropy_radius", lo=lo, hi=hi))
    if s.velocity_law == "line_of_sight_kurtosis":
        params.append(Parameter("kappa", lo=s.kappa_range[0], hi=s.kappa_range[1]))
    if s.velocity_law == "free_kurtosis":
        lo, hi = s.kappa_range
        names = ("kappa",) if s.kappa_profile == "constant" else ("kappa_inner", "kappa_outer")
        params.extend(Parameter(name, lo=lo, hi=hi) for name in names)
    sd = s.distance_sd(distance)
    if sd > 0:
        params.append(Parameter("distance", prior="gaussian", mean=distance, sd=sd))
    if positions and s.centre_error > 0:
        for name in ("x0", "y0"):
            params.append(Parameter(name, prior="gaussian", mean=0.0, sd=s.centre_error))
    if positions and s.systemic_error > 0:
        for name in ("pm_x0", "pm_y0"):
            params.append(Parameter(name, prior="gaussian", mean=0.0, sd=s.systemic_error))
    return ParameterSpace([Parameter(**{**p.__dict__, "label": LABELS[p.name]}) for p in params])


def make_likelihood(
    stars: StarSample,
    space: ParameterSpace,
    settings: DynamicsSettings,
    distance: float,
    star_counts: bool | None = None,
):
    """The discrete likelihood for one model's parameter order.

    ``star_counts`` overrides ``settings.star_counts`` (False: kinematics only).

    Parameters
    ----------
    stars : StarSample
        The stars.
    space : ParameterSpace
        The model's parameters (their order sets the vector ``theta``).
    settings : DynamicsSettings
        Tracer, completeness, star counts and quadrature settings.
    distance : float
        Distance [kpc].
    star_counts : bool, optional
        Override of ``settings.star_counts``.

    Returns
    -------
    DiscreteLikelihood
        The likelihood.
    """
    s = settings
    completeness = None
    if s.completeness is not None:
        completeness = (s.completeness_radius, s.completeness)
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
        points_per_efold=s.radial_points_per_efold,
        x_max=s.truncation,
        star_counts=s.star_counts if star_counts is None else star_counts,
        completeness=completeness,
        velocity_law=s.velocity_law,
        line_of_sight_nodes=s.line_of_sight_nodes,
    )


@dataclass
class ModelFit:
    """One model's fit: space, likelihood, chain, summary and evidences.

    Parameters
    ----------
    name : str
        Model name (``none``, ``imbh``, ``dark``, ``imbh_dark``).
    space : ParameterSpace
        Its parameters and priors.
    likelihood : DiscreteLikelihood
        Its likelihood.
    chain : ChainResult
        Posterior samples and diagnostics.
    summary : dict
        Posterior quantiles per parameter.
    evidence, evidence_kinematic : EvidenceResult or None
        Nested-sampling evidences with and without the star counts.
    criteria : dict
        ``max_log_like``, ``aic``, ``bic``.
    wall_s : dict
        Wall-clock times of the emcee run and the nested sampling [s].
    law_fits : tuple of ModelFit
        With the velocity laws weighed: the model's fit with each law (each with its own
        evidence), whose evidence-weighted mixture is the model's posterior
        (:func:`marginal_bh_samples`); empty otherwise.
    """

    name: str
    space: ParameterSpace
    likelihood: DiscreteLikelihood
    chain: ChainResult
    summary: dict
    evidence: EvidenceResult | None = None
    evidence_kinematic: EvidenceResult | None = None
    criteria: dict = field(default_factory=dict)
    #: wall-clock seconds of the emcee run and of the nested sampling
    wall_s: dict = field(default_factory=dict)
    #: the model's fit with each velocity law when the laws are weighed
    law_fits: tuple = ()

    @property
    def has_bh(self) -> bool:
        """Whether the model has a central point mass."""
        return MODELS[self.name]["bh"]


def backend_key(stars, settings, distance, model, seed) -> str:
    """Hash of everything an emcee chain depends on: the stars, the settings, distance, seed.

    Stored with the chain in its backend so that a chain is resumed only for the
    same data and settings, never continued for other data.

    Parameters
    ----------
    stars : StarSample
        The stars.
    settings : DynamicsSettings
        The settings.
    distance : float
        Distance [kpc].
    model : str
        Model name.
    seed : int
        Random seed.

    Returns
    -------
    str
        Hexadecimal key.
    """
    from dataclasses import asdict

    from mavispm.core.array_cache import content_key

    knobs = {k: v for k, v in asdict(settings).items() if k not in ("progress", "workers")}
    cols = ("R", "v_r", "v_t", "e_r", "e_t") + (("x", "y") if stars.x is not None else ())
    arrays = [np.asarray(getattr(stars, c), dtype=float) for c in cols]
    return content_key(
        *arrays,
        float(stars.field_radius),
        knobs,
        None if distance is None else float(distance),
        str(model),
        int(seed),
    )


def fit_model(stars, settings, distance, model, seed, backend_path=None) -> ModelFit:
    """Sample one model with emcee (and its evidences with dynesty if enabled).

    BLAS runs single-threaded inside (the likelihood's small matrix products are
    2x slower with threads on a busy machine); parallelism is across models
    (``settings.workers``).

    Parameters
    ----------
    stars : StarSample
        The stars.
    settings : DynamicsSettings
        The settings (``posterior``, sampler and evidence switches).
    distance : float
        Distance [kpc].
    model : str
        Model name.
    seed : int
        Random seed.
    backend_path : str or os.PathLike, optional
        HDF5 file where the emcee chain is kept (and resumed from).

    Returns
    -------
    ModelFit
        The model's fit.
    """
    from threadpoolctl import threadpool_limits

    if settings.velocity_law == WEIGHED:
        raise ValueError(
            "fit_model fits one velocity law; velocity_law = 'weighed' (the default) is "
            "fitted by fit_models"
        )
    with threadpool_limits(limits=1, user_api="blas"):
        return _fit_model(stars, settings, distance, model, seed, backend_path)


def _fit_model(stars, settings, distance, model, seed, backend_path, kinematic=True) -> ModelFit:
    """One model's posterior and evidence; its kinematics-only evidence too if ``kinematic``."""
    name = _model_name(model)
    space = parameter_space(settings, distance, name, positions=stars.x is not None)
    like = make_likelihood(stars, space, settings, distance)
    wall = {}
    chain = None
    if settings.posterior == "emcee":
        t0 = time.perf_counter()
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
            backend_key=backend_key(stars, settings, distance, name, seed),
        )
        wall["emcee"] = time.perf_counter() - t0
    evid = evid_kin = None
    if settings.evidence:
        t0 = time.perf_counter()
        evid = _run_evidence(stars, space, settings, distance, like, seed + 1)
        wall["evidence"] = time.perf_counter() - t0
        if _separate_kinematic_evidence(settings):
            if kinematic:
                evid_kin, wall["evidence_kinematic"] = _kinematic_evidence(
                    stars, settings, distance, model, seed
                )
        elif not settings.star_counts:
            evid_kin = evid
    if chain is None:
        chain = nested_chain(evid, space)
    max_ll = chain.max_log_like if evid is None else max(chain.max_log_like, evid.max_log_like)
    return ModelFit(
        name=name,
        space=space,
        likelihood=like,
        chain=chain,
        summary=summarise(chain.samples, chain.names),
        evidence=evid,
        evidence_kinematic=evid_kin,
        criteria={"max_log_like": max_ll, **information_criteria(max_ll, len(space), stars.R.size)},
        wall_s=wall,
    )


def _separate_kinematic_evidence(settings: DynamicsSettings) -> bool:
    """Whether the kinematics-only evidence is a nested run of its own."""
    return bool(settings.evidence and settings.kinematic_evidence and settings.star_counts)


def _kinematic_evidence(stars, settings, distance, model, seed):
    """The kinematics-only evidence (star-count term off) and its wall time [s]."""
    space = parameter_space(settings, distance, _model_name(model), positions=stars.x is not None)
    kin = make_likelihood(stars, space, settings, distance, star_counts=False)
    t0 = time.perf_counter()
    evid = _run_evidence(stars, space, settings, distance, kin, seed + 2, star_counts=False)
    return evid, time.perf_counter() - t0


def _run_evidence(stars, space, settings, distance, like, seed, star_counts=None):
    """dynesty on ``like``; with ``reweight`` (and the line-of-sight law) a run with the
    Gaussian law reweighted to ``like`` (:func:`mavispm.dynamics.evidence.run_dynesty`)."""
    target = None
    if settings.reweight and settings.velocity_law == "line_of_sight":
        target = like
        gaussian = replace(settings, velocity_law="gaussian")
        like = make_likelihood(stars, space, gaussian, distance, star_counts=star_counts)
    s = settings
    return run_dynesty(
        like, space, seed, nlive=s.nlive, dlogz=s.dlogz, target=target, walks=s.walks
    )


def _n_extra(model: str) -> int:
    """Parameters a model adds to the cluster's (its relative cost)."""
    return int(MODELS[model]["bh"]) + 2 * int(MODELS[model]["dark"])


def _fit_part(args):
    """One job of :func:`fit_models`: a model's fit (``part = "fit"``, its
    kinematics-only evidence left out) or its kinematics-only evidence (``"kinematic"``)."""
    from threadpoolctl import threadpool_limits

    stars, settings, distance, model, seed, backend_path, part = args
    with threadpool_limits(limits=1, user_api="blas"):
        if part == "kinematic":
            return _kinematic_evidence(stars, settings, distance, model, seed)
        return _fit_model(stars, settings, distance, model, seed, backend_path, kinematic=False)


def fit_models(stars, settings, distance, seed, backend_stem=None) -> list:
    """Fit every model of ``settings.models`` (in ``settings.workers`` processes).

    With ``settings.velocity_law = "weighed"`` (the default) each model is fitted with each
    law of ``settings.compare_velocity_laws`` (:func:`weigh_velocity_laws`); otherwise
    with ``settings.velocity_law``.

    With more than one worker each model's fit and its kinematics-only evidence (with each
    law) are separate jobs of one process pool, handed out longest first, so that the
    pool's tail is short.

    Parameters
    ----------
    stars : StarSample
    settings : DynamicsSettings
    distance : float
        Distance [kpc] (prior mean when fitted).
    seed : int
    backend_stem : path, optional
        emcee backends are kept in ``<backend_stem>-<model>.h5`` (one file per
        model, so that models may run in parallel processes).

    Returns
    -------
    list of ModelFit
        In the order of ``settings.models``; the result does not depend on ``workers``.
    """
    per_law = _fit_laws(stars, settings, distance, seed, backend_stem)
    if settings.velocity_law == WEIGHED:
        return weigh_velocity_laws(per_law)
    return per_law[settings.velocity_law]


def _fit_laws(stars, settings, distance, seed, backend_stem=None) -> dict:
    """Each law of ``settings.laws`` fitted with every model: ``{law: [ModelFit, ...]}``.

    With more than one worker every (law, model, part) is one job of a single process pool,
    the dearest first (the depth-mixture laws, then the models with the most parameters,
    a fit before a lone kinematics-only evidence), so that neither a law's pool start-up
    nor its tail waits for the next law. The fits do not depend on ``workers``.
    """
    from pathlib import Path

    weighed = settings.velocity_law == WEIGHED
    one = {
        law: replace(settings, velocity_law=law, compare_velocity_laws=()) for law in settings.laws
    }

    def backend(law, m):
        if backend_stem is None:
            return None
        return Path(f"{backend_stem}-{law}-{m}.h5" if weighed else f"{backend_stem}-{m}.h5")

    workers = int(settings.workers)
    parts = ("fit", "kinematic") if _separate_kinematic_evidence(settings) else ("fit",)
    if workers <= 1 or len(one) * len(settings.models) * len(parts) <= 1:
        return {
            law: [fit_model(stars, s, distance, m, seed, backend(law, m)) for m in s.models]
            for law, s in one.items()
        }
    import concurrent.futures as cf
    import multiprocessing as mp

    jobs = [
        (stars, replace(s, progress=False), distance, m, seed, backend(law, m), part)
        for law, s in one.items()
        for m in s.models
        for part in parts
    ]  # no bars from worker processes
    order = sorted(
        range(len(jobs)),
        key=lambda i: (
            jobs[i][1].velocity_law not in DEPTH_MIXTURE_LAWS,
            -_n_extra(jobs[i][3]),
            jobs[i][6],
        ),
    )
    with cf.ProcessPoolExecutor(
        min(workers, len(jobs)), mp_context=mp.get_context("spawn")
    ) as pool:
        futures = {i: pool.submit(_fit_part, jobs[i]) for i in order}
        done = {
            (jobs[i][1].velocity_law, jobs[i][3], jobs[i][6]): futures[i].result() for i in order
        }
    per_law = {}
    for law, s in one.items():
        fits = []
        for m in s.models:
            fit = done[(law, m, "fit")]
            if "kinematic" in parts:
                evid_kin, wall_kin = done[(law, m, "kinematic")]
                fit = replace(
                    fit,
                    evidence_kinematic=evid_kin,
                    wall_s={**fit.wall_s, "evidence_kinematic": wall_kin},
                )
            fits.append(fit)
        per_law[law] = fits
    return per_law


def _mean_evidence(evids: list) -> EvidenceResult:
    """The evidence of a model under equal prior odds of the laws: the mean of the laws'
    evidences, ``ln Z = logsumexp(ln Z_L) - ln n`` (error: the laws' errors weighted by
    their shares); the rest of the result is the most probable law's."""
    log_z = np.array([e.log_z for e in evids])
    err = np.array([e.log_z_err for e in evids])
    share = softmax(log_z)
    return replace(
        evids[int(np.argmax(log_z))],
        log_z=float(logsumexp(log_z) - np.log(len(evids))),
        log_z_err=float(np.sqrt(np.sum((share * err) ** 2))),
    )


def weigh_velocity_laws(per_law: dict) -> list:
    """Combine fits of the same models with several velocity laws.

    Each model's evidence becomes the laws' mean (equal prior odds per law; the Bayes
    factors between models then compare evidences marginalised over the laws), and its
    posterior tables, likelihood and summary those of the law with the highest evidence
    (``criteria["velocity_law"]``); every law's fit is kept in ``law_fits``, so that the
    M_BH marginal is the exact evidence-weighted mixture over models and laws
    (:func:`marginal_bh_samples`). The laws' own ln Z are kept in ``criteria``
    (``log_z_<law>``).

    Parameters
    ----------
    per_law : dict of str to list of ModelFit
        For each law, the fits of the same models in the same order (with evidences).

    Returns
    -------
    list of ModelFit
    """
    laws = list(per_law)
    out = []
    for fits in zip(*(per_law[law] for law in laws)):
        if any(f.evidence is None for f in fits):
            raise ValueError("weighing velocity laws needs each fit's nested evidence")
        k = int(np.argmax([f.evidence.log_z for f in fits]))
        kin = [f.evidence_kinematic for f in fits]
        criteria = {
            **fits[k].criteria,
            "velocity_law": laws[k],
            **{f"log_z_{law}": float(f.evidence.log_z) for law, f in zip(laws, fits)},
        }
        out.append(
            replace(
                fits[k],
                evidence=_mean_evidence([f.evidence for f in fits]),
                evidence_kinematic=None if None in kin else _mean_evidence(kin),
                criteria=criteria,
                wall_s={key: sum(f.wall_s.get(key, 0.0) for f in fits) for key in fits[k].wall_s},
                law_fits=tuple(fits),
            )
        )
    return out


def nested_chain(evid: EvidenceResult, space: ParameterSpace) -> ChainResult:
    """A :class:`ChainResult` from nested-sampling posterior samples (``posterior = "nested"``).

    The run stopped at its ``dlogz`` criterion, so it counts as converged; tau and
    acceptance are NaN, the MAP is the highest-likelihood point.

    Parameters
    ----------
    evid : EvidenceResult
        The nested-sampling result with its equal-weight samples.
    space : ParameterSpace
        The model's parameters.

    Returns
    -------
    ChainResult
        The samples as a chain.
    """
    ndim = len(space)
    return ChainResult(
        names=list(space.names),
        samples=evid.samples,
        log_like=np.full(evid.samples.shape[0], np.nan),
        tau=np.full(ndim, np.nan),
        steps=0,
        converged=True,
        map_params=evid.best,
        max_log_like=evid.max_log_like,
        acceptance=np.nan,
    )


@dataclass
class Comparison:
    """Model comparison (``ln B > 0`` favours an IMBH) and the verdict.

    Parameters
    ----------
    ln_bayes_factor, ln_bayes_factor_err : float
        ln Z of the best model with an IMBH minus that of the best without, and its error.
    ln_bayes_factor_kinematic, ln_bayes_factor_kinematic_err : float
        The same from the kinematics-only evidences.
    best_model, best_model_with_imbh, best_model_without_imbh : str
        Highest-evidence models overall, with and without an IMBH.
    ln_b_dark_centre : float
        Best model with any dark centre against ``none``.
    ln_b_imbh_vs_extended : float
        ``imbh`` against ``dark``.
    imbh_extended_indistinguishable : bool
        A dark centre is favoured but an IMBH and an extended one are not told apart.
    dark_radius_at_prior_edge : bool
        The ``dark`` model's scale radius (posterior median) lies within
        :data:`DARK_EDGE_DEX` of the lower edge of its prior: its "extended" component is as
        compact as the prior allows, below what the stars resolve.
    delta_ln_likelihood, delta_aic, delta_bic : float
        Best with minus best without an IMBH.
    savage_dickey_ln_b : float
        Savage-Dickey ln B of the ``imbh`` model (NaN when not valid).
    savage_dickey_note : str
        Why it is (not) valid.
    converged : bool
        Whether every model's chains converged.
    verdict : str
        ``imbh``, ``no_imbh``, ``undecided``, ``no_evidence`` or ``not_converged``.
    verdict_text : str
        The verdict in words.
    """

    ln_bayes_factor: float = np.nan
    ln_bayes_factor_err: float = np.nan
    ln_bayes_factor_kinematic: float = np.nan
    ln_bayes_factor_kinematic_err: float = np.nan
    best_model: str = ""
    best_model_with_imbh: str = ""
    best_model_without_imbh: str = ""
    ln_b_dark_centre: float = np.nan
    ln_b_imbh_vs_extended: float = np.nan
    imbh_extended_indistinguishable: bool = False
    dark_radius_at_prior_edge: bool = False
    delta_ln_likelihood: float = np.nan
    delta_aic: float = np.nan
    delta_bic: float = np.nan
    savage_dickey_ln_b: float = np.nan
    savage_dickey_note: str = ""
    converged: bool = True
    verdict: str = ""
    verdict_text: str = ""

    def as_attrs(self) -> dict:
        """Root attributes for the dynamics product."""
        return dict(self.__dict__)


#: how close [dex] to the lower edge of its prior the ``dark`` model's scale radius must
#: sit to count as unresolved (a tenth of the default prior's 2 dex)
DARK_EDGE_DEX = 0.2


def _best(fits, key="evidence"):
    """(fit, ln Z, ln Z err) of the highest evidence among ``fits`` (None if none)."""
    best = None
    for f in fits:
        ev = getattr(f, key)
        if ev is not None and (best is None or ev.log_z > best[1]):
            best = (f, ev.log_z, ev.log_z_err)
    return best


def _ln_z(fits, name, key="evidence"):
    for f in fits:
        if f.name == name and getattr(f, key) is not None:
            return getattr(f, key).log_z
    return np.nan


def marginal_bh_samples(fits, seed: int = 0) -> np.ndarray:
    """M_BH posterior samples marginalised over the IMBH models (evidence-weighted mixture).

    A model whose velocity laws were weighed (``law_fits``) enters as its laws' fits, each
    weighted by its own evidence (equal prior odds of the laws and of the models: the
    weight of model m with law L is proportional to Z_m,L). Without evidences the IMBH
    models are weighted equally.

    Parameters
    ----------
    fits : sequence of ModelFit
        All fitted models (those without a point mass are skipped).
    seed : int
        Seed of the resampling.

    Returns
    -------
    ndarray
        M_BH samples [solMass]; empty without an IMBH model.
    """
    bh_fits = [part for f in fits if f.has_bh for part in (f.law_fits or (f,))]
    if not bh_fits:
        return np.empty(0)
    if all(f.evidence is not None for f in bh_fits):
        lz = np.array([f.evidence.log_z for f in bh_fits])
        w = np.exp(lz - lz.max())
    else:
        w = np.ones(len(bh_fits))
    w = w / w.sum()
    n = min(f.chain.samples.shape[0] for f in bh_fits)
    rng = np.random.default_rng(seed)
    parts = []
    for f, wi in zip(bh_fits, w):
        k = int(round(wi * n))
        col = f.chain.samples[:, f.space.index("bh_mass")]
        if k > 0:
            parts.append(rng.choice(col, size=k, replace=k > col.size))
    return np.concatenate(parts) if parts else np.empty(0)


def compare(fits, bh_mass_max: float, ambiguous_ln_b: float = 1.0) -> Comparison:
    """Compare the fitted models.

    Parameters
    ----------
    fits : list of ModelFit
    bh_mass_max : float
        Upper edge of the M_BH prior (Savage-Dickey).
    ambiguous_ln_b : float
        ``|ln B|`` below which two models count as indistinguishable.
    """
    out = Comparison()
    with_bh = [f for f in fits if f.has_bh]
    without = [f for f in fits if not f.has_bh]
    for key, attr in (("evidence", ""), ("evidence_kinematic", "_kinematic")):
        b1, b0 = _best(with_bh, key), _best(without, key)
        if b1 is not None and b0 is not None:
            setattr(out, f"ln_bayes_factor{attr}", b1[1] - b0[1])
            setattr(out, f"ln_bayes_factor{attr}_err", float(np.hypot(b1[2], b0[2])))
            if key == "evidence":
                out.best_model_with_imbh, out.best_model_without_imbh = b1[0].name, b0[0].name
    best = _best(fits)
    if best is not None:
        out.best_model = best[0].name
        dark_side = [f for f in fits if f.name != "none"]
        bd = _best(dark_side)
        if bd is not None and np.isfinite(_ln_z(fits, "none")):
            out.ln_b_dark_centre = bd[1] - _ln_z(fits, "none")
    out.ln_b_imbh_vs_extended = _ln_z(fits, "imbh") - _ln_z(fits, "dark")
    dark = next((f for f in fits if f.name == "dark"), None)
    if dark is not None and "log_dark_radius" in dark.space.names:
        i = dark.space.index("log_dark_radius")
        median = float(np.median(dark.chain.samples[:, i]))
        out.dark_radius_at_prior_edge = bool(median - dark.space.params[i].lo < DARK_EDGE_DEX)
    ml1 = max((f.criteria["max_log_like"] for f in with_bh), default=np.nan)
    ml0 = max((f.criteria["max_log_like"] for f in without), default=np.nan)
    out.delta_ln_likelihood = ml1 - ml0
    if with_bh and without:
        a1 = min(with_bh, key=lambda f: f.criteria["aic"])
        a0 = min(without, key=lambda f: f.criteria["aic"])
        out.delta_aic = a1.criteria["aic"] - a0.criteria["aic"]
        out.delta_bic = min(f.criteria["bic"] for f in with_bh) - min(
            f.criteria["bic"] for f in without
        )
    imbh = next((f for f in fits if f.name == "imbh"), None)
    if imbh is not None:
        bh = imbh.chain.samples[:, imbh.space.index("bh_mass")]
        out.savage_dickey_ln_b, out.savage_dickey_note = savage_dickey(bh, bh_mass_max)
    unconverged = [f.name for f in fits if not f.chain.converged]
    out.converged = not unconverged
    out.verdict, out.verdict_text = _verdict(out, unconverged, ambiguous_ln_b)
    if unconverged:  # never reported as a result
        out.ln_bayes_factor = out.ln_bayes_factor_kinematic = np.nan
    return out


def evidence_strength(ln_b: float) -> str:
    """Kass & Raftery (1995) words for a Bayes factor: ``|ln B|`` < 1 "not worth more than
    a bare mention", 1-3 "positive", 3-5 "strong", > 5 "very strong".

    Parameters
    ----------
    ln_b : float
        Natural log of the Bayes factor (either sign).

    Returns
    -------
    str
        The word for ``|ln B|``.
    """
    x = abs(float(ln_b))
    if x < 1.0:
        return "not worth more than a bare mention"
    if x < 3.0:
        return "positive"
    return "strong" if x < 5.0 else "very strong"


def _verdict(c: Comparison, unconverged, thr: float):
    """One word and one sentence for the product."""
    if unconverged:
        return "not_converged", (
            f"emcee chains of model(s) {', '.join(unconverged)} did not converge: no result "
            'is reported; set posterior = "nested" (the default; the posterior the '
            "simulation-based calibration covers), or raise max_steps or simplify the model"
        )
    lnb = c.ln_bayes_factor
    if not np.isfinite(lnb):
        return "no_evidence", "no evidence computed (or a side of the comparison is missing)"
    kin = c.ln_bayes_factor_kinematic
    kin_txt = f"; kinematics alone ln B = {kin:.2f}" if np.isfinite(kin) else ""
    parts = []
    if np.isfinite(c.ln_b_imbh_vs_extended) and abs(c.ln_b_imbh_vs_extended) < thr:
        c.imbh_extended_indistinguishable = bool(
            np.isfinite(c.ln_b_dark_centre) and c.ln_b_dark_centre > thr
        )
    if c.imbh_extended_indistinguishable:
        parts.append(
            "a dark central mass is favoured, but the data cannot tell an IMBH from an "
            f"extended dark component (ln Z_imbh - ln Z_dark = {c.ln_b_imbh_vs_extended:.2f})"
        )
    err = f" +- {c.ln_bayes_factor_err:.2f}" if np.isfinite(c.ln_bayes_factor_err) else ""
    if lnb > thr:
        word = "imbh"
        head = (
            f"IMBH favoured, {evidence_strength(lnb)} evidence (ln B = {lnb:.2f}{err}, "
            f"best model {c.best_model})"
        )
    elif lnb < -thr:
        word = "no_imbh"
        head = (
            f"no IMBH favoured, {evidence_strength(lnb)} evidence (ln B = {lnb:.2f}{err}, "
            f"best model {c.best_model})"
        )
    else:
        word = "undecided"
        head = f"the data cannot decide whether there is an IMBH (ln B = {lnb:.2f}{err})"
    if word != "imbh" and c.best_model == "dark" and c.ln_b_dark_centre > thr:
        # "no IMBH" must not read as "no dark centre": say what the data do favour
        text = (
            f"a dark central mass is favoured over none (ln B = {c.ln_b_dark_centre:.2f}), "
            "spread in an extended dark component rather than a point mass"
        )
        if c.dark_radius_at_prior_edge:
            text += (
                ", but that component is as compact as its prior allows (its scale radius "
                "at the prior's lower edge, below what the stars resolve): whether the compact "
                "dark mass is an IMBH rests on the few innermost stars"
            )
        parts.append(text)
    return word, "; ".join([head + kin_txt, *parts])
