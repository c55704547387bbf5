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
from numpy.typing import ArrayLike

from mavispm.simulate.cluster import population as pop
from mavispm.simulate.cluster.eddington import (
    DistributionFunction,
    NoIsotropicDFError,
    check_isotropic_df_exists,
    eddington_df,
)
from mavispm.simulate.cluster.effective_temperature import effective_temperature
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
    build_multi_mass_model,
    central_dispersion_cored,
    influence_radius,
    king_solution,
    king_w0_for_truncation,
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
#: Inner 3-D slope of the core-collapse-like cusp (projected slope -0.8 of post-core-collapse
#: clusters, Djorgovski & King 1986; Lugger, Cohn & Grindlay 1995).
CORE_COLLAPSE_GAMMA = 1.8
#: Default black-hole-subsystem scale radius, in scale radii of the reference group.
BH_SUBSYSTEM_RADIUS = 0.4
#: Regions in stream order.
REGIONS = ("field", "frame")
#: Largest ratio of stars drawn to stars kept for an offset field.
MAX_OFFSET_OVERSAMPLING = 200.0
#: IDs: object ``i`` of stream ``k`` (group ``k // 2``, region ``k % 2``) gets
#: ``(k + 1) * ID_STRIDE + i``; the IMBH, when present, gets :data:`IMBH_ID`.
ID_STRIDE = 10**9
IMBH_ID = 0


@dataclass(frozen=True)
class Component:
    """Groups sharing one density shape: their mass model and DF.

    Parameters
    ----------
    mass : MassModel
        The component's density in the total potential.
    df : DistributionFunction
    groups : tuple of int
        Indices into ``params["groups"]``.
    """

    mass: MassModel
    df: DistributionFunction
    groups: tuple


@dataclass(frozen=True)
class ClusterModel:
    """A (multi-mass) cluster model with its DFs and its parameters.

    Parameters
    ----------
    components : tuple of Component
        One per distinct density shape (one for an unsegregated model).
    params : dict
        See :func:`resolve_model_params`.
    """

    components: tuple
    params: dict

    @property
    def mass(self) -> MassModel:
        """Mass model of the first component (the whole cluster when unsegregated)."""
        return self.components[0].mass

    @property
    def df(self) -> DistributionFunction:
        """DF of the first component (the whole cluster when unsegregated)."""
        return self.components[0].df

    def total_density(self, r: ArrayLike) -> np.ndarray:
        """Density of all components [solMass/pc^3] at ``r`` [pc] (no IMBH).

        Parameters
        ----------
        r : array_like
            Radii [pc].

        Returns
        -------
        ndarray
            Summed mass density of the components [solMass/pc^3].
        """
        return np.sum([c.mass.density(r) for c in self.components], axis=0)


def _mass_function(settings, preset=None) -> pop.MassFunction:
    preset = preset or get_preset(settings.preset)
    return pop.MassFunction(
        settings.mass_min,
        settings.mass_break,
        settings.mass_max,
        preset.alpha_low if settings.alpha_low is None else settings.alpha_low,
        preset.alpha_high if settings.alpha_high is None else settings.alpha_high,
    )


def _pick(settings, preset, key):
    value = getattr(settings, key)
    return getattr(preset, key) if value is None else value


def _population_groups(settings, preset, mf, total_mass: float) -> list[dict]:
    """Mass groups with their total masses [solMass] (see :func:`resolve_model_params`)."""
    groups = pop.mass_groups(
        mf,
        settings.include_remnants,
        _pick(settings, preset, "ns_retention"),
        _pick(settings, preset, "bh_retention"),
    )
    bhs = float(settings.bh_subsystem_mass)
    if bhs > 0:
        if bhs >= 0.5 * total_mass:
            raise ValueError(
                f"'bh_subsystem_mass' ({bhs:g} solMass) must be below half the cluster mass "
                f"({total_mass:g} solMass)"
            )
        groups = [g for g in groups if g.kind != "black_hole"] + [pop.black_hole_subsystem(bhs)]
    rest = sum(g.mass for g in groups if not g.fixed_range)
    out = []
    for g in groups:
        mass = g.mass if g.fixed_range else (total_mass - bhs) * g.mass / rest
        out.append(
            {
                "kind": g.kind,
                "lo": g.lo,
                "hi": g.hi,
                "fixed_range": g.fixed_range,
                "mass": float(mass),
                "mean_mass": float(g.mean_mass),
                "number": float(mass / g.mean_mass),
            }
        )
    return out


