"""``mavispm simulate calibration``: image the pinhole mask and recover the distortion.

Reads the distortion of a scene (``[scene.optics.distortion]``) and the mask settings
(``[calibration]`` of a mask TOML file, keys of
:class:`~mavispm.simulate.optics.calibration_mask.CalibrationMaskSettings`), simulates
the calibration and writes a ``calibration`` product (docs/formats.md). A scene whose
``[scene.optics.distortion] calibration`` names that product renders frames with the
post-calibration residual distortion.
"""

from __future__ import annotations

import argparse
import tomllib
from collections.abc import Mapping
from pathlib import Path

from mavispm.core.config import from_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.simulate.optics.calibration_mask import (
    CalibrationMaskSettings,
    CalibrationResult,
    simulate_calibration,
    write_calibration,
)
from mavispm.simulate.optics.cli import load_scene_optics
from mavispm.simulate.optics.distortion import Distortion, DistortionSettings

__all__ = ["register", "run_calibration", "load_mask_settings"]


def load_mask_settings(path: str | Path | None, overrides: Mapping | None = None):
    """The :class:`CalibrationMaskSettings` of a mask TOML file plus CLI overrides.

    The file holds a ``[calibration]`` table (or the keys at its top level).

    Parameters
    ----------
    path : str or pathlib.Path or None
        The TOML file (None: defaults).
    overrides : mapping, optional
        Command-line values, overriding the file's.

    Returns
    -------
    CalibrationMaskSettings
        The validated mask settings.
    """
    table: dict = {}
    source = None
    if path is not None:
        path = Path(path)
        source = str(path)
        if not path.is_file():
            raise InputError("mask settings file does not exist", path=path)
        try:
            data = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise ConfigError(f"invalid TOML ({exc})", source=source) from None
        table = data.get("calibration", data)
        if not isinstance(table, Mapping):
            raise ConfigError("expected a table", key="calibration", source=source)
        table = dict(table)
    table.update({k: v for k, v in (overrides or {}).items() if v is not None})
    return from_mapping(CalibrationMaskSettings, table, prefix="calibration", source=source)


def run_calibration(
    distortion: Mapping | DistortionSettings | None,
    mask: CalibrationMaskSettings,
    output: str | Path,
    source=None,
) -> CalibrationResult:
    """Simulate the calibration of ``distortion`` and write the product to ``output``.

    Parameters
    ----------
    distortion : mapping or DistortionSettings or None
        The ``[scene.optics.distortion]`` table (None: defaults).
    mask : CalibrationMaskSettings
        The mask and the fit.
    output : str or pathlib.Path
        The ``calibration`` product written.
    source : str, optional
        File named in error messages.

    Returns
    -------
    CalibrationResult
        The measured holes and the recovered distortion.
    """
    if not isinstance(distortion, DistortionSettings):
        distortion = from_mapping(
            DistortionSettings, distortion, prefix="scene.optics.distortion", source=source
        )
    result = simulate_calibration(Distortion(distortion), mask)
    from mavispm.core.config import to_mapping

    write_calibration(output, result, distortion_config=to_mapping(distortion))
    return result


def _handler(args: argparse.Namespace) -> int:
    optics = load_scene_optics(args.scene) if args.scene else {}
    overrides = {"order": args.order, "method": args.method, "seed": args.seed}
    if args.seed is not None and args.seed < 0:
        raise ConfigError("expected a seed >= 0", key="--seed")
    mask = load_mask_settings(args.mask, overrides)
    out = Path(args.output)
    if out.is_dir():
        raise InputError("output is a folder; expected an HDF5 file name", path=out)
    result = run_calibration(optics.get("distortion", {}), mask, out, source=args.scene)
    print(
        f"wrote {out}: input distortion {result.input_rms:.4f} mas RMS, "
        f"residual after calibration {result.residual_rms:.5f} mas RMS "
        f"({mask.method}, order {mask.order}, {mask.n_holes}x{mask.n_holes} holes)"
    )
    return 0


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``calibration`` sub-command.

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
        "calibration",
        help="image the astrometric calibration mask and recover the distortion",
        description="Image a pinhole mask through a scene's static and dynamic distortion, "
        "measure the holes, fit a polynomial distortion (differential or direct method) and "
        "write the recovered distortion and its residual as a calibration product.",
    )
    p.add_argument(
        "--scene", help="scene TOML file ([scene.optics.distortion]); defaults if omitted"
    )
    p.add_argument("--mask", help="mask settings TOML file ([calibration] table)")
    p.add_argument("--order", type=int, help="polynomial order (overrides the mask file)")
    p.add_argument(
        "--method", choices=("differential", "direct"), help="recovery method (overrides)"
    )
    p.add_argument("--seed", type=int, help="seed of hole errors and noise (overrides)")
    p.add_argument("-o", "--output", required=True, help="output calibration HDF5 file")
    p.set_defaults(func=_handler)
    return p
