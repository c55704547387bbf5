"""The ``stars`` stage: ``mavispm measure stars frames.h5 -o measured.h5``.

Stage interface (docs/stages.md): :func:`register`, :func:`validate_settings`,
:func:`run_stage` and :func:`write_report`.
"""

from __future__ import annotations

import argparse
import json
import os
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import astropy.units as u
import numpy as np

from mavispm.core.cliargs import non_negative_int
from mavispm.core.config import from_mapping, to_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.frame import Frame
from mavispm.core.products import write_product
from mavispm.measure.stars import accuracy_report
from mavispm.measure.stars.measure_frame import measure_frame, read_frame
from mavispm.measure.stars.psf_reconstruction import check_prior
from mavispm.measure.stars.settings import MeasureSettings, nest_knobs
from mavispm.measure.stars.start_list import read_earlier

if TYPE_CHECKING:
    from astropy.table import QTable

    from mavispm.measure.stars.variable_psf import VariableEPSF

__all__ = [
    "add_fitted_magnitudes",
    "measure_stars",
    "MEASURED_KIND",
    "register",
    "run_stage",
    "validate_settings",
    "write_measured",
    "write_report",
]

MEASURED_KIND = "measured"

#: Detector attributes of the frame copied to the measured product.
_COPIED_ATTRS = (
    "epoch",
    "pixel_scale",
    "gain",
    "read_noise",
    "saturation",
    "sky",
    "nexp",
    "exptime",
    "zero_point",
)


def validate_settings(settings: Mapping | None, source: str | None = None) -> MeasureSettings:
    """Build :class:`MeasureSettings` from a mapping (a TOML table).

    Knobs may be given flat or in ``knobs`` (:func:`~mavispm.measure.stars.settings.nest_knobs`).

    Parameters
    ----------
    settings : mapping or None
        The stage's TOML table (keys in docs/measure.md); None: all defaults.
    source : str, optional
        File name, for messages.

    Returns
    -------
    MeasureSettings

    Raises
    ------
    ConfigError
        Unknown keys, wrong types, bad units or impossible values, naming the key.
    """
    return from_mapping(MeasureSettings, nest_knobs(settings, source), source=source)


def add_fitted_magnitudes(stars: QTable, attrs: Mapping) -> None:
    """Add ``mag_fit`` and ``mag_fit_err`` [mag] from the fitted fluxes (in place).

    ``mag_fit = zero_point - 2.5 log10(flux / (exptime nexp))`` with the frame's
    photometric ``zero_point`` [mag for 1 electron/s]: a PSF magnitude, the light
    inside the ePSF footprint (no aperture correction, so fainter than the total
    magnitude by ``-2.5 log10(epsf_flux_fraction)`` when a seeing halo spreads
    light beyond it). ``mag_fit_err = 2.5 / ln 10 * flux_err / flux``. NaN where
    the flux is not positive or the frame has no zero point.

    Parameters
    ----------
    stars : QTable
        Measured stars with ``flux``, ``flux_err`` [electron].
    attrs : mapping
        Frame attributes: ``zero_point`` [mag], ``exptime`` [s], ``nexp``.
    """
    flux = stars["flux"].to_value(u.electron)
    err = stars["flux_err"].to_value(u.electron)
    mag = np.full(len(stars), np.nan)
    mag_err = np.full(len(stars), np.nan)
    if "zero_point" in attrs and "exptime" in attrs:
        zp = u.Quantity(attrs["zero_point"], u.mag).value
        total = u.Quantity(attrs["exptime"], u.s).value * int(attrs.get("nexp", 1))
        with np.errstate(all="ignore"):
            ok = np.isfinite(flux) & (flux > 0)
            mag[ok] = zp - 2.5 * np.log10(flux[ok] / total)
            mag_err[ok] = 2.5 / np.log(10.0) * err[ok] / flux[ok]
    stars["mag_fit"] = mag * u.mag
    stars["mag_fit_err"] = mag_err * u.mag


