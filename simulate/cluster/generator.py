"""Equilibrium cluster catalogues: model set-up, field-only sampling, epochs.

Public API
----------
:func:`resolve_model_params`
    Settings (+ preset) to the model's true parameters (a JSON-able dict,
    stored in the catalogue as the root attribute ``model_params``).
:func:`build_cluster_model` / :func:`model_from_params`
    The mass model and its isotropic DF.
:func:`sample_stars`
    Stars in the field and margin at the reference epoch (cluster frame truth).
:func:`simulate_catalogue`
    Epoch tables and root attributes of a catalogue product (no file written).

Random streams: ``SeedSequence(seed)`` is split into one child per star group
(luminous field, luminous margin, dark field, dark margin), each split into
population / position / velocity streams. Catalogues that differ only in the
IMBH (and cusp) therefore share their star count, IDs, masses and magnitudes
exactly, and feed the same uniform numbers to the position and velocity
inverse-CDF maps: their differences are dynamical only.
"""

from __future__ import annotations

from dataclasses import dataclass

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.simulate.cluster import population as pop
from mavispm.simulate.cluster.eddington import (
    DistributionFunction,
    check_isotropic_df_exists,
    eddington_df,
)
from mavispm.simulate.cluster.field_sampler import (
    FieldSampler,
    SamplerResolution,
    build_field_sampler,
)
from mavispm.simulate.cluster.presets import get_preset
from mavispm.simulate.cluster.profiles import (
    MassModel,
    TracerProfile,
    build_mass_model,
    central_dispersion_cored,
    influence_radius,
    projected_radii,
)
from mavispm.simulate.cluster.projection import (
    arcsec_to_pc,
    in_square,
    pc_to_arcsec,
    propagate,
    sky_to_field,
    velocity_to_pm,
)
from mavispm.simulate.cluster.settings import ClusterSettings

#: Inner cusp slope used by default when an IMBH is present (N-body models).
DEFAULT_CUSP_GAMMA = 1.55
#: Star groups in stream order: (region, luminous).
GROUPS = (("field", True), ("frame", True), ("field", False), ("frame", False))
#: Largest ratio of stars drawn to stars kept for an offset field.
MAX_OFFSET_OVERSAMPLING = 200.0


@dataclass(frozen=True)
class ClusterModel:
    """A mass model with its isotropic DF and its parameters.

    Attributes
    ----------
    mass : MassModel
    df : DistributionFunction
    params : dict
        See :func:`resolve_model_params`.
    """

    mass: MassModel
    df: DistributionFunction
    params: dict