def resolve_model_params(settings: ClusterSettings) -> dict:
    """The model's true parameters from the settings and their preset.

    Parameters
    ----------
    settings : ClusterSettings
        Validated settings; values left None come from the preset.

    Returns
    -------
    dict
        ``tracer``, ``king_w0``, ``stellar_mass`` [solMass] (all stars and remnants,
        no IMBH), ``scale_radius`` [pc] (of the reference group, mass
        ``reference_mass``), ``bh_mass`` [solMass], ``cusp_gamma``, ``cusp_radius`` [pc],
        ``distance`` [kpc], ``extinction_v`` [mag], ``truncation_radius`` [pc],
        ``core_radius``, ``half_mass_radius_projected`` [pc] (of the cored reference
        profile, without cusp), ``central_dispersion_cored`` [km/s] (1-D, single-mass,
        no IMBH), ``ra_center``, ``dec_center`` [deg], ``preset``, ``segregation``,
        ``reference_mass`` [solMass], ``anisotropy_radius`` [pc] (None: isotropic),
        ``bh_subsystem_mass`` [solMass], ``core_collapse``, and ``groups``: one dict per
        mass group with ``kind``, ``lo``, ``hi`` (initial-mass range [solMass]; final
        masses for ``fixed_range`` groups), ``mass`` (total [solMass]), ``mean_mass``
        [solMass], ``number``, ``scale_radius`` [pc] and ``king_w0``; and
        ``anisotropy_beta`` (constant anisotropy, 0 unless set).

    Raises
    ------
    ValueError
        Unknown preset, a cored tracer around an IMBH (An & Evans 2006), or an
        impossible setting combination.
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
        gamma = (
            DEFAULT_CUSP_GAMMA
            if bh > 0
            else (CORE_COLLAPSE_GAMMA if settings.core_collapse else 0.0)
        )
    check_isotropic_df_exists(gamma, bh, settings.anisotropy_beta)
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
            if bh > 0 or not settings.core_collapse:
                ref_bh = bh if bh > 0 else 0.01 * mass
                cusp_radius = influence_radius(cored, mass, ref_bh)
            else:
                cusp_radius = scale
    tracer = TracerProfile(tracer_kind, scale, w0, gamma, cusp_radius)
    segregation = float(_pick(settings, preset, "segregation"))
    groups = _population_groups(settings, preset, _mass_function(settings, preset), mass)
    m_ref = pop.tip_mass()
    for g in groups:
        if g["fixed_range"] and settings.bh_subsystem_radius is not None:
            g_scale = float(settings.bh_subsystem_radius)
        elif g["fixed_range"]:
            g_scale = BH_SUBSYSTEM_RADIUS * scale
        else:
            g_scale = scale * (g["mean_mass"] / m_ref) ** -segregation
        g["scale_radius"] = g_scale
        g["king_w0"] = _group_w0(tracer_kind, w0, scale, g_scale)
    ra = settings.anisotropy_radius
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
        "segregation": segregation,
        "reference_mass": m_ref,
        "anisotropy_radius": None if ra is None else float(arcsec_to_pc(ra, distance)),
        "anisotropy_beta": float(settings.anisotropy_beta),
        "bh_subsystem_mass": float(settings.bh_subsystem_mass),
        "core_collapse": bool(settings.core_collapse),
        "groups": groups,
        "units": {
            **observed["units"],
            "stellar_mass": "solMass",
            "scale_radius": "pc",
            "cusp_radius": "pc",
            "truncation_radius": "pc",
            "core_radius": "pc",
            "half_mass_radius_projected": "pc",
            "central_dispersion_cored": "km/s",
            "reference_mass": "solMass",
            "anisotropy_radius": "pc",
            "bh_subsystem_mass": "solMass",
        },
    }


def _group_w0(kind: str, w0: float, scale: float, group_scale: float) -> float:
    """King W0 of a group: the one that keeps the reference truncation radius."""
    if kind != "king" or group_scale == scale:
        return w0
    try:
        return king_w0_for_truncation(
            king_solution(float(w0))[2] * scale / group_scale, guess=float(w0)
        )
    except ValueError:
        raise ValueError(
            f"'segregation' too strong for a King model: a group with scale radius "
            f"{group_scale:.3g} pc cannot share the truncation radius; lower segregation, "
            "bh_subsystem_radius, or use tracer = 'plummer'"
        ) from None


def observed_params(settings: ClusterSettings) -> dict:
    """Preset-or-setting values that do not depend on the dynamical model.

    Parameters
    ----------
    settings : ClusterSettings
        Validated settings; values left None come from the preset.

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
    """Rebuild the mass model and DFs from a ``model_params`` dict.

    Groups with the same scale radius and W0 share one component (one density
    shape, one DF). Catalogues written before multi-mass models (no ``groups``)
    give one component of all the mass.

    Parameters
    ----------
    params : dict
        As returned by :func:`resolve_model_params` (or read from a catalogue's
        ``model_params`` attribute, a JSON string, after ``json.loads``).
    n_energy : int
        Energy grid size of the DF table.

    Raises
    ------
    NoIsotropicDFError
        If a component has no non-negative DF; the message names the component.
    """
    groups = params.get("groups") or [
        {"scale_radius": params["scale_radius"], "king_w0": params["king_w0"], "mass": 1.0}
    ]
    keys = []
    for g in groups:
        key = (round(g["scale_radius"], 12), g["king_w0"])
        if key not in keys:
            keys.append(key)
    members = [
        tuple(i for i, g in enumerate(groups) if (round(g["scale_radius"], 12), g["king_w0"]) == k)
        for k in keys
    ]
    weights = np.array([sum(groups[i]["mass"] for i in m) for m in members])
    masses = params["stellar_mass"] * weights / weights.sum()
    tracers = [
        TracerProfile(params["tracer"], a, w, params["cusp_gamma"], params["cusp_radius"])
        for a, w in keys
    ]
    if len(tracers) == 1:
        models = [build_mass_model(tracers[0], params["stellar_mass"], params["bh_mass"])]
    else:
        models = build_multi_mass_model(tracers, masses, params["bh_mass"])
    ra = params.get("anisotropy_radius")
    ra = np.inf if ra is None else float(ra)
    components = []
    for model, member in zip(models, members):
        try:
            df = eddington_df(
                model,
                n_energy=n_energy,
                anisotropy_radius=ra,
                beta=params.get("anisotropy_beta", 0.0),
            )
        except NoIsotropicDFError as exc:
            if len(models) == 1:
                raise
            kinds = sorted({groups[i].get("kind", "star") for i in member})
            raise NoIsotropicDFError(
                f"mass group(s) {kinds} with scale radius {model.tracer.scale_radius:.3g} pc: {exc}"
            ) from None
        components.append(Component(model, df, member))
    return ClusterModel(tuple(components), dict(params))