def measure_stars(
    frame: Frame,
    settings: Mapping | MeasureSettings | None = None,
    seed: int | None = None,
    earlier: Sequence | None = None,
) -> tuple[QTable, VariableEPSF]:
    """Measure every star of a frame in memory.

    Parameters
    ----------
    frame : Frame or astropy.nddata.NDData
        A rendered frame (:func:`mavispm.render_epoch`), one read from a
        ``frames`` product (:func:`~mavispm.measure.stars.measure_frame.read_frame`),
        or an NDData in adu whose ``meta`` holds the frame attributes and, for
        forced photometry, ``truth`` (:meth:`~mavispm.core.frame.Frame.from_nddata`).
    settings : mapping or MeasureSettings, optional
        Stage settings (see :class:`MeasureSettings`); default: all defaults.
    seed : int, optional
        Seed of the forced-position perturbation.
    earlier : sequence, optional
        Earlier epochs' measured stars (:func:`~mavispm.measure.stars.start_list.read_earlier`);
        with ``later_epochs = "measured"`` (observer mode) the frame starts from them.

    Returns
    -------
    stars : QTable
        The ``stars`` table of the ``measured`` product (docs/formats.md), with
        units, including the measured magnitude ``mag_fit`` [mag]
        (:func:`add_fitted_magnitudes`; ``mag`` is the input magnitude); ``stars.meta`` holds the product's root attributes (the frame's
        ``epoch`` [yr], detector attributes, engine, timings, ePSF description).
    psf : VariableEPSF
        The frame's ePSF.
    """
    cfg = settings if isinstance(settings, MeasureSettings) else validate_settings(settings)
    if not isinstance(frame, Frame):  # an astropy NDData in adu with the frame attributes
        frame = Frame.from_nddata(frame)
    earlier = list(earlier or ())
    carried = bool(earlier) and cfg.later_epochs == "measured"
    if frame.truth is None and not (cfg.blind or carried):
        raise InputError(
            "the frame has no truth table: forced photometry needs the input star list "
            "(use blind mode to detect stars instead)",
            path=frame.path,
        )
    stars, attrs, psf = measure_frame(frame, cfg, seed, earlier=earlier)
    add_fitted_magnitudes(stars, frame.attrs)
    copied = {k: frame.attrs[k] for k in _COPIED_ATTRS if k in frame.attrs}
    psf_meta = json.dumps({"kind": psf.kind, "oversampling": psf.oversampling, **psf.meta})
    stars.meta.update({**copied, **attrs, "epsf": psf_meta})
    if frame.path is not None:
        stars.meta["frames"] = str(frame.path)
    return stars, psf


def run_stage(
    frames: str | os.PathLike,
    settings: Mapping | MeasureSettings | None,
    output: str | os.PathLike,
    seed: int | None = None,
    earlier: Sequence | None = None,
    psf_prior: str | os.PathLike | None = None,
) -> Path:
    """Measure every star of a ``frames`` product and write the ``measured`` product.

    Parameters
    ----------
    frames : path
        Input ``frames`` product.
    settings : mapping or MeasureSettings
        Stage settings (see :class:`MeasureSettings`).
    output : path
        Output ``measured`` product (written atomically).
    seed : int, optional
        Seed of the forced-position perturbation.
    earlier : sequence of path, optional
        ``measured`` products of earlier epochs. With ``later_epochs =
        "measured"`` (the default, observer mode) the frame starts from their
        measured positions instead of the truth (docs/measure.md).
    psf_prior : path, optional
        ``psfgrid`` product of the scene's optics (a workflow's optics node): the PSF-R
        prior, used unless the settings name one (``psf_prior``) or ``psf_model = "epsf"``.

    Returns
    -------
    pathlib.Path
    """
    cfg = settings if isinstance(settings, MeasureSettings) else validate_settings(settings)
    if psf_prior is not None and not cfg.psf_prior:
        cfg = cfg.replace(psf_prior=str(psf_prior))
    if cfg.uses_psfr and cfg.psf_prior:
        check_prior(cfg.psf_prior)  # before the frame is read: a bad prior costs nothing
    previous = [read_earlier(p) for p in (earlier or ())]
    carried = bool(previous) and cfg.later_epochs == "measured"
    frame = read_frame(frames, require_truth=not (cfg.blind or carried))
    try:
        stars, psf = measure_stars(frame, cfg, seed, earlier=previous)
    except InputError as exc:
        if exc.path is not None:
            raise
        raise InputError(str(exc), path=frames) from None  # name the frame measured
    return write_measured(output, stars, psf, cfg, seed)


