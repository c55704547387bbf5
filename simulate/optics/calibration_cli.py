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

__all__ = [
    "load_mask_settings",
    "register",
    "run_calibration",
    "run_stage",
    "validate_settings",
    "write_report",
]


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


def validate_settings(settings: Mapping | None, source=None) -> CalibrationMaskSettings:
    """The :class:`CalibrationMaskSettings` of a ``[calibration]`` table.

    Parameters
    ----------
    settings : mapping or CalibrationMaskSettings or None
        The table (None: defaults); a settings object is returned as is.
    source : str, optional
        File named in error messages.

    Returns
    -------
    CalibrationMaskSettings
        The validated settings.

    Raises
    ------
    ConfigError
        Naming the first bad key.
    """
    if isinstance(settings, CalibrationMaskSettings):
        return settings
    return from_mapping(
        CalibrationMaskSettings, dict(settings or {}), prefix="calibration", source=source
    )


def run_stage(
    settings: Mapping | None,
    distortion: Mapping | None,
    output: str | Path,
    seed: int | None = None,
    scene: Mapping | None = None,
) -> Path:
    """The workflow's calibration stage: calibrate a scene's distortion, write the product.

    Parameters
    ----------
    settings : mapping
        The mask table (``[scenes.NAME.calibration]``).
    distortion : mapping
        The scene's ``[scene.optics.distortion]`` table (without ``calibration``).
    output : path
        The calibration product to write (atomically).
    seed : int, optional
        Seed of the hole errors and centroid noise when the table sets no ``seed``.
    scene : mapping, optional
        The scene (``[scene]``) whose PSF and detector image the holes when the mask's
        ``imaging`` is "rendered".

    Returns
    -------
    Path
        ``output``.
    """
    table = dict(settings or {})
    if seed is not None and "seed" not in table:
        table["seed"] = int(seed)
    run_calibration(distortion or {}, validate_settings(table), output, scene=scene)
    return Path(output)


def write_report(paths, outdir) -> list[Path]:
    """Markdown table of the input and post-calibration distortion of calibration products.

    Parameters
    ----------
    paths : list of path
        Calibration products.
    outdir : path
        Folder of the report (created).

    Returns
    -------
    list of Path
        The Markdown file written.
    """
    from mavispm.core.atomic import atomic_path
    from mavispm.core.products import read_product

    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    lines = [
        "| product | method | order | input distortion RMS [mas] | residual RMS [mas] |",
        "|---|---|---|---|---|",
    ]
    for path in map(Path, paths):
        attrs = read_product(path, "calibration", load_arrays=False).attrs
        lines.append(
            f"| {path.parent.name}/{path.name} | {attrs['method']} | {int(attrs['order'])} | "
            f"{attrs['input_rms'].to_value('mas'):.4f} | "
            f"{attrs['residual_rms'].to_value('mas'):.5f} |"
        )
    target = outdir / "calibration.md"
    with atomic_path(target) as tmp:
        tmp.write_text(
            'Distortion over the science field (r <= 15"), both axes, mean removed, before '
            "and after the calibration mask (docs/optics.md).\n\n" + "\n".join(lines) + "\n"
        )
    return [target]


def hole_imager(mask: CalibrationMaskSettings, scene: Mapping | None, source=None):
    """The imager of ``mask`` (None: analytic centroid noise), rendering through ``scene``.

    Parameters
    ----------
    mask : CalibrationMaskSettings
        The mask (``imaging``, ``hole_magnitude``, ``seed``).
    scene : mapping or None
        The ``[scene]`` table the holes are rendered through.
    source : str, optional
        File named in error messages.

    Returns
    -------
    callable or None
        The rendered-hole imager; None for analytic imaging.

    Raises
    ------
    ConfigError
        Rendered imaging without a scene.
    """
    if mask.imaging != "rendered":
        return None
    if scene is None:
        raise ConfigError(
            "imaging = 'rendered' renders the holes through a scene; give one (--scene)",
            key="calibration.imaging",
            source=source,
        )
    from mavispm.simulate.optics.pinhole_imaging import rendered_hole_imager
    from mavispm.simulate.render import cli as render_cli

    settings = render_cli.validate_settings(scene, source=source)
    optics = render_cli.build_scene_optics(settings)
    return rendered_hole_imager(settings, optics, mask.hole_magnitude, seed=mask.seed)


def run_calibration(
    distortion: Mapping | DistortionSettings | None,
    mask: CalibrationMaskSettings,
    output: str | Path,
    source=None,
    scene: Mapping | None = None,
) -> CalibrationResult:
    """Simulate the calibration of ``distortion`` and write the product to ``output``.

    ``scene`` (a ``[scene]`` mapping) is needed when the mask's ``imaging`` is
    "rendered": its PSF, detector and noise image the holes.

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
    scene : mapping, optional
        The ``[scene]`` table whose PSF, detector and noise image the holes when the
        mask's ``imaging`` is "rendered".

    Returns
    -------
    CalibrationResult
        The measured holes and the recovered distortion.
    """
    if not isinstance(distortion, DistortionSettings):
        distortion = from_mapping(
            DistortionSettings, distortion, prefix="scene.optics.distortion", source=source
        )
    imager = hole_imager(mask, scene, source)
    result = simulate_calibration(Distortion(distortion), mask, imager=imager)
    from mavispm.core.config import to_mapping

    write_calibration(output, result, distortion_config=to_mapping(distortion))
    return result


def _handler(args: argparse.Namespace) -> int:
    optics = load_scene_optics(args.scene) if args.scene else {}
    scene = None
    if args.scene:
        data = tomllib.loads(Path(args.scene).read_text())  # checked by load_scene_optics
        scene = data.get("scene", data)
    overrides = {"order": args.order, "method": args.method, "seed": args.seed}
    if args.seed is not None and args.seed < 0:
        raise ConfigError("expected a seed >= 0", key="--seed")
    mask = load_mask_settings(args.mask, overrides)
    out = Path(args.output)
    if out.is_dir():
        raise InputError("output is a folder; expected an HDF5 file name", path=out)
    result = run_calibration(
        optics.get("distortion", {}), mask, out, source=args.scene, scene=scene
    )
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
