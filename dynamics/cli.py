"""The ``mavispm dynamics`` stage: read proper motions, fit, compare, write, plot.

``mavispm dynamics pm.h5 -o fit.h5 --plots plots/ [--truth imbh.h5 --truth-no-imbh no.h5] [--fast]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.catalogue import Catalogue, read_catalogue
from mavispm.core.cliargs import non_negative_int
from mavispm.core.config import from_mapping, to_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.products import TableSpec, read_product, validate_table, write_product
from mavispm.dynamics.fit import compare, fit_model
from mavispm.dynamics.likelihood import StarSample
from mavispm.dynamics.profiles import dispersion_profile, radial_tangential
from mavispm.dynamics.settings import DynamicsSettings

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
    """Build :class:`DynamicsSettings` from a mapping (TOML table), raising ConfigError."""
    return from_mapping(DynamicsSettings, settings or {}, prefix="dynamics", source=source)


def load_stars(path, settings: DynamicsSettings):
    """Read a propermotions product into a :class:`StarSample` plus its distance [kpc].

    See :func:`star_sample`, which does the selection.

    Raises
    ------
    InputError
        Missing columns or distance, negative errors, or no usable stars.
    """
    prod = read_product(path, "propermotions", load_arrays=False)
    t = prod.tables.get("stars")
    if t is None:
        raise InputError("table 'stars' missing", path=path)
    return star_sample(t, prod.attrs, settings, path=path)


def star_sample(table, attrs, settings: DynamicsSettings, path=None):
    """A propermotions ``stars`` table as a :class:`StarSample` plus its distance [kpc].

    Stars with a non-zero flag (unless ``use_flagged``) or a NaN proper motion or
    error are dropped; stars outside the field radius are dropped. Errors become
    ``sqrt((pm_error_scale e)^2 + pm_error_floor^2)``.

    Parameters
    ----------
    table : QTable
        Columns of ``PM_SPEC`` (``x``, ``y``, ``R`` [arcsec], ``pm_r``, ``pm_t`` and
        their errors [mas/yr], optional ``flag``).
    attrs : mapping
        Root attributes; ``distance`` [kpc] unless ``settings.distance`` is set.
    settings : DynamicsSettings
    path : path, optional
        Source file, for messages.

    Returns
    -------
    stars : StarSample
    distance : float
        [kpc]

    Raises
    ------
    InputError
        Missing columns or distance, negative errors, or no usable stars.
    """
    t = table
    if "flag" in t.colnames and not settings.use_flagged:
        # flagged rows are not used: drop them before validating (they may carry
        # NaN in columns the fit needs, e.g. a detection without a truth match)
        t = t[np.asarray(t["flag"]).astype(np.int64) == 0]
    t = validate_table(t, PM_SPEC, path=path, table_name="stars")
    distance = settings.distance
    if distance is None:
        if attrs.get("distance") is None:
            raise InputError(
                "no 'distance' root attribute; set dynamics.distance in the settings", path=path
            )
        distance = u.Quantity(attrs["distance"], u.kpc).to_value(u.kpc)
    if not (np.isfinite(distance) and distance > 0):
        raise InputError(f"distance must be > 0 kpc, got {distance}", path=path)
    cols = {k: np.asarray(t[k].value, dtype=float) for k in PM_SPEC.required if k != "id"}
    for k in ("pm_r_err", "pm_t_err"):
        bad = cols[k] < 0
        if np.any(bad):
            raise InputError(f"{int(bad.sum())} negative errors", path=path, column=k)
    ok = np.all([np.isfinite(cols[k]) for k in ("pm_r", "pm_t", "pm_r_err", "pm_t_err")], axis=0)
    if "flag" in t.colnames and not settings.use_flagged:
        ok &= np.asarray(t["flag"]) == 0
    field = settings.field_radius
    if field is None:
        sel_x, sel_y = np.abs(cols["x"][ok]), np.abs(cols["y"][ok])
        if sel_x.size == 0:
            raise InputError("no unflagged stars with finite proper motions", path=path)
        field = float(min(sel_x.max(), sel_y.max(), cols["R"][ok].max()))
    ok &= cols["R"] <= field
    if ok.sum() < 2:
        raise InputError(f"only {int(ok.sum())} usable stars inside {field:.3g} arcsec", path=path)
    scale, floor = settings.pm_error_scale, settings.pm_error_floor
    stars = StarSample(
        R=np.maximum(cols["R"][ok], settings.min_radius),
        v_r=cols["pm_r"][ok],
        v_t=cols["pm_t"][ok],
        e_r=np.hypot(scale * cols["pm_r_err"][ok], floor),
        e_t=np.hypot(scale * cols["pm_t_err"][ok], floor),
        field_radius=field,
    )
    for name, err in (("pm_r_err", stars.e_r), ("pm_t_err", stars.e_t)):
        if np.any(err == 0):
            raise InputError(
                f"{int(np.count_nonzero(err == 0))} stars with zero error; expected measured "
                "uncertainties > 0 (or set dynamics.pm_error_floor)",
                path=path,
                column=name,
            )
    return stars, float(distance)


def truth_profile(path, field_radius: float, settings: DynamicsSettings, seed: int) -> QTable:
    """Dispersion profile of a truth catalogue (path or Catalogue; first epoch, luminous stars)."""
    cat = path if isinstance(path, Catalogue) else read_catalogue(path)
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

    Attributes
    ----------
    tables : dict of str to QTable
        ``profile`` (binned dispersion profile), ``posterior_imbh``,
        ``posterior_no_imbh`` (samples), ``summary`` (per-parameter credible
        intervals), ``profile_truth_*`` when truth catalogues were given.
    attrs : dict
        Root attributes: model comparison (``ln_bayes_factor``, ``delta_aic`` ...),
        ``bh_mass_median`` ... [solMass], ``bh_detected``, convergence, timings.
    fits : list of ModelFit
        The IMBH and no-IMBH fits (chains, likelihoods).
    """

    tables: dict
    attrs: dict
    fits: list

    @property
    def truth_profiles(self) -> dict:
        """Truth dispersion profiles by model ("imbh", "no_imbh") when truth was given."""
        prefix = "profile_truth_"
        return {k.removeprefix(prefix): t for k, t in self.tables.items() if k.startswith(prefix)}

    @property
    def profile(self) -> QTable:
        """Binned dispersion profile of the stars (radius [arcsec], dispersions [mas/yr])."""
        return self.tables["profile"]

    @property
    def summary(self) -> QTable:
        """Posterior summary per model and parameter."""
        return self.tables["summary"]