def resolve_model_params(settings: ClusterSettings) -> dict:
    """The model's true parameters from the settings and their preset.

    Returns
    -------
    dict
        ``tracer``, ``king_w0``, ``stellar_mass`` [solMass], ``scale_radius`` [pc],
        ``bh_mass`` [solMass], ``cusp_gamma``, ``cusp_radius`` [pc],
        ``distance`` [kpc], ``extinction_v`` [mag], ``truncation_radius`` [pc],
        ``core_radius``, ``half_mass_radius_projected`` [pc] (of the cored tracer,
        without cusp), ``central_dispersion_cored`` [km/s] (1-D, no IMBH),
        ``ra_center``, ``dec_center`` [deg], ``preset``.

    Raises
    ------
    ValueError
        Unknown preset, or a cored tracer around an IMBH (An & Evans 2006).
    """
    observed = observed_params(settings)
    preset = get_preset(settings.preset)
    tracer_kind = settings.tracer or preset.tracer
    w0 = settings.king_w0 if settings.king_w0 is not None else preset.king_w0
    distance = observed["distance"]
    mass = settings.stellar_mass if settings.stellar_mass is not None else preset.stellar_mass
    bh = float(settings.imbh_mass)
    gamma = settings.cusp_gamma
    if gamma is None:
        gamma = DEFAULT_CUSP_GAMMA if bh > 0 else 0.0
    check_isotropic_df_exists(gamma, bh)
    unit_core, unit_half = projected_radii(TracerProfile(tracer_kind, 1.0, w0))
    if settings.scale_radius is not None:
        scale = float(settings.scale_radius)
    else:
        r_h = settings.half_light_radius or preset.half_light_radius
        scale = float(arcsec_to_pc(r_h * 60.0, distance)) / unit_half
    cored = TracerProfile(tracer_kind, scale, w0)
    cusp_radius = 0.0
    if gamma > 0:
        cusp_radius = settings.cusp_radius
        if cusp_radius is None:
            ref_bh = bh if bh > 0 else 0.01 * mass
            cusp_radius = influence_radius(cored, mass, ref_bh)
    tracer = TracerProfile(tracer_kind, scale, w0, gamma, cusp_radius)
    return {
        **observed,
        "tracer": tracer_kind,
        "king_w0": w0,
        "stellar_mass": mass,
        "scale_radius": scale,
        "bh_mass": bh,
        "cusp_gamma": gamma,
        "cusp_radius": cusp_radius,
        "truncation_radius": tracer.truncation_radius,
        "core_radius": unit_core * scale,
        "half_mass_radius_projected": unit_half * scale,
        "central_dispersion_cored": central_dispersion_cored(cored, mass),
        "units": {
            **observed["units"],
            "stellar_mass": "solMass",
            "scale_radius": "pc",
            "cusp_radius": "pc",
            "truncation_radius": "pc",
            "core_radius": "pc",
            "half_mass_radius_projected": "pc",
            "central_dispersion_cored": "km/s",
        },
    }


def observed_params(settings: ClusterSettings) -> dict:
    """Preset-or-setting values that do not depend on the dynamical model.

    Returns
    -------
    dict
        ``preset``, ``bh_mass`` [solMass], ``distance`` [kpc], ``extinction_v`` [mag],
        ``ra_center``, ``dec_center`` [deg] and their ``units``.
    """
    preset = get_preset(settings.preset)

    def pick(key):
        value = getattr(settings, key)
        return getattr(preset, key) if value is None else value

    return {
        "preset": preset.name,
        "bh_mass": float(settings.imbh_mass),
        **{k: pick(k) for k in ("distance", "extinction_v", "ra_center", "dec_center")},
        "units": {
            "bh_mass": "solMass",
            "distance": "kpc",
            "extinction_v": "mag",
            "ra_center": "deg",
            "dec_center": "deg",
        },
    }


def model_from_params(params: dict, n_energy: int = 800) -> ClusterModel:
    """Rebuild the mass model and DF from a ``model_params`` dict.

    Parameters
    ----------
    params : dict
        As returned by :func:`resolve_model_params` (or read from a catalogue's
        ``model_params`` attribute, a JSON string, after ``json.loads``).
    n_energy : int
        Energy grid size of the DF table.
    """
    tracer = TracerProfile(
        params["tracer"],
        params["scale_radius"],
        params["king_w0"],
        params["cusp_gamma"],
        params["cusp_radius"],
    )
    mass = build_mass_model(tracer, params["stellar_mass"], params["bh_mass"])
    return ClusterModel(mass, eddington_df(mass, n_energy=n_energy), dict(params))


def build_cluster_model(settings: ClusterSettings) -> ClusterModel:
    """Model parameters, mass model and DF for ``settings``."""
    return model_from_params(resolve_model_params(settings), settings.resolution.n_energy)


def _streams(seed: int):
    """Per-group (population, position, velocity) generators."""
    children = np.random.SeedSequence(seed).spawn(len(GROUPS))
    return [[np.random.default_rng(s) for s in child.spawn(3)] for child in children]