def write_measured(
    output: str | Path,
    stars: QTable,
    psf: VariableEPSF,
    settings: MeasureSettings,
    seed: int | None = None,
) -> Path:
    """Write a ``measured`` product (atomically) from :func:`measure_stars`' results.

    Parameters
    ----------
    output : path
        The product to write.
    stars : QTable
        Measured stars; ``stars.meta`` becomes the root attributes.
    psf : VariableEPSF
        The frame's ePSF (its basis is stored as ``epsf_basis``).
    settings : MeasureSettings
        Recorded as the product's configuration.
    seed : int, optional
        Recorded as the product's seed.

    Returns
    -------
    pathlib.Path
        ``output``.
    """
    attrs = dict(stars.meta)
    table = stars.copy(copy_data=False)
    table.meta.clear()
    return write_product(
        output,
        MEASURED_KIND,
        tables={"stars": table},
        arrays={"epsf_basis": psf.basis},
        attrs=attrs,
        config=to_mapping(settings),
        seed=seed,
    )


def write_report(measured_paths: Sequence, outdir: str | os.PathLike) -> list[Path]:
    """Accuracy report (ECSV, Markdown, PNG) of measured products, per epoch.

    Parameters
    ----------
    measured_paths : sequence of path
        ``measured`` products with truth columns.
    outdir : path
        Output folder (created).

    Returns
    -------
    list of pathlib.Path
        See :func:`mavispm.measure.stars.accuracy_report.write_report`.
    """
    return accuracy_report.write_report(measured_paths, outdir)


def _load_config(path) -> dict:
    if path is None:
        return {}
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read settings ({exc})", key="--config", source=path) from None
    return dict(data.get("stars", data))


def _handler(args: argparse.Namespace) -> int:
    settings = _load_config(args.config)
    if args.engine is not None:
        settings["engine"] = args.engine
    if args.blind:
        settings["blind"] = True
    if args.psf is not None:
        settings["psf_variation"] = args.psf
    if args.progress:
        settings["progress"] = True
    if args.psf_prior is not None:
        settings["psf_prior"] = args.psf_prior
    cfg = validate_settings(settings, source=args.config)
    out = run_stage(args.frames, cfg, args.output, args.seed, earlier=args.earlier)
    print(f"wrote {out}")
    if args.report is not None:
        for path in write_report([out], args.report):
            print(f"wrote {path}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``stars`` sub-command.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The sub-parsers of the ``mavispm`` parser (or of its command group).
    """
    p = subparsers.add_parser(
        "stars",
        help="build the ePSF and fit every star of a frame (forced or blind)",
        description="Measure star positions and fluxes in a frames product by ePSF fitting.",
    )
    p.add_argument("frames", help="input frames product (HDF5)")
    p.add_argument("-o", "--output", required=True, help="output measured product (HDF5)")
    p.add_argument("--engine", choices=("fast", "photutils"), default=None, help="fitting engine")
    p.add_argument(
        "--psf", choices=("constant", "grid", "polynomial"), default=None, help="ePSF variation"
    )
    p.add_argument(
        "--psf-prior",
        default=None,
        metavar="PSFGRID",
        help="psfgrid product of the optics (PSF-R prior): fit the PSF-R model instead of an ePSF",
    )
    p.add_argument("--blind", action="store_true", help="detect stars instead of forced positions")
    p.add_argument(
        "--earlier",
        nargs="+",
        default=None,
        metavar="MEASURED",
        help="measured products of earlier epochs: start from their positions (observer mode)",
    )
    p.add_argument("--config", default=None, help="TOML settings file (table [stars] or top level)")
    p.add_argument(
        "--seed", type=non_negative_int, default=0, help="seed of the position perturbation"
    )
    p.add_argument(
        "--report", default=None, metavar="DIR", help="also write the accuracy report here"
    )
    p.add_argument("--progress", action="store_true", help="show progress bars")
    p.set_defaults(func=_handler)
    return p
