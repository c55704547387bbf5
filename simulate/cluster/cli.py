"""The ``simulate cluster`` stage: settings validation, run_stage and the CLI command.

``mavispm simulate cluster --preset ngc3201 --imbh-mass 1500 --epochs 0,10 --seed 1 -o cluster.h5``
"""

from __future__ import annotations

import argparse
import tomllib
from collections.abc import Mapping
from pathlib import Path

from mavispm.core.catalogue import write_catalogue
from mavispm.core.cliargs import non_negative_int, positive_int
from mavispm.core.config import from_mapping, to_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.knobs import gather_knobs
from mavispm.simulate.cluster.eddington import NoIsotropicDFError, check_isotropic_df_exists
from mavispm.simulate.cluster.external import read_external_stars
from mavispm.simulate.cluster.generator import (
    catalogue_attrs,
    observed_params,
    resolve_model_params,
    simulate_catalogue,
    stars_to_epoch_tables,
)
from mavispm.simulate.cluster.presets import get_preset
from mavispm.simulate.cluster.settings import CLUSTER_KNOB_HOMES, ClusterSettings

#: Largest IMBH mass accepted, as a fraction of the cluster's stellar mass (observed
#: candidates are a few per cent; above this the "cluster" is a galaxy nucleus).
MAX_IMBH_FRACTION = 0.2

#: Memory per star and epoch while a catalogue is drawn and written (about 20
#: float64 columns, with the sampler's temporaries).
BYTES_PER_STAR_EPOCH = 160


def validate_settings(settings: Mapping | None, source: str | None = None) -> ClusterSettings:
    """Build :class:`ClusterSettings` from a mapping (TOML table ``[cluster]``).

    Parameters
    ----------
    settings : mapping or None
        The ``[cluster]`` table (None: defaults); the knobs may be given in ``knobs`` or in
        the earlier ``resolution`` table, not both for one knob.
    source : str, optional
        File named in error messages.

    Returns
    -------
    ClusterSettings
        The validated settings.

    Raises
    ------
    ConfigError
        Unknown keys, wrong types or units, impossible values, an unknown preset,
        or a cored tracer around an IMBH.
    """
    mapping = gather_knobs(settings, CLUSTER_KNOB_HOMES, ("resolution",), source=source)
    obj = from_mapping(ClusterSettings, mapping, source=source)
    from mavispm.core.limits import check_memory

    check_memory(
        float(obj.n_stars) * BYTES_PER_STAR_EPOCH * (len(obj.epochs) + 2),
        f"a catalogue of {obj.n_stars} stars at {len(obj.epochs)} epochs",
        "n_stars",
        source,
    )
    try:
        preset = get_preset(obj.preset)
    except ValueError as exc:
        raise ConfigError(str(exc), key="preset", source=source) from None
    cluster_mass = obj.stellar_mass if obj.stellar_mass is not None else preset.stellar_mass
    if obj.imbh_mass > MAX_IMBH_FRACTION * cluster_mass:
        raise ConfigError(
            f"an IMBH of {obj.imbh_mass:.4g} solMass is more than {MAX_IMBH_FRACTION:g} x the "
            f"cluster's stellar mass ({cluster_mass:.4g} solMass); the stars would move at "
            "unphysical speeds around it. Expected a black hole lighter than its cluster",
            key="imbh_mass",
            source=source,
        )
    if obj.cusp_gamma is not None:
        try:
            check_isotropic_df_exists(obj.cusp_gamma, obj.imbh_mass, obj.anisotropy_beta)
        except NoIsotropicDFError as exc:
            raise ConfigError(str(exc), key="cusp_gamma", source=source) from None
    if obj.external.path and obj.external.format == "mavisim" and not obj.external.pm_convention:
        raise ConfigError(
            "MAVISIM source lists need an explicit pm_convention ('mas_per_yr' or "
            "'arcsec_per_baseline')",
            key="external.pm_convention",
            source=source,
        )
    return obj