def _group_counts(settings, sampler: FieldSampler, n_field: int) -> list[int]:
    mf = _mass_function(settings)
    frame = sampler.region_mass["frame"] / max(sampler.region_mass["field"], 1e-300)
    n_lum = [n_field, int(round(n_field * frame))]
    ratio = pop.remnant_ratio(mf) if settings.include_remnants else 0.0
    return n_lum + [int(round(n * ratio)) for n in n_lum]


def _mass_function(settings) -> pop.MassFunction:
    return pop.MassFunction(
        settings.mass_min,
        settings.mass_break,
        settings.mass_max,
        settings.alpha_low,
        settings.alpha_high,
    )


def _field_geometry(settings, distance):
    """Half-size of the sampled square and its margin [pc] (cluster-centred)."""
    half = 0.5 * settings.field_size
    offset = max(abs(settings.offset_x), abs(settings.offset_y))
    if offset == 0:
        return arcsec_to_pc(half, distance), arcsec_to_pc(settings.margin, distance)
    # offset field: sample a cluster-centred square enclosing the rotated field + margin
    big = offset + (half + settings.margin) * np.sqrt(2.0)
    return arcsec_to_pc(big, distance), 0.0


def _field_sampler(settings, model: ClusterModel) -> FieldSampler:
    half, margin = _field_geometry(settings, model.params["distance"])
    return build_field_sampler(model.mass, model.df, half, margin, settings.resolution)


def _offset_field_fraction(settings, sampler: FieldSampler, distance) -> float:
    """Expected fraction of the big square's stars that fall in the offset field."""
    half = 0.5 * settings.field_size
    g = np.linspace(-half, half, 241)
    xf, yf = np.meshgrid(g, g)
    c, s = np.cos(np.radians(settings.rotation)), np.sin(np.radians(settings.rotation))
    xs = c * xf - s * yf + settings.offset_x
    ys = s * xf + c * yf + settings.offset_y
    R = arcsec_to_pc(np.hypot(xs, ys), distance)
    rows, sigma = sampler.sigma_rows
    sig = np.exp(np.interp(np.log(np.maximum(R, rows[0])), np.log(rows), np.log(sigma)))
    sig[R >= rows[-1]] = 0.0
    area = arcsec_to_pc(settings.field_size, distance) ** 2
    mass = np.trapezoid(np.trapezoid(sig, g, axis=1), g) / settings.field_size**2 * area
    return mass / max(sampler.region_mass["field"], 1e-300)


def sample_stars(settings: ClusterSettings, seed: int, model: ClusterModel | None = None):
    """Draw the stars in the field and its margin at the reference epoch.

    Parameters
    ----------
    settings : ClusterSettings
    seed : int
    model : ClusterModel, optional
        Prebuilt model (default: :func:`build_cluster_model`).

    Returns
    -------
    stars : dict of ndarray
        Cluster-frame truth: ``x, y, z, r3d`` [pc], ``vx, vy, vz`` [km/s] (sky axes,
        z along the line of sight away from the observer), ``mass`` [solMass],
        ``mag`` [mag], ``luminous`` (bool), ``id`` (int64), ``region``
        (0 field, 1 margin).
    model : ClusterModel
    """
    model = model or build_cluster_model(settings)
    distance = model.params["distance"]
    sampler = _field_sampler(settings, model)
    offset_mode = bool(settings.offset_x or settings.offset_y)  # see _field_geometry
    n_field = settings.n_stars
    if sampler.region_mass["field"] <= 0 and settings.n_stars > 0:
        raise ValueError("the field holds no cluster stars (is it beyond the tidal radius?)")
    if offset_mode:
        fraction = _offset_field_fraction(settings, sampler, distance)
        if settings.n_stars > 0 and fraction * MAX_OFFSET_OVERSAMPLING < 1:
            raise ValueError(
                f"the offset field holds only {fraction:.1e} of the stars of the square "
                "enclosing it; field-only sampling would need too many stars: reduce the offset"
            )
        n_field = int(round(settings.n_stars / max(fraction, 1e-300)))
    counts = _group_counts(settings, sampler, n_field)
    mf = _mass_function(settings)
    parts = []
    for (region, luminous), n, (rng_pop, rng_pos, rng_vel) in zip(GROUPS, counts, _streams(seed)):
        u_mass = rng_pop.random(n)
        if luminous:
            mass = mf.sample(u_mass, hi=pop.tip_mass())
            mag = pop.apparent_v(mass, distance, model.params["extinction_v"])
        else:
            mass = pop.remnant_mass(mf.sample(u_mass, lo=pop.tip_mass()))
            mag = np.full(n, pop.DARK_MAGNITUDE)
        stars = sampler.sample(region, rng_pos.random((n, 4)), rng_vel.random((n, 3)))
        stars.update(
            mass=mass,
            mag=mag,
            luminous=np.full(n, luminous),
            region=np.full(n, 0 if region == "field" else 1),
        )
        parts.append(stars)
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "psi"}
    out["id"] = np.arange(out["x"].size, dtype=np.int64)
    if offset_mode:
        keep = _in_offset_field(settings, out, distance)
        out = {k: v[keep] for k, v in out.items()}
    return out, model


