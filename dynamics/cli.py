"""The ``mavispm dynamics`` stage: read proper motions, fit, compare, write, plot.

``mavispm dynamics pm.h5 -o fit.h5 --plots plots/ [--truth imbh.h5 --truth-no-imbh no.h5] [--fast]``
``mavispm dynamics --from-catalogue cat.h5 [--epoch e0] [--pm-error 0.001] -o fit.h5``
(truth-level fit: the true motions of the luminous stars inside the field radius).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.catalogue import read_catalogue
from mavispm.core.cliargs import non_negative_int
from mavispm.core.config import from_mapping, to_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.knobs import gather_knobs
from mavispm.core.products import TableSpec, read_product, validate_table, write_product
from mavispm.dynamics.fit import compare, fit_models, marginal_bh_samples
from mavispm.dynamics.likelihood import StarSample
from mavispm.dynamics.profiles import dispersion_profile, radial_tangential
from mavispm.dynamics.settings import (
    DYNAMICS_KNOB_HOMES,
    POSTERIORS,
    WEIGHED,
    DynamicsKnobs,
    DynamicsSettings,
)

__all__ = [
    "DynamicsResult",
    "MIN_FIT_STARS",
    "PM_SPEC",
    "fit_dynamics",
    "load_catalogue_stars",
    "load_sample_ids",
    "load_stars",
    "register",
    "run_stage",
    "truth_profile",
    "validate_settings",
]

#: What the dynamics stage needs from a propermotions product.
PM_SPEC = TableSpec(
    required={
        "id": "",
        "x": "arcsec",
        "y": "arcsec",
        "R": "arcsec",
        "pm_r": "mas/yr",
        "pm_t": "mas/yr",
        "pm_r_err": "mas/yr",
        "pm_t_err": "mas/yr",
    },
    optional={"flag": "", "mag": "mag", "pm_x": "mas/yr", "pm_y": "mas/yr"},
    # mag is the truth magnitude (scoring only): NaN for a star without a truth match
    allow_nan=("pm_r", "pm_t", "pm_r_err", "pm_t_err", "mag", "pm_x", "pm_y"),
)


def validate_settings(settings=None, source=None) -> DynamicsSettings:
    """Build :class:`DynamicsSettings` from a mapping (TOML table).

    Parameters
    ----------
    settings : mapping or DynamicsSettings, optional
        The ``[dynamics]`` table (None: defaults); its accuracy and speed knobs
        (:class:`~mavispm.dynamics.settings.DynamicsKnobs`) flat or in a ``knobs``
        table, not both for one knob. A settings object is returned as is.
    source : str, optional
        File named in error messages.

    Returns
    -------
    DynamicsSettings
        The validated settings.

    Raises
    ------
    ConfigError
        Naming the first bad key.
    """
    if isinstance(settings, DynamicsSettings):
        return settings
    known = tuple(f.name for f in dataclasses.fields(DynamicsSettings))
    mapping = gather_knobs(
        settings, DYNAMICS_KNOB_HOMES, prefix="dynamics", source=source, known=known
    )
    knobs = mapping.pop("knobs", {})
    # unknown knob names and wrong types are refused by the knobs object itself
    from_mapping(DynamicsKnobs, knobs, prefix="dynamics.knobs", source=source)
    # the knobs are fields of DynamicsSettings (their flat home)
    return from_mapping(DynamicsSettings, {**mapping, **knobs}, prefix="dynamics", source=source)


def _usable_rows(path, settings: DynamicsSettings):
    """The stars table of a propermotions product, its columns, the usable rows, the
    distance [kpc] and the field radius [arcsec] (see :func:`load_stars`)."""
    prod = read_product(path, "propermotions", load_arrays=False)
    t = prod.tables.get("stars")
    if t is None:
        raise InputError("table 'stars' missing", path=path)
    if "flag" in t.colnames and not settings.use_flagged:
        # rejected rows are not used: drop them before validating (they may carry
        # NaN in columns the fit needs, e.g. a detection without a truth match). The
        # product's ``flag_reject_mask`` names the bits that reject (a clipped reference
        # star, often a fast one near the centre, is kept); without it any bit rejects.
        mask = int(prod.attrs.get("flag_reject_mask", -1))
        t = t[(np.asarray(t["flag"]).astype(np.int64) & mask) == 0]
    t = validate_table(t, PM_SPEC, path=path, table_name="stars")
    distance = settings.distance
    if distance is None:
        if "distance" not in prod.attrs:
            raise InputError(
                "no 'distance' root attribute; set dynamics.distance in the settings", path=path
            )
        distance = u.Quantity(prod.attrs["distance"], u.kpc).to_value(u.kpc)
    if not (np.isfinite(distance) and distance > 0):
        raise InputError(f"distance must be > 0 kpc, got {distance}", path=path)
    cols = {k: np.asarray(t[k].value, dtype=float) for k in PM_SPEC.required if k != "id"}
    for k in ("pm_r_err", "pm_t_err"):
        bad = cols[k] < 0
        if np.any(bad):
            raise InputError(f"{int(bad.sum())} negative errors", path=path, column=k)
    ok = np.all([np.isfinite(cols[k]) for k in ("pm_r", "pm_t", "pm_r_err", "pm_t_err")], axis=0)
    field = settings.field_radius
    if field is None:
        sel_x, sel_y = np.abs(cols["x"][ok]), np.abs(cols["y"][ok])
        if sel_x.size == 0:
            raise InputError("no unflagged stars with finite proper motions", path=path)
        field = float(min(sel_x.max(), sel_y.max(), cols["R"][ok].max()))
    ok &= cols["R"] <= field
    if ok.sum() < 2:
        raise InputError(f"only {int(ok.sum())} usable stars inside {field:.3g} arcsec", path=path)
    return t, cols, ok, float(distance), field


def load_stars(path, settings: DynamicsSettings):
    """Read a propermotions product into a :class:`StarSample` plus its distance [kpc].

    Stars with a flag bit of the product's ``flag_reject_mask`` (any bit if the product
    has none; nothing with ``use_flagged``) or a NaN proper motion or error are dropped;
    stars outside the field radius are dropped. Errors become
    ``sqrt((pm_error_scale e)^2 + pm_error_floor^2)``.

    Parameters
    ----------
    path : str or os.PathLike
        The ``propermotions`` product.
    settings : DynamicsSettings
        ``use_flagged``, the field radius and the error scale and floor.

    Returns
    -------
    stars : StarSample
        The usable stars.
    distance : float
        Distance [kpc].

    Raises
    ------
    InputError
        Missing columns or distance, negative errors, or no usable stars.
    """
    stars, distance, _ = _load_propermotions(path, settings)
    return stars, distance


def _load_propermotions(path, settings: DynamicsSettings):
    """:func:`load_stars` plus the catalogue ids of its stars (:func:`load_sample_ids`),
    from one read of the product."""
    t, cols, ok, distance, field = _usable_rows(path, settings)
    scale, floor = settings.pm_error_scale, settings.pm_error_floor
    stars = StarSample(
        R=np.maximum(cols["R"][ok], settings.min_radius),
        v_r=cols["pm_r"][ok],
        v_t=cols["pm_t"][ok],
        e_r=np.hypot(scale * cols["pm_r_err"][ok], floor),
        e_t=np.hypot(scale * cols["pm_t_err"][ok], floor),
        field_radius=field,
        x=cols["x"][ok],
        y=cols["y"][ok],
    )
    for name, err in (("pm_r_err", stars.e_r), ("pm_t_err", stars.e_t)):
        if np.any(err == 0):
            raise InputError(
                f"{int(np.count_nonzero(err == 0))} stars with zero error; expected measured "
                "uncertainties > 0 (or set dynamics.pm_error_floor)",
                path=path,
                column=name,
            )
    return stars, float(distance), _sample_ids(t, ok)


def load_sample_ids(path, settings: DynamicsSettings) -> np.ndarray:
    """Catalogue ids of the stars :func:`load_stars` fits (for the artificial-star test).

    Parameters
    ----------
    path : str or os.PathLike
        The ``propermotions`` product.
    settings : DynamicsSettings
        As for :func:`load_stars`.

    Returns
    -------
    ndarray of int64
        The ``id_true`` column (blind detection: -1 for a detection without a catalogue
        star) or, without it, ``id`` (forced measurement of catalogue stars).
    """
    t, _, ok, _, _ = _usable_rows(path, settings)
    return _sample_ids(t, ok)


def _sample_ids(t, ok) -> np.ndarray:
    """``id_true`` (else ``id``) of the usable rows ``ok`` of a propermotions table."""
    column = "id_true" if "id_true" in t.colnames else "id"
    return np.asarray(t[column], dtype=np.int64)[ok]


def load_catalogue_stars(path, settings: DynamicsSettings, epoch=None, pm_error: float = 0.001):
    """True motions of a catalogue's luminous stars as a :class:`StarSample` and distance [kpc].

    Parameters
    ----------
    path : path
        A ``catalogue`` product (truth).
    settings : DynamicsSettings
        ``field_radius`` (default: the largest circle inside the epoch's x/y extent),
        ``distance`` (default: the catalogue's) and ``min_radius`` are used.
    epoch : str, optional
        Epoch table name (default: the first).
    pm_error : float
        Error given to every proper-motion component [mas/yr] (> 0); the true
        motions are used unperturbed.

    Raises
    ------
    InputError
        Unknown epoch, no distance, bad error, or fewer than two stars.
    """
    if not (np.isfinite(pm_error) and pm_error > 0):
        raise InputError(f"--pm-error must be > 0 mas/yr, got {pm_error}", path=path)
    cat = read_catalogue(path)
    if epoch is None:
        epoch = next(iter(cat.epochs))
    if epoch not in cat.epochs:
        raise InputError(f"no epoch {epoch!r}; epochs are {sorted(cat.epochs)}", path=path)
    t = cat.epochs[epoch]
    keep = np.ones(len(t), bool)
    if "luminous" in t.colnames:
        keep &= np.asarray(t["luminous"], bool)
    x, y = t["x"].to_value(u.arcsec)[keep], t["y"].to_value(u.arcsec)[keep]
    pmx, pmy = t["pm_x"].to_value(u.mas / u.yr)[keep], t["pm_y"].to_value(u.mas / u.yr)[keep]
    distance = settings.distance
    if distance is None:
        if "distance" not in cat.attrs:
            raise InputError("no 'distance' attribute; set dynamics.distance", path=path)
        distance = u.Quantity(cat.attrs["distance"], u.kpc).to_value(u.kpc)
    R, v_r, v_t = radial_tangential(x, y, pmx, pmy)
    field = settings.field_radius
    if field is None:
        if x.size == 0:
            raise InputError("no luminous stars", path=path)
        field = float(min(np.abs(x).max(), np.abs(y).max()))
    sel = R <= field
    if sel.sum() < 2:
        raise InputError(
            f"only {int(sel.sum())} luminous stars inside {field:.3g} arcsec", path=path
        )
    err = np.full(int(sel.sum()), float(pm_error))
    stars = StarSample(
        R=np.maximum(R[sel], settings.min_radius),
        v_r=v_r[sel],
        v_t=v_t[sel],
        e_r=err,
        e_t=err.copy(),
        field_radius=field,
        x=x[sel],
        y=y[sel],
    )
    return stars, float(distance)


def truth_profile(path, field_radius: float, settings: DynamicsSettings, seed: int) -> QTable:
    """Dispersion profile of a truth catalogue (first epoch, luminous stars, no errors).

    Parameters
    ----------
    path : str or os.PathLike
        The ``catalogue`` product.
    field_radius : float
        Stars beyond this projected radius are left out [arcsec].
    settings : DynamicsSettings
        ``bin_size`` and ``n_bootstrap`` of the profile.
    seed : int
        Seed of the bootstrap.

    Returns
    -------
    astropy.table.QTable
        The binned radial and tangential dispersion profile [mas/yr].
    """
    cat = read_catalogue(path)
    t = next(iter(cat.epochs.values()))
    keep = np.ones(len(t), bool)
    if "luminous" in t.colnames:
        keep &= np.asarray(t["luminous"], bool)
    x, y = t["x"].to_value(u.arcsec)[keep], t["y"].to_value(u.arcsec)[keep]
    pmx, pmy = t["pm_x"].to_value(u.mas / u.yr)[keep], t["pm_y"].to_value(u.mas / u.yr)[keep]
    R, v_r, v_t = radial_tangential(x, y, pmx, pmy)
    sel = R <= field_radius
    zero = np.zeros(int(sel.sum()))
    pm = u.mas / u.yr
    dist = cat.attrs.get("distance")
    return dispersion_profile(
        R[sel] * u.arcsec,
        v_r[sel] * pm,
        v_t[sel] * pm,
        zero * pm,
        zero * pm,
        bin_size=settings.bin_size,
        n_bootstrap=settings.n_bootstrap,
        distance=None if dist is None else u.Quantity(dist, u.kpc),
        seed=seed,
    )


def _summary_table(fits) -> QTable:
    rows = []
    for fit in fits:
        for i, name in enumerate(fit.chain.names):
            s = fit.summary[name]
            rows.append(
                {
                    "model": fit.name,
                    "parameter": name,
                    "median": s["median"],
                    "lo68": s["lo68"],
                    "hi68": s["hi68"],
                    "lo95": s["lo95"],
                    "hi95": s["hi95"],
                    "upper95": s["upper95"],
                    "tau": fit.chain.tau[i],
                    "map": fit.chain.map_params[i],
                }
            )
    return QTable(rows=rows)


def _posterior_table(fit) -> QTable:
    t = QTable()
    for i, name in enumerate(fit.chain.names):
        t[name] = fit.chain.samples[:, i]
    t["log_like"] = fit.chain.log_like
    return t


#: Fewest usable stars a dynamical fit accepts (below, the "mass" is the prior's).
MIN_FIT_STARS = 10


@dataclasses.dataclass
class DynamicsResult:
    """What :func:`fit_dynamics` returns: the ``dynamics`` product in memory.

    Parameters
    ----------
    tables : dict of str to QTable
        ``profile``, ``summary``, ``posterior_<model>``, ... (docs/formats.md).
    attrs : dict
        Root attributes: model comparison, ``bh_mass_median`` ... [solMass], convergence.
    """

    tables: dict
    attrs: dict

    @property
    def profile(self) -> QTable:
        """Binned dispersion profile (radius [arcsec], dispersions [mas/yr])."""
        return self.tables["profile"]

    @property
    def summary(self) -> QTable:
        """Posterior summary per model and parameter."""
        return self.tables["summary"]


def fit_dynamics(propermotions: QTable, settings=None, seed: int = 0, **kwargs) -> DynamicsResult:
    """The dynamics stage on a proper-motion table in memory.

    The table (``meta`` = the product's root attributes, as
    :func:`mavispm.proper_motions` returns it) goes through :func:`run_stage` in a
    temporary folder, so the result is exactly the stage's product.

    Parameters
    ----------
    propermotions : QTable
        The ``stars`` table of a ``propermotions`` product; ``meta["distance"]``
        [kpc] unless ``settings.distance`` is set.
    settings : mapping or DynamicsSettings, optional
        See :class:`~mavispm.dynamics.settings.DynamicsSettings`.
    seed : int
        Seed of the samplers and the bootstrap.
    **kwargs
        Passed to :func:`run_stage` (``truth``, ``truth_no_imbh``, ...).

    Returns
    -------
    DynamicsResult
    """
    import tempfile

    table = propermotions.copy(copy_data=False)
    attrs = dict(table.meta)
    table.meta.clear()
    with tempfile.TemporaryDirectory() as tmp:
        pm = write_product(
            Path(tmp) / "pm.h5", "propermotions", tables={"stars": table}, attrs=attrs
        )
        out = run_stage(pm, settings, Path(tmp) / "dynamics.h5", seed, **kwargs)
        prod = read_product(out, "dynamics")
    return DynamicsResult(tables=prod.tables, attrs=prod.attrs)


def _artificial_star_completeness(sample_ids, artificial_stars, settings, field_radius):
    """Settings with the completeness measured from the artificial-star catalogue, and the
    product tables ``completeness`` (against radius) and ``completeness_mag`` (radius and
    magnitude); see :mod:`mavispm.dynamics.completeness`."""
    from mavispm.dynamics.completeness import (
        completeness_by_radius,
        completeness_by_radius_and_magnitude,
        completeness_points,
    )

    if artificial_stars is None:
        raise ConfigError(
            "completeness_source = 'artificial_stars' needs the catalogue of the injected "
            "stars (--artificial-stars CATALOGUE.h5; a workflow passes its own catalogue)",
            key="dynamics.completeness_source",
        )
    cat = read_catalogue(artificial_stars)
    t = next(iter(cat.epochs.values()))
    keep = np.asarray(t["luminous"], bool) if "luminous" in t.colnames else np.ones(len(t), bool)
    ids = np.asarray(t["id"], dtype=np.int64)[keep]
    x, y = t["x"].to_value(u.arcsec)[keep], t["y"].to_value(u.arcsec)[keep]
    mag = t["mag"].to_value(u.mag)[keep]
    found = np.isin(ids, sample_ids)
    if not np.any(found):
        raise InputError(
            "no fitted star is in the artificial-star catalogue (ids do not match)",
            path=artificial_stars,
            column="id",
        )
    limit = settings.completeness_mag_limit
    if limit is None:
        limit = float(np.max(mag[found]))
    radius = np.hypot(x, y)
    by_r = completeness_by_radius(radius, mag, found, field_radius, limit)
    edges = np.concatenate(
        [by_r["radius_lo"].to_value(u.arcsec), by_r["radius_hi"].to_value(u.arcsec)[-1:]]
    )
    mag_edges = np.arange(np.floor(np.min(mag[found])), np.floor(limit) + 1.5, 1.0)
    by_rm = completeness_by_radius_and_magnitude(radius, mag, found, field_radius, mag_edges, edges)
    r_pts, c_pts = completeness_points(by_r)
    fitted = dataclasses.replace(
        settings, completeness_source="table", completeness_radius=r_pts, completeness=c_pts
    )
    return fitted, {"completeness": by_r, "completeness_mag": by_rm}


def _prior_from_surface_density(path, settings):
    """Settings with the scale-radius prior (and King62 concentration) fitted to the
    surface-density profile at ``path``, and the product attributes recording it."""
    from mavispm.dynamics.surface_density import fit_surface_density, read_surface_density

    if settings.log_scale_radius_prior is not None:
        raise ConfigError(
            "give either log_scale_radius_prior or a surface-density profile, not both",
            key="dynamics.log_scale_radius_prior",
        )
    fit = fit_surface_density(
        *read_surface_density(path), tracer=settings.tracer, dehnen_gamma=settings.dehnen_gamma
    )
    lo, hi = settings.log_scale_radius_range
    if not lo < fit.log_scale_radius < hi:
        raise ConfigError(
            f"the profile's log10 scale radius {fit.log_scale_radius:.3f} lies outside "
            f"log_scale_radius_range [{lo}, {hi}]",
            key="dynamics.log_scale_radius_range",
        )
    changes = {"log_scale_radius_prior": fit.prior}
    attrs = {
        "surface_density_profile": str(path),
        "surface_density_log_scale_radius": fit.log_scale_radius,
        "surface_density_log_scale_radius_err": fit.log_scale_radius_err,
        "surface_density_chi2": fit.chi2,
        "surface_density_dof": fit.dof,
    }
    if settings.tracer == "king62":
        changes["king_concentration"] = fit.concentration
        attrs["surface_density_concentration"] = fit.concentration
        attrs["surface_density_concentration_err"] = fit.concentration_err
    return dataclasses.replace(settings, **changes), attrs


def run_stage(
    propermotions,
    settings,
    output,
    seed,
    plots_dir=None,
    truth=None,
    truth_no_imbh=None,
    from_catalogue=None,
    epoch=None,
    pm_error: float = 0.001,
    artificial_stars=None,
    surface_density=None,
):
    """Run the dynamics stage.

    Parameters
    ----------
    propermotions : path or None
        A ``propermotions`` product (None with ``from_catalogue``).
    settings : mapping or DynamicsSettings
    output : path
        The ``dynamics`` product to write (atomically). The emcee chains are
        kept next to it in ``<output>.emcee-<model>.h5`` so an interrupted fit resumes.
    seed : int
    plots_dir : path, optional
        Write the profile and corner plots here.
    truth, truth_no_imbh : path, optional
        Truth catalogues (IMBH / no-IMBH) whose profiles are drawn for comparison.
    from_catalogue : path, optional
        Fit the true motions of this catalogue's luminous stars instead.
    epoch : str, optional
        Catalogue epoch (default: the first).
    pm_error : float
        Proper-motion error given to the catalogue's stars [mas/yr].
    artificial_stars : path, optional
        The catalogue product of the stars injected into the frames (in a simulation,
        the run's own catalogue): with ``completeness_source = "artificial_stars"`` the
        star-count term's completeness is measured from it.
    surface_density : path, optional
        An observed surface-density profile (``radius``, ``density``, ``density_err``):
        the tracer law fitted to it gives the ``log_scale_radius`` prior (and the King62
        concentration); see :mod:`mavispm.dynamics.surface_density`.

    Returns
    -------
    pathlib.Path
    """
    if not isinstance(settings, DynamicsSettings):
        settings = validate_settings(settings)
    requested = settings
    output = Path(output)
    completeness_tables = {}
    profile_attrs = {}
    if surface_density is not None:
        settings, profile_attrs = _prior_from_surface_density(surface_density, settings)
    if from_catalogue is not None:
        stars, distance = load_catalogue_stars(from_catalogue, settings, epoch, pm_error)
        source = {"catalogue": str(from_catalogue), "pm_error": pm_error * u.mas / u.yr}
        if settings.completeness_source == "artificial_stars":  # every star is in the sample
            settings = dataclasses.replace(settings, completeness_source="table")
    else:
        stars, distance, sample_ids = _load_propermotions(propermotions, settings)
        source = {"propermotions": str(propermotions)}
        if settings.completeness_source == "artificial_stars":
            settings, completeness_tables = _artificial_star_completeness(
                sample_ids, artificial_stars, settings, stars.field_radius
            )
    if stars.R.size < MIN_FIT_STARS:
        raise InputError(
            f"only {stars.R.size} usable stars (finite, unflagged proper motions in the field); "
            f"a dynamical fit needs at least {MIN_FIT_STARS}",
            path=propermotions if from_catalogue is None else from_catalogue,
        )
    pm = u.mas / u.yr
    profile = dispersion_profile(
        stars.R * u.arcsec,
        stars.v_r * pm,
        stars.v_t * pm,
        stars.e_r * pm,
        stars.e_t * pm,
        bin_size=settings.bin_size,
        n_bootstrap=settings.n_bootstrap,
        distance=distance * u.kpc,
        seed=seed,
    )
    truths = {}
    for key, path in (("imbh", truth), ("no_imbh", truth_no_imbh)):
        if path is not None:
            truths[key] = truth_profile(path, stars.field_radius, settings, seed)
    fits = fit_models(stars, settings, distance, seed, output.with_name(output.name + ".emcee"))
    comp = compare(fits, settings.bh_mass_max, settings.ambiguous_ln_b)
    weighed = settings.laws if settings.velocity_law == WEIGHED else ()
    attrs = {
        **comp.as_attrs(),
        "completeness_source": requested.completeness_source,
        **profile_attrs,
        "distance": distance * u.kpc,
        "field_radius": stars.field_radius * u.arcsec,
        "n_stars": int(stars.R.size),
        "tracer": settings.tracer,
        "models": ",".join(f.name for f in fits),
        "evidence_computed": bool(settings.evidence),
        "velocity_law": settings.velocity_law,
        "compare_velocity_laws": ",".join(weighed),
        **source,
    }
    if "free_kurtosis" in settings.laws and fits:
        # where kappa_inner / kappa_outer of the summary table hold (radial profile)
        lo, hi = np.exp(fits[0].likelihood.kappa_anchors)
        attrs["kappa_anchor_radii"] = np.array([lo, hi]) * u.arcsec
    bh = marginal_bh_samples(fits, seed)
    if bh.size:
        q = np.percentile(bh, [2.5, 16, 50, 84, 97.5, 95])
        if not comp.converged:  # never reported as a result
            q = np.full(6, np.nan)
        for k, key in enumerate(("lo95", "lo68", "median", "hi68", "hi95", "upper95")):
            attrs[f"bh_mass_{key}"] = q[k] * u.Msun
        detected_post = bool(q[0] > 0.1 * q[2])
        attrs["bh_detected"] = bool(
            comp.ln_bayes_factor > settings.ambiguous_ln_b
            if np.isfinite(comp.ln_bayes_factor)
            else detected_post
        )
        attrs["bh_detected_posterior"] = detected_post
    for fit in fits:
        n = fit.name
        attrs[f"converged_{n}"] = bool(fit.chain.converged)
        if fit.chain.steps > 0:  # an emcee chain (the nested posterior has no steps nor tau)
            attrs[f"steps_{n}"] = int(fit.chain.steps)
            attrs[f"tau_max_{n}"] = float(np.max(fit.chain.tau))
            attrs[f"acceptance_{n}"] = float(fit.chain.acceptance)
        attrs[f"posterior_samples_{n}"] = int(len(fit.chain.samples))
        attrs[f"aic_{n}"] = float(fit.criteria["aic"])
        attrs[f"bic_{n}"] = float(fit.criteria["bic"])
        attrs[f"max_log_like_{n}"] = float(fit.criteria["max_log_like"])
        if "velocity_law" in fit.criteria:  # compare_velocity_laws: the law kept, each ln Z
            attrs[f"velocity_law_{n}"] = fit.criteria["velocity_law"]
            for law in settings.compare_velocity_laws:
                attrs[f"log_z_{law}_{n}"] = float(fit.criteria[f"log_z_{law}"])
        for part, seconds in fit.wall_s.items():
            attrs[f"time_{part}_{n}"] = float(seconds) * u.s
        if fit.evidence is not None:
            attrs[f"log_z_{n}"] = fit.evidence.log_z
            attrs[f"log_z_err_{n}"] = fit.evidence.log_z_err
            attrs[f"evidence_method_{n}"] = fit.evidence.method
            attrs[f"pareto_k_{n}"] = float(fit.evidence.pareto_k)
        if fit.evidence_kinematic is not None:
            attrs[f"log_z_kinematic_{n}"] = fit.evidence_kinematic.log_z
            attrs[f"log_z_kinematic_err_{n}"] = fit.evidence_kinematic.log_z_err
    tables = {"profile": profile, "summary": _summary_table(fits), **completeness_tables}
    for fit in fits:
        tables[f"posterior_{fit.name}"] = _posterior_table(fit)
    if bh.size:
        tables["bh_mass_marginal"] = QTable({"bh_mass": bh * u.Msun})
    for key, tab in truths.items():
        tables[f"profile_truth_{key}"] = tab
    fast = None
    if settings.fast_stars is not None:
        from mavispm.dynamics.fast_stars import run_on_fits

        fast = run_on_fits(
            propermotions, settings, fits, distance, stars.field_radius, seed, stars=stars
        )
        tables["fast_stars"] = fast.table
        attrs.update(fast.attrs)
    path = write_product(
        output, "dynamics", tables=tables, attrs=attrs, config=to_mapping(requested), seed=seed
    )
    if plots_dir is not None:
        from mavispm.dynamics.plots import corner_plot, profile_plot

        plots_dir = Path(plots_dir)
        profile_plot(profile, fits, truths, plots_dir / "dispersion_profile.png")
        for fit in fits:
            corner_plot(fit, plots_dir / f"corner_{fit.name}.png")
        if fast is not None and fast.possible:
            from mavispm.dynamics.plots import fast_star_plot

            fast_star_plot(fast, plots_dir / "fast_stars.png")
    return path


def _handler(args) -> int:
    settings = {}
    if args.config is not None:
        import tomllib

        try:
            with open(args.config, "rb") as fh:
                settings = tomllib.load(fh).get("dynamics", {})
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(
                f"cannot read settings ({exc}); expected a TOML file with a [dynamics] table",
                key="--config",
                source=args.config,
            ) from None
    settings = validate_settings(settings, source=args.config)
    if settings.progress and not sys.stderr.isatty():  # bars on a terminal only
        settings = dataclasses.replace(settings, progress=False)
    if args.fast:
        settings = settings.fast()
    if args.posterior is not None:
        settings = dataclasses.replace(settings, posterior=args.posterior)
    if args.no_evidence:
        if args.posterior == "nested":
            raise InputError(
                "--no-evidence skips the nested sampling that --posterior nested needs"
            )
        if settings.posterior == "nested":
            print(
                "mavispm dynamics: --no-evidence: posterior from emcee (the nested posterior "
                "needs the nested-sampling run); its chains may not converge on the full model",
                file=sys.stderr,
            )
        if settings.velocity_law == WEIGHED:
            print(
                f"mavispm dynamics: --no-evidence: velocity law {settings.laws[0]} alone "
                "(weighing the laws needs their evidences)",
                file=sys.stderr,
            )
            settings = dataclasses.replace(
                settings, velocity_law=settings.laws[0], compare_velocity_laws=()
            )
        settings = dataclasses.replace(settings, evidence=False, posterior="emcee")
    if args.fast_stars and settings.fast_stars is None:
        from mavispm.dynamics.fast_stars import FastStarSettings

        settings = dataclasses.replace(settings, fast_stars=FastStarSettings())
    if (args.propermotions is None) == (args.from_catalogue is None):
        raise InputError("give either a propermotions product or --from-catalogue CATALOGUE")
    if args.from_catalogue is None and (args.epoch is not None or args.pm_error is not None):
        raise InputError("--epoch and --pm-error go with --from-catalogue")
    out = run_stage(
        args.propermotions,
        settings,
        args.output,
        args.seed,
        plots_dir=args.plots,
        truth=args.truth,
        truth_no_imbh=args.truth_no_imbh,
        from_catalogue=args.from_catalogue,
        epoch=args.epoch,
        pm_error=0.001 if args.pm_error is None else args.pm_error,
        artificial_stars=args.artificial_stars,
        surface_density=args.surface_density,
    )
    from mavispm.core.products import read_product as _read

    a = _read(out, "dynamics", load_arrays=False).attrs
    if a.get("verdict") == "not_converged":  # the product withholds the numbers: say why
        print(f"mavispm dynamics: {a.get('verdict_text')}", file=sys.stderr)
    print(
        json.dumps(
            {
                "output": str(out),
                "ln_bayes_factor": a.get("ln_bayes_factor"),
                "ln_bayes_factor_kinematic": a.get("ln_bayes_factor_kinematic"),
                "bh_mass_median": float(u.Quantity(a.get("bh_mass_median", np.nan)).value),
                "bh_mass_upper95": float(u.Quantity(a.get("bh_mass_upper95", np.nan)).value),
                "bh_detected": bool(a.get("bh_detected", False)),
                "verdict": a.get("verdict"),
            }
        )
    )
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the top-level ``dynamics`` command.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``mavispm`` sub-parsers.

    Returns
    -------
    argparse.ArgumentParser
        The new sub-parser.
    """
    p = subparsers.add_parser(
        "dynamics",
        help="fit Jeans mass models (no dark centre, IMBH, extended dark, both) to proper motions",
        description="Dispersion profile, fits of the Jeans mass models (posterior and "
        "evidences, full and kinematics-only, from dynesty; emcee with posterior = "
        '"emcee"), model comparison and plots.',
    )
    p.add_argument("propermotions", nargs="?", default=None, help="propermotions product (HDF5)")
    p.add_argument(
        "--from-catalogue",
        default=None,
        help="fit the true motions of this catalogue's luminous stars (truth-level fit)",
    )
    p.add_argument("--epoch", default=None, help="catalogue epoch (default: the first)")
    p.add_argument(
        "--pm-error",
        type=float,
        default=None,
        help="proper-motion error of the catalogue's stars [mas/yr] (default 0.001)",
    )
    p.add_argument("-o", "--output", required=True, help="dynamics product to write")
    p.add_argument("--plots", default=None, help="folder for PNG plots")
    p.add_argument("--truth", default=None, help="truth catalogue with the IMBH")
    p.add_argument("--truth-no-imbh", default=None, help="truth catalogue without IMBH")
    p.add_argument(
        "--artificial-stars",
        default=None,
        metavar="CATALOGUE",
        help="catalogue of the stars injected into the frames (the run's own catalogue): "
        "the completeness of completeness_source = 'artificial_stars'",
    )
    p.add_argument(
        "--surface-density",
        default=None,
        metavar="PROFILE",
        help="observed surface-density profile (radius, density, density_err): the tracer "
        "law fitted to it sets the log_scale_radius prior (and the King62 concentration)",
    )
    p.add_argument("--config", default=None, help="TOML file with a [dynamics] table")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--fast", action="store_true", help="cheap sampler settings")
    p.add_argument(
        "--posterior",
        choices=POSTERIORS,
        default=None,
        help="posterior from the nested-sampling run (the default) or from emcee "
        "(overrides the settings' posterior)",
    )
    p.add_argument(
        "--no-evidence",
        action="store_true",
        help="skip nested sampling: no ln B, the posterior from emcee",
    )
    p.add_argument(
        "--fast-stars",
        action="store_true",
        help="also run the fast-star test (stars above the no-IMBH escape velocity)",
    )
    p.set_defaults(func=_handler)
    return p