def build_cluster_model(settings: ClusterSettings) -> ClusterModel:
    """Model parameters, mass model and DF for ``settings``.

    Parameters
    ----------
    settings : ClusterSettings
        Validated settings (``resolution.n_energy`` sets the DF's energy grid).

    Returns
    -------
    ClusterModel
        The model (see :func:`resolve_model_params` for its ``params``).
    """
    return model_from_params(resolve_model_params(settings), settings.resolution.n_energy)


def _streams(seed: int, n_streams: int):
    """Per-stream (population, position, velocity) generators."""
    children = np.random.SeedSequence(seed).spawn(n_streams)
    return [[np.random.default_rng(s) for s in child.spawn(3)] for child in children]


def _group_counts(groups, fractions, n_field: int) -> np.ndarray:
    """Objects per (group, region): expected numbers with exactly ``n_field`` luminous in the field.

    ``fractions[i][j]`` is the fraction of group ``i``'s mass in region ``j``.
    """
    expect = np.array([[g["number"] * f for f in fr] for g, fr in zip(groups, fractions)])
    lum = np.array([g["kind"] == "star" for g in groups])
    total = expect[lum, 0].sum()
    if n_field == 0 or total <= 0:
        return np.zeros(expect.shape, int)
    expect *= n_field / total
    counts = np.rint(expect).astype(int)
    # largest remainder: the luminous field counts sum to n_field exactly
    lum_idx = np.flatnonzero(lum)
    base = np.floor(expect[lum_idx, 0]).astype(int)
    short = n_field - base.sum()
    order = np.argsort(-(expect[lum_idx, 0] - base), kind="stable")
    base[order[:short]] += 1
    counts[lum_idx, 0] = base
    return counts


def _field_geometry(settings, distance):
    """Half-size of the sampled square and its margin [pc] (cluster-centred)."""
    half = 0.5 * settings.field_size
    offset = max(abs(settings.offset_x), abs(settings.offset_y))
    if offset == 0:
        return arcsec_to_pc(half, distance), arcsec_to_pc(settings.margin, distance)
    # offset field: sample a cluster-centred square enclosing the rotated field + margin
    big = offset + (half + settings.margin) * np.sqrt(2.0)
    return arcsec_to_pc(big, distance), 0.0


def _field_samplers(settings, model: ClusterModel) -> list[FieldSampler]:
    half, margin = _field_geometry(settings, model.params["distance"])
    return [
        build_field_sampler(c.mass, c.df, half, margin, settings.resolution)
        for c in model.components
    ]


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