def _in_offset_field(settings, stars, distance):
    x = pc_to_arcsec(stars["x"], distance)
    y = pc_to_arcsec(stars["y"], distance)
    xf, yf, _, _ = sky_to_field(
        x, y, x, y, (settings.offset_x, settings.offset_y), settings.rotation
    )
    stars["region"] = np.where(in_square(xf, yf, 0.5 * settings.field_size), 0, 1)
    return in_square(xf, yf, 0.5 * settings.field_size + settings.margin)


def n_stars_for_circle(
    settings: ClusterSettings, n_circle: int, radius: float, model: ClusterModel | None = None
) -> int:
    """``n_stars`` that gives on average ``n_circle`` luminous stars within ``radius``.

    Parameters
    ----------
    settings : ClusterSettings
        Field geometry and model (no offset).
    n_circle : int
        Wanted mean number of luminous stars with projected radius < ``radius``.
    radius : float
        Projected radius [arcsec]; must fit in the field (``<= field_size / 2``).
    model : ClusterModel, optional

    Returns
    -------
    int
    """
    if not 0 < radius <= 0.5 * settings.field_size:
        raise ValueError(f"radius must be in (0, field_size/2], got {radius} arcsec")
    model = model or build_cluster_model(settings)
    distance = model.params["distance"]
    sampler = _field_sampler(settings, model)
    grid, cdf = sampler.radius_grid, sampler.radius_cdf["field"]
    fraction = float(np.interp(arcsec_to_pc(radius, distance), grid, cdf))
    return int(round(n_circle / max(fraction, 1e-300)))


