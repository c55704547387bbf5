"""``mavispm fast-stars``: run (or rerun) the fast-star test on an existing dynamics product.

``mavispm fast-stars fit.h5 -o fit_fast.h5 [--config fs.toml] [--propermotions pm.h5]
[--plots plots/] [--seed 0]``

The fits are not repeated: the mass models come from the product's posterior
tables (``posterior_imbh``, ``posterior_no_imbh`` and any other
``posterior_<model>``), rebuilt with the product's own settings; the proper
motions from the product's ``propermotions`` path (or ``--propermotions``). The
output is the input product plus the ``fast_stars`` table and attributes
(written atomically; ``-o`` may name the input file). Settings: the
``[dynamics.fast_stars]`` table of ``--config``, else the product's, else the
defaults.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import astropy.units as u
import numpy as np

from mavispm.core.errors import InputError

__all__ = [
    "register",
    "run",
    "stored_fits",
]


@dataclass
class _Chain:
    samples: np.ndarray
    map_params: np.ndarray


@dataclass
class _StoredFit:
    """What :func:`mavispm.dynamics.fast_stars.run_on_fits` needs of a fit."""

    name: str
    space: object
    likelihood: object
    chain: _Chain


def stored_fits(product, settings, stars, distance):
    """Fits rebuilt from a dynamics product's posterior tables (no sampling).

    Parameters
    ----------
    product : Product
        A read ``dynamics`` product.
    settings : DynamicsSettings
    stars : StarSample
    distance : float
        [kpc]
    """
    from mavispm.dynamics.fit import make_likelihood, parameter_space
    from mavispm.dynamics.likelihood import VELOCITY_LAWS
    from mavispm.dynamics.settings import WEIGHED

    fits = []
    summary = product.tables.get("summary")
    for key, table in product.tables.items():
        if not key.startswith("posterior_"):
            continue
        name = key.removeprefix("posterior_")
        names = [c for c in table.colnames if c != "log_like"]
        # the law this posterior was drawn with (the law kept when the laws were weighed)
        law = product.attrs.get(f"velocity_law_{name}", product.attrs.get("velocity_law"))
        one = settings
        if law in VELOCITY_LAWS:
            one = dataclasses.replace(settings, velocity_law=law, compare_velocity_laws=())
        elif settings.velocity_law == WEIGHED:
            raise InputError(
                f"no velocity_law_{name} attribute: which law posterior_{name} was drawn "
                "with is unknown",
                path=product.path,
            )
        space = parameter_space(
            one, distance, name, positions=stars.x is not None and "x0" in names
        )
        if set(space.names) != set(names):
            raise InputError(
                f"posterior columns {names} do not match the settings' parameters "
                f"{list(space.names)}",
                path=product.path,
                column=key,
            )
        names = list(space.names)  # the likelihood's order (tables may list them sorted)
        samples = np.stack([np.asarray(table[n], float) for n in names], axis=1)
        best = np.median(samples, axis=0)
        if summary is not None:
            rows = {
                str(r["parameter"]): float(r["map"]) for r in summary if str(r["model"]) == name
            }
            if set(rows) == set(names):
                best = np.array([rows[n] for n in names])
        like = make_likelihood(stars, space, one, distance)
        fits.append(_StoredFit(name, space, like, _Chain(samples, best)))
    if not fits:
        raise InputError("no posterior tables (posterior_<model>)", path=product.path)
    return fits


def run(
    dynamics: str | os.PathLike,
    output: str | os.PathLike,
    settings_mapping: Mapping | None = None,
    propermotions: str | os.PathLike | None = None,
    plots_dir: str | os.PathLike | None = None,
    seed: int = 0,
):
    """Add the fast-star test to a dynamics product; returns the output path.

    The stored fits are reused (no refit); the settings are the product's own, with the
    ``[dynamics.fast_stars]`` table replaced by ``settings_mapping`` when given.

    Parameters
    ----------
    dynamics : str or os.PathLike
        The ``dynamics`` product.
    output : str or os.PathLike
        The new ``dynamics`` product with the ``fast_stars`` table.
    settings_mapping : mapping, optional
        A ``[dynamics.fast_stars]`` table.
    propermotions : str or os.PathLike, optional
        The ``propermotions`` product (default: the one the product names).
    plots_dir : str or os.PathLike, optional
        Folder for ``fast_stars.png`` (no plot when None or no test was possible).
    seed : int
        Random seed.

    Returns
    -------
    pathlib.Path
        ``output``.

    Raises
    ------
    InputError
        When the product names no proper-motion product and none is given.
    """
    from mavispm.core.products import read_product, write_product
    from mavispm.dynamics.cli import load_stars, validate_settings
    from mavispm.dynamics.fast_stars import FastStarSettings, run_on_fits

    prod = read_product(dynamics, "dynamics")
    config = prod.attrs.get("config") or {}
    if isinstance(config, str):
        config = json.loads(config)
    settings = validate_settings(config, source=dynamics)
    if settings_mapping is not None:
        from mavispm.core.config import from_mapping

        fs = from_mapping(FastStarSettings, settings_mapping, prefix="dynamics.fast_stars")
        settings = dataclasses.replace(settings, fast_stars=fs)
    elif settings.fast_stars is None:
        settings = dataclasses.replace(settings, fast_stars=FastStarSettings())
    pm_path = propermotions or prod.attrs.get("propermotions")
    if not pm_path:
        raise InputError(
            "no 'propermotions' attribute (a truth-level fit); pass --propermotions",
            path=dynamics,
        )
    if "distance" in prod.attrs and settings.distance is None:
        settings = dataclasses.replace(
            settings, distance=float(u.Quantity(prod.attrs["distance"], u.kpc).value)
        )
    if "field_radius" in prod.attrs and settings.field_radius is None:
        fr = float(u.Quantity(prod.attrs["field_radius"], u.arcsec).value)
        settings = dataclasses.replace(settings, field_radius=fr)
    stars, distance = load_stars(pm_path, settings)
    fits = stored_fits(prod, settings, stars, distance)
    result = run_on_fits(pm_path, settings, fits, distance, stars.field_radius, seed, stars=stars)
    tables = {k: v for k, v in prod.tables.items() if k != "fast_stars"}
    tables["fast_stars"] = result.table
    keep = {"format", "kind", "format_version", "mavispm_version", "created", "seed", "config"}
    attrs = {k: v for k, v in prod.attrs.items() if k not in keep and not k.startswith("fast_")}
    attrs.update(result.attrs)
    config = {**config, "fast_stars": dataclasses.asdict(settings.fast_stars)}
    path = write_product(output, "dynamics", tables=tables, attrs=attrs, config=config, seed=seed)
    if plots_dir is not None and result.possible:
        from mavispm.dynamics.plots import fast_star_plot

        fast_star_plot(result, Path(plots_dir) / "fast_stars.png")
    return path


def _handler(args) -> int:
    mapping = None
    if args.config is not None:
        import tomllib

        try:
            with open(args.config, "rb") as fh:
                table = tomllib.load(fh)
        except (OSError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"cannot read the config ({exc})", path=args.config) from None
        mapping = table.get("dynamics", {}).get("fast_stars", table.get("fast_stars", {}))
    out = run(args.dynamics, args.output, mapping, args.propermotions, args.plots, args.seed)
    from mavispm.core.products import read_product

    a = read_product(out, "dynamics", load_arrays=False).attrs
    print(
        json.dumps(
            {
                "output": str(out),
                "fast_test_possible": bool(a["fast_test_possible"]),
                "fast_n_significant": int(a["fast_n_significant"]),
                "fast_expected_false": float(a.get("fast_expected_false", float("nan"))),
                "bh_mass_lower_limit": float(u.Quantity(a["bh_mass_lower_limit"]).value),
            }
        )
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the top-level ``fast-stars`` command.

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
        "fast-stars",
        help="fast-star test (stars above the no-IMBH escape velocity) on a dynamics product",
        description="Stars faster than the escape velocity of every no-IMBH mass model, "
        "their significance, the expected false ones and the lower IMBH mass limit, "
        "from an existing dynamics product (no refit).",
    )
    p.add_argument("dynamics", help="dynamics product (HDF5)")
    p.add_argument("-o", "--output", required=True, help="dynamics product to write")
    p.add_argument("--config", default=None, help="TOML with a [dynamics.fast_stars] table")
    p.add_argument("--propermotions", default=None, help="override the product's input")
    p.add_argument("--plots", default=None, help="folder for fast_stars.png")
    p.add_argument("--seed", type=int, default=0)
    p.set_defaults(func=_handler)
    return p