def _group_fractions(model: ClusterModel, samplers) -> list[list[float]]:
    """Fraction of each group's mass in the field and in the frame."""
    out = [None] * len(model.params.get("groups") or [0])
    for comp, sampler in zip(model.components, samplers):
        total = comp.mass.stellar_mass
        fr = [sampler.region_mass[r] / total for r in REGIONS]
        for i in comp.groups:
            out[i] = fr
    return out


def _luminous_weights(model: ClusterModel, fractions) -> np.ndarray:
    """Share of each component in the luminous stars of the field."""
    groups = _groups(model)
    w = np.zeros(len(model.components))
    for k, comp in enumerate(model.components):
        w[k] = sum(groups[i]["number"] * fractions[i][0] for i in comp.groups if _lum(groups[i]))
    return w / max(w.sum(), 1e-300)


def _groups(model: ClusterModel) -> list[dict]:
    """The model's groups (old single-mass parameter sets: one luminous group)."""
    return model.params.get("groups") or [{"kind": "star", "number": 1.0, "mass": 1.0}]


def _lum(group: dict) -> bool:
    return group["kind"] == "star"


def sample_stars(settings: ClusterSettings, seed: int, model: ClusterModel | None = None):
    """Draw the objects in the field and its margin at the reference epoch.

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
        ``mag`` [mag], ``luminous`` (bool), ``kind`` (str), ``group`` (index into
        ``model_params["groups"]``, -1 for the IMBH), ``id`` (int64), ``region``
        (0 field, 1 margin). Order: luminous field, luminous margin, dark field,
        dark margin (each by group). The IMBH is not included (see
        :func:`simulate_catalogue`).
    model : ClusterModel
    """
    model = model or build_cluster_model(settings)
    distance = model.params["distance"]
    samplers = _field_samplers(settings, model)
    groups = _groups(model)
    fractions = _group_fractions(model, samplers)
    offset_mode = bool(settings.offset_x or settings.offset_y)  # see _field_geometry
    n_field = settings.n_stars
    weights = _luminous_weights(model, fractions)
    if settings.n_stars > 0 and not any(
        fractions[i][0] > 0 for i, g in enumerate(groups) if _lum(g)
    ):
        raise ValueError("the field holds no cluster stars (is it beyond the tidal radius?)")
    if offset_mode:
        fraction = sum(
            w * _offset_field_fraction(settings, s, distance) for w, s in zip(weights, samplers)
        )
        if settings.n_stars > 0 and fraction * MAX_OFFSET_OVERSAMPLING < 1:
            raise ValueError(
                f"the offset field holds only {fraction:.1e} of the stars of the square "
                "enclosing it; field-only sampling would need too many stars: reduce the offset"
            )
        n_field = int(round(settings.n_stars / max(fraction, 1e-300)))
    counts = _group_counts(groups, fractions, n_field)
    sampler_of = {i: samplers[k] for k, c in enumerate(model.components) for i in c.groups}
    mf = _mass_function(settings)
    streams = _streams(seed, 2 * len(groups))
    parts = []
    for luminous in (True, False):
        for j, region in enumerate(REGIONS):
            for i, g in enumerate(groups):
                if _lum(g) != luminous:
                    continue
                n = int(counts[i, j])
                rng_pop, rng_pos, rng_vel = streams[2 * i + j]
                mass = _group_masses(g, mf, rng_pop.random(n))
                if luminous:
                    mag = pop.apparent_v(mass, distance, model.params["extinction_v"])
                    teff = effective_temperature(mass)
                else:
                    mag = np.full(n, pop.DARK_MAGNITUDE)
                    teff = np.full(n, np.nan)
                stars = sampler_of[i].sample(region, rng_pos.random((n, 4)), rng_vel.random((n, 3)))
                stars.update(
                    mass=mass,
                    mag=mag,
                    teff=teff,
                    luminous=np.full(n, luminous),
                    kind=np.full(n, g["kind"]),
                    group=np.full(n, i),
                    region=np.full(n, j),
                    id=(2 * i + j + 1) * ID_STRIDE + np.arange(n, dtype=np.int64),
                )
                parts.append(stars)
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "psi"}
    if offset_mode:
        keep = _in_offset_field(settings, out, distance)
        out = {k: v[keep] for k, v in out.items()}
    return out, model