def build_catalogue(settings: ClusterSettings, seed: int):
    """Epoch tables and root attributes for validated settings (model or external input).

    Parameters
    ----------
    settings : ClusterSettings
        Validated settings.
    seed : int
        Random seed.

    Returns
    -------
    tables : dict of str to astropy.table.QTable
        Epoch name to star table.
    attrs : dict
        Root attributes of the catalogue product.

    Raises
    ------
    ConfigError
        For an impossible model or geometry.
    """
    try:
        if settings.external.path:
            params = _external_params(settings)
            stars = read_external_stars(
                settings.external, settings, params["distance"], params["extinction_v"]
            )
            tables = stars_to_epoch_tables(stars, settings, params["distance"])
            return tables, catalogue_attrs(settings, params, f"external: {settings.external.path}")
        return simulate_catalogue(settings, seed)
    except (InputError, ConfigError):
        raise
    except ValueError as exc:  # impossible model or geometry (incl. NoIsotropicDFError)
        raise ConfigError(str(exc)) from None


def _external_params(settings: ClusterSettings) -> dict:
    return {**observed_params(settings), "external": settings.external.path}


def run_stage(settings: Mapping, output: Path, seed: int) -> Path:
    """Simulate (or import) a cluster catalogue and write it atomically.

    Parameters
    ----------
    settings : mapping
        The ``[cluster]`` table (keys in ``docs/cluster.md``).
    output : pathlib.Path
        Catalogue product to write (HDF5, kind "catalogue").
    seed : int
        Random seed.

    Returns
    -------
    pathlib.Path
        ``output``.
    """
    obj = settings if isinstance(settings, ClusterSettings) else validate_settings(settings)
    tables, attrs = build_catalogue(obj, seed)
    return write_catalogue(output, tables, attrs=attrs, config=to_mapping(obj), seed=seed)


def _epochs(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated years, got {text!r}") from None


#: CLI option -> settings key (None values are not passed on).
_OPTION_KEYS = {
    "preset": "preset",
    "imbh_mass": "imbh_mass",
    "n_stars": "n_stars",
    "field_size": "field_size",
    "margin": "margin",
    "epochs": "epochs",
    "tracer": "tracer",
    "king_w0": "king_w0",
    "cusp_gamma": "cusp_gamma",
    "distance": "distance",
    "stellar_mass": "stellar_mass",
    "anisotropy_radius": "anisotropy_radius",
    "anisotropy_beta": "anisotropy_beta",
    "bh_subsystem_mass": "bh_subsystem_mass",
    "segregation": "segregation",
    "core_collapse": "core_collapse",
}


def _handler(args: argparse.Namespace) -> int:
    settings: dict = {}
    if args.config:
        try:
            with open(args.config, "rb") as fh:
                data = tomllib.load(fh)
        except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"cannot read TOML settings ({exc})", path=args.config) from None
        settings.update(data.get("cluster", data))
    for opt, key in _OPTION_KEYS.items():
        value = getattr(args, opt)
        if value is not None:
            settings[key] = value
    if args.input:
        ext = dict(settings.get("external", {}))
        ext["path"] = args.input
        for opt, key in (("input_format", "format"), ("pm_convention", "pm_convention")):
            if getattr(args, opt):
                ext[key] = getattr(args, opt)
        if args.pm_baseline is not None:
            ext["pm_baseline"] = args.pm_baseline
        if args.flux_zeropoint is not None:
            ext["flux_zeropoint"] = args.flux_zeropoint
        settings["external"] = ext
    try:
        obj = validate_settings(settings, source=args.config)
        out = run_stage(obj, Path(args.output), args.seed)
    except ConfigError as exc:
        raise _as_option_error(exc, args) from None
    print(f"wrote {out}")
    return 0


#: Settings key -> the option that sets it (errors name what the user typed).
_KEY_OPTIONS = {
    "external.path": "input",
    "external.format": "input_format",
    "external.pm_convention": "pm_convention",
    "external.pm_baseline": "pm_baseline",
    "external.flux_zeropoint": "flux_zeropoint",
}