def stars_to_epoch_tables(stars: dict, settings: ClusterSettings, distance: float) -> dict:
    """Field-frame epoch tables (``docs/formats.md`` catalogue columns) from cluster-frame stars.

    Parameters
    ----------
    stars : dict of ndarray
        As returned by :func:`sample_stars` (``x, y`` [pc] or ``x_arcsec, y_arcsec``
        [arcsec] for already projected inputs; ``pm_x, pm_y`` [mas/yr] may replace
        ``vx, vy``).
    settings : ClusterSettings
        Epochs, reference epoch, offset, rotation, systemic PM.
    distance : float
        [kpc]

    Returns
    -------
    dict of str to QTable
        ``e0, e1, ...`` in epoch order, each with ``meta["epoch"]`` [yr].
    """
    if "x_arcsec" in stars:
        x, y = stars["x_arcsec"], stars["y_arcsec"]
    else:
        x, y = pc_to_arcsec(stars["x"], distance), pc_to_arcsec(stars["y"], distance)
    if "pm_x" in stars:
        pmx, pmy = stars["pm_x"], stars["pm_y"]
    else:
        pmx, pmy = velocity_to_pm(stars["vx"], distance), velocity_to_pm(stars["vy"], distance)
    xf, yf, pmxf, pmyf = sky_to_field(
        x,
        y,
        pmx,
        pmy,
        (settings.offset_x, settings.offset_y),
        settings.rotation,
        (settings.pm_sys_x, settings.pm_sys_y),
    )
    truth = {}
    for key, unit in (("mass", u.solMass), ("r3d", u.pc), ("z", u.pc)):
        if key in stars:
            truth[key] = np.asarray(stars[key], float) * unit
    if "vx" in stars:
        vxf, vyf, _, _ = sky_to_field(
            stars["vx"], stars["vy"], stars["vx"], stars["vy"], (0, 0), settings.rotation
        )
        truth.update(
            vx=vxf * u.km / u.s, vy=vyf * u.km / u.s, vz=np.asarray(stars["vz"]) * u.km / u.s
        )
    if "luminous" in stars:
        truth["luminous"] = np.asarray(stars["luminous"], bool)
    tables = {}
    for i, epoch in enumerate(sorted(settings.epochs)):
        xe, ye = propagate(xf, yf, pmxf, pmyf, epoch, settings.reference_epoch)
        table = QTable(
            {
                "id": np.asarray(stars["id"], np.int64),
                "x": xe * u.arcsec,
                "y": ye * u.arcsec,
                "pm_x": pmxf * u.mas / u.yr,
                "pm_y": pmyf * u.mas / u.yr,
                "mag": np.asarray(stars["mag"], float) * u.mag,
                **truth,
            },
            meta={"epoch": epoch * u.yr},
        )
        tables[f"e{i}"] = table
    return tables


def catalogue_attrs(settings: ClusterSettings, params: dict, model_name: str) -> dict:
    """Root attributes of a catalogue product (``docs/formats.md`` + ``model_params``)."""
    return {
        "distance": params["distance"] * u.kpc,
        "ra_center": params["ra_center"] * u.deg,
        "dec_center": params["dec_center"] * u.deg,
        "field_size": settings.field_size * u.arcsec,
        "imbh_mass": params.get("bh_mass", settings.imbh_mass) * u.solMass,
        "model": model_name,
        "model_params": params,
        "margin": settings.margin * u.arcsec,
        "reference_epoch": settings.reference_epoch * u.yr,
        "n_stars_field": int(settings.n_stars),
    }


def simulate_catalogue(settings: ClusterSettings, seed: int, model: ClusterModel | None = None):
    """Simulate an equilibrium cluster catalogue in memory.

    Parameters
    ----------
    settings : ClusterSettings
    seed : int
    model : ClusterModel, optional
        Prebuilt model (saves the DF construction in loops).

    Returns
    -------
    epochs : dict of str to QTable
        Epoch tables for :func:`mavispm.core.catalogue.write_catalogue`.
    attrs : dict
        Root attributes (``distance``, ``imbh_mass``, ``model_params``, ...).
    """
    stars, model = sample_stars(settings, seed, model)
    params = model.params
    tables = stars_to_epoch_tables(stars, settings, params["distance"])
    name = f"isotropic {params['tracer']}"
    if params["tracer"] == "king":
        name += f" W0={params['king_w0']:g}"
    if params["cusp_gamma"] > 0:
        name += f" + cusp gamma={params['cusp_gamma']:g}"
    if params["bh_mass"] > 0:
        name += f" + IMBH {params['bh_mass']:g} Msun"
    return tables, catalogue_attrs(settings, params, name)


__all__ = [
    "ClusterModel",
    "SamplerResolution",
    "build_cluster_model",
    "catalogue_attrs",
    "model_from_params",
    "n_stars_for_circle",
    "observed_params",
    "resolve_model_params",
    "sample_stars",
    "simulate_catalogue",
    "stars_to_epoch_tables",
]