def _group_masses(group: dict, mf: pop.MassFunction, uniform: np.ndarray) -> np.ndarray:
    """Present-day masses [solMass] of a group's objects from uniforms."""
    if "lo" not in group:  # single-mass parameter sets: luminous stars of the mass function
        return mf.sample(uniform, hi=pop.tip_mass())
    g = pop.MassGroup(
        group["kind"],
        group["lo"],
        group["hi"],
        group["number"],
        group["mass"],
        group["fixed_range"],
    )
    return g.sample_masses(mf, uniform)


def with_imbh(stars: dict, settings: ClusterSettings, bh_mass: float) -> dict:
    """Append the IMBH (kind ``imbh``, id :data:`IMBH_ID`) if it lies in the field or margin.

    Parameters
    ----------
    stars : dict of str to ndarray
        Column name to per-star values.
    settings : ClusterSettings
        Field geometry (size, margin, offset, rotation).
    bh_mass : float
        IMBH mass [solMass]; nothing is added when it is not > 0.

    Returns
    -------
    dict of str to ndarray
        The columns with the IMBH row appended at the cluster centre (region 0 in the field,
        1 in the margin), or ``stars`` unchanged.
    """
    if not bh_mass > 0:
        return stars
    row = _imbh_row(bh_mass)
    xf, yf, _, _ = sky_to_field(
        0.0, 0.0, 0.0, 0.0, (settings.offset_x, settings.offset_y), settings.rotation
    )
    if not in_square(xf, yf, 0.5 * settings.field_size + settings.margin):
        return stars
    row["region"][0] = 0 if in_square(xf, yf, 0.5 * settings.field_size) else 1
    return {k: np.concatenate([v, row[k]]) for k, v in stars.items() if k in row}


def _imbh_row(bh_mass: float) -> dict:
    """The IMBH as a catalogue row: at rest at the centre, dark."""
    zero = np.zeros(1)
    return {
        **{k: zero for k in ("x", "y", "z", "r3d", "vx", "vy", "vz")},
        "mass": np.array([bh_mass]),
        "mag": np.array([pop.DARK_MAGNITUDE]),
        "teff": np.array([np.nan]),
        "luminous": np.array([False]),
        "kind": np.array(["imbh"]),
        "group": np.array([-1]),
        "region": np.array([0]),
        "id": np.array([IMBH_ID], np.int64),
    }


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
    samplers = _field_samplers(settings, model)
    weights = _luminous_weights(model, _group_fractions(model, samplers))
    r_pc = arcsec_to_pc(radius, distance)
    fraction = sum(
        w * float(np.interp(r_pc, s.radius_grid, s.radius_cdf["field"]))
        for w, s in zip(weights, samplers)
    )
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
    for key, unit in (("mass", u.solMass), ("r3d", u.pc), ("z", u.pc), ("teff", u.K)):
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
    if "kind" in stars:
        truth["kind"] = np.asarray(stars["kind"], str)
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
    """Root attributes of a catalogue product (``docs/formats.md`` + ``model_params``).

    Parameters
    ----------
    settings : ClusterSettings
        The stage settings.
    params : dict
        The model parameters (:func:`resolve_model_params`, or the external input's).
    model_name : str
        Description stored as ``model``.

    Returns
    -------
    dict
        Attribute name to value: ``distance`` [kpc], ``ra_center``, ``dec_center`` [deg],
        ``field_size``, ``margin`` [arcsec], ``imbh_mass`` [solMass], ``reference_epoch`` [yr]
        as quantities, ``model``, ``model_params``, ``n_stars_field``.
    """
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
    stars = with_imbh(stars, settings, params["bh_mass"])
    tables = stars_to_epoch_tables(stars, settings, params["distance"])
    ra = params.get("anisotropy_radius")
    name = "isotropic" if ra is None else f"Osipkov-Merritt r_a={ra:.3g} pc"
    if params.get("anisotropy_beta", 0):
        name = f"constant beta={params['anisotropy_beta']:g}"
    name += f" {params['tracer']}"
    if params["tracer"] == "king":
        name += f" W0={params['king_w0']:g}"
    if params.get("segregation", 0) > 0:
        name += f" multi-mass segregation={params['segregation']:g}"
    if params.get("bh_subsystem_mass", 0) > 0:
        name += f" + BH subsystem {params['bh_subsystem_mass']:g} Msun"
    if params["cusp_gamma"] > 0:
        name += f" + cusp gamma={params['cusp_gamma']:g}"
        if params.get("core_collapse") and params["bh_mass"] == 0:
            name += " (core collapse)"
    if params["bh_mass"] > 0:
        name += f" + IMBH {params['bh_mass']:g} Msun"
    return tables, catalogue_attrs(settings, params, name)


__all__ = [
    "ClusterModel",
    "Component",
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