def _as_option_error(exc: ConfigError, args: argparse.Namespace) -> ConfigError:
    """The error naming ``--option`` instead of the settings key.

    Done when the option set the key, or when no ``--config`` file could have.
    """
    keys = {key: opt for opt, key in _OPTION_KEYS.items()} | _KEY_OPTIONS
    opt = keys.get(exc.key or "")
    given = getattr(args, opt, None) not in (None, False) if opt else False
    if opt is None or (args.config and not given):  # the key came from the --config file
        return exc
    flag = "--" + opt.replace("_", "-")
    text = str(exc)
    if exc.source is not None:
        text = text.replace(f"file '{exc.source}', ", "", 1)
    text = text.replace(f"key '{exc.key}'", f"option {flag}", 1)
    err = ConfigError(text)
    err.key, err.source = flag, exc.source
    return err


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``cluster`` sub-command.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The ``mavispm simulate`` sub-parsers.

    Returns
    -------
    argparse.ArgumentParser
        The new sub-parser.
    """
    p = subparsers.add_parser(
        "cluster",
        help="equilibrium cluster catalogue (with or without IMBH) or external star list",
        description="Draw the objects in the imaged field from an equilibrium cluster model "
        "(multi-mass, optionally mass-segregated, isotropic or Osipkov-Merritt DFs in the total "
        "potential of stars, remnants and IMBH), or import an N-body snapshot or MAVISIM "
        "source list, and write a catalogue product with one table per epoch.",
    )
    p.add_argument("-o", "--output", required=True, help="output catalogue (HDF5)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="random seed (default 0)")
    p.add_argument("--config", help="TOML file with a [cluster] table (options override it)")
    p.add_argument("--preset", help="cluster preset (default ngc3201)")
    p.add_argument("--imbh-mass", type=float, help="IMBH mass in solMass (0 = none)")
    p.add_argument(
        "--n-stars", type=positive_int, help="luminous stars in the field (default 3500)"
    )
    p.add_argument("--field-size", type=float, help="field side in arcsec (default 30)")
    p.add_argument("--margin", type=float, help="margin around the field in arcsec (default 1)")
    p.add_argument("--epochs", type=_epochs, help="comma-separated epochs in yr (default 0,10)")
    p.add_argument("--tracer", choices=["plummer", "king"], help="tracer profile (default: preset)")
    p.add_argument("--king-w0", type=float, help="King W0 (default: preset)")
    p.add_argument(
        "--cusp-gamma", type=float, help="inner cusp slope (default 1.55 with IMBH, else 0)"
    )
    p.add_argument("--distance", type=float, help="distance in kpc (default: preset)")
    p.add_argument("--stellar-mass", type=float, help="stellar mass in solMass (default: preset)")
    p.add_argument(
        "--anisotropy-radius",
        type=float,
        metavar="ARCSEC",
        help="Osipkov-Merritt anisotropy radius in arcsec (omitted: isotropic)",
    )
    p.add_argument(
        "--anisotropy-beta",
        type=float,
        metavar="BETA",
        help="constant velocity anisotropy in (-0.5, 0.5) (Cuddeford DF; default 0)",
    )
    p.add_argument(
        "--bh-subsystem-mass",
        type=float,
        metavar="MSUN",
        help="total mass of a central subsystem of 10-20 solMass black holes (default 0)",
    )
    p.add_argument(
        "--segregation",
        type=float,
        help="mass-segregation exponent, scale radius ~ mass^-s (0 = none; default: preset)",
    )
    p.add_argument(
        "--core-collapse",
        action="store_const",
        const=True,
        help="core-collapse-like cusp without an IMBH (3-D slope 1.8 unless --cusp-gamma)",
    )
    p.add_argument("--input", help="external N-body snapshot or MAVISIM source list")
    p.add_argument("--input-format", choices=["auto", "csv", "ecsv", "fits", "hdf5", "mavisim"])
    p.add_argument(
        "--pm-convention",
        choices=["mas_per_yr", "arcsec_per_baseline"],
        help="meaning of MAVISIM PM_X/PM_Y",
    )
    p.add_argument("--pm-baseline", type=float, help="baseline of PM displacements in yr (10)")
    p.add_argument("--flux-zeropoint", type=float, help="mag of Flux = 1 for MAVISIM lists")
    p.set_defaults(func=_handler)
    return p


__all__ = ["build_catalogue", "register", "resolve_model_params", "run_stage", "validate_settings"]