def fit_dynamics(
    propermotions,
    settings=None,
    seed: int = 0,
    truth=None,
    truth_no_imbh=None,
    backend_path=None,
    source=None,
) -> DynamicsResult:
    """Dispersion profile, IMBH and no-IMBH Jeans fits and their comparison, in memory.

    Parameters
    ----------
    propermotions : QTable
        The ``stars`` table of a ``propermotions`` product (``meta["distance"]``
        [kpc] unless ``settings.distance`` is set), as :func:`mavispm.proper_motions`
        returns it.
    settings : mapping or DynamicsSettings, optional
        See :class:`~mavispm.dynamics.settings.DynamicsSettings`.
    seed : int
        Seed of the samplers and the bootstrap.
    truth, truth_no_imbh : Catalogue or path, optional
        Truth catalogues whose profiles are added for comparison.
    backend_path : path, optional
        HDF5 file keeping the emcee chains (an interrupted fit resumes).
    source : path, optional
        The product the table was read from, named in error messages.

    Returns
    -------
    DynamicsResult
    """
    if not isinstance(settings, DynamicsSettings):
        settings = validate_settings(settings)
    stars, distance = star_sample(propermotions, propermotions.meta, settings, path=source)
    if stars.R.size < MIN_FIT_STARS:
        raise InputError(
            f"only {stars.R.size} usable stars (finite, unflagged proper motions in the field); "
            f"a dynamical fit needs at least {MIN_FIT_STARS}",
            path=source,
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
    fits = [
        fit_model(stars, settings, distance, with_bh, seed, backend_path=backend_path)
        for with_bh in (True, False)
    ]
    comp = compare(fits[0], fits[1], settings.bh_mass_max)
    bh = fits[0].summary["bh_mass"]
    attrs = {
        **comp.as_attrs(),
        "distance": distance * u.kpc,
        "field_radius": stars.field_radius * u.arcsec,
        "n_stars": int(stars.R.size),
        "tracer": settings.tracer,
        "bh_mass_median": bh["median"] * u.Msun,
        "bh_mass_lo68": bh["lo68"] * u.Msun,
        "bh_mass_hi68": bh["hi68"] * u.Msun,
        "bh_mass_lo95": bh["lo95"] * u.Msun,
        "bh_mass_hi95": bh["hi95"] * u.Msun,
        "bh_mass_upper95": bh["upper95"] * u.Msun,
        # with evidence: detected when ln B > 1 (positive evidence); else the posterior test
        "bh_detected": bool(
            comp.ln_bayes_factor > 1.0 if np.isfinite(comp.ln_bayes_factor) else bh["detected"]
        ),
        "bh_detected_posterior": bool(bh["detected"]),
        "evidence_computed": bool(settings.evidence),
    }
    for fit in fits:
        attrs[f"converged_{fit.name}"] = bool(fit.chain.converged)
        attrs[f"steps_{fit.name}"] = int(fit.chain.steps)
        attrs[f"tau_max_{fit.name}"] = float(np.max(fit.chain.tau))
        attrs[f"acceptance_{fit.name}"] = float(fit.chain.acceptance)
        attrs[f"aic_{fit.name}"] = float(fit.criteria["aic"])
        attrs[f"bic_{fit.name}"] = float(fit.criteria["bic"])
        attrs[f"max_log_like_{fit.name}"] = float(fit.criteria["max_log_like"])
        for part, seconds in fit.wall_s.items():
            attrs[f"time_{part}_{fit.name}"] = float(seconds) * u.s
        if fit.evidence is not None:
            attrs[f"log_z_{fit.name}"] = fit.evidence.log_z
            attrs[f"log_z_err_{fit.name}"] = fit.evidence.log_z_err
    tables = {
        "profile": profile,
        "posterior_imbh": _posterior_table(fits[0]),
        "posterior_no_imbh": _posterior_table(fits[1]),
        "summary": _summary_table(fits),
    }
    for key, tab in truths.items():
        tables[f"profile_truth_{key}"] = tab
    tables = {
        "profile": profile,
        "posterior_imbh": _posterior_table(fits[0]),
        "posterior_no_imbh": _posterior_table(fits[1]),
        "summary": _summary_table(fits),
    }
    for key, tab in truths.items():
        tables[f"profile_truth_{key}"] = tab
    return DynamicsResult(tables=tables, attrs=attrs, fits=fits)


def run_stage(
    propermotions, settings, output, seed, plots_dir=None, truth=None, truth_no_imbh=None
):
    """Run the dynamics stage.

    Parameters
    ----------
    propermotions : path
        A ``propermotions`` product.
    settings : mapping or DynamicsSettings
    output : path
        The ``dynamics`` product to write (atomically). The emcee chains are
        kept next to it in ``<output>.emcee.h5`` so an interrupted fit resumes.
    seed : int
    plots_dir : path, optional
        Write the profile and corner plots here.
    truth, truth_no_imbh : path, optional
        Truth catalogues (IMBH / no-IMBH) whose profiles are drawn for comparison.

    Returns
    -------
    pathlib.Path
    """
    if not isinstance(settings, DynamicsSettings):
        settings = validate_settings(settings)
    output = Path(output)
    prod = read_product(propermotions, "propermotions", load_arrays=False)
    table = prod.tables.get("stars")
    if table is None:
        raise InputError("table 'stars' missing", path=propermotions)
    table.meta = dict(prod.attrs)
    result = fit_dynamics(
        table,
        settings,
        seed,
        truth=truth,
        truth_no_imbh=truth_no_imbh,
        backend_path=output.with_name(output.name + ".emcee.h5"),
        source=propermotions,
    )
    tables, attrs, fits = result.tables, result.attrs, result.fits
    profile, truths = tables["profile"], result.truth_profiles
    attrs["propermotions"] = str(propermotions)
    path = write_product(
        output, "dynamics", tables=tables, attrs=attrs, config=to_mapping(settings), seed=seed
    )
    if plots_dir is not None:
        from mavispm.dynamics.plots import corner_plot, profile_plot

        plots_dir = Path(plots_dir)
        profile_plot(profile, fits, truths, plots_dir / "dispersion_profile.png")
        corner_plot(fits[0], plots_dir / "corner_imbh.png")
        corner_plot(fits[1], plots_dir / "corner_no_imbh.png")
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
    if args.fast:
        settings = settings.fast()
    if args.no_evidence:
        settings = dataclasses.replace(settings, evidence=False)
    out = run_stage(
        args.propermotions,
        settings,
        args.output,
        args.seed,
        plots_dir=args.plots,
        truth=args.truth,
        truth_no_imbh=args.truth_no_imbh,
    )
    from mavispm.core.products import read_product as _read

    a = _read(out, "dynamics", load_arrays=False).attrs
    print(
        json.dumps(
            {
                "output": str(out),
                "ln_bayes_factor": a.get("ln_bayes_factor"),
                "bh_mass_median": float(u.Quantity(a["bh_mass_median"]).value),
                "bh_mass_upper95": float(u.Quantity(a["bh_mass_upper95"]).value),
                "bh_detected": bool(a["bh_detected"]),
            }
        )
    )
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the top-level ``dynamics`` command."""
    p = subparsers.add_parser(
        "dynamics",
        help="fit Jeans models with and without an IMBH to proper motions",
        description="Dispersion profile, emcee fits of IMBH / no-IMBH Jeans models, "
        "dynesty evidence and plots.",
    )
    p.add_argument("propermotions", help="propermotions product (HDF5)")
    p.add_argument("-o", "--output", required=True, help="dynamics product to write")
    p.add_argument("--plots", default=None, help="folder for PNG plots")
    p.add_argument("--truth", default=None, help="truth catalogue with the IMBH")
    p.add_argument("--truth-no-imbh", default=None, help="truth catalogue without IMBH")
    p.add_argument("--config", default=None, help="TOML file with a [dynamics] table")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--fast", action="store_true", help="cheap sampler settings")
    p.add_argument("--no-evidence", action="store_true", help="skip nested sampling")
    p.set_defaults(func=_handler)
    return p
