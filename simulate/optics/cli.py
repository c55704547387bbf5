"""``mavispm simulate optics``: build/cache the PSF grid and draw the optics plots.

Stage interface (docs/stages.md): ``register(subparsers)``,
``validate_settings(settings, source=None)`` and ``run_stage(settings, output) -> Path``.
"""

from __future__ import annotations

import argparse
import tomllib
from collections.abc import Mapping
from pathlib import Path

import astropy.units as u
import numpy as np

from mavispm.core.config import to_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.simulate.optics.model import Optics, OpticsSettings, build_optics
from mavispm.simulate.optics.model import validate_settings as _validate
from mavispm.simulate.optics.psf_grid import PSFGrid, read_grid, write_grid
from mavispm.simulate.optics.tiptilt import kernel_map


def validate_settings(
    settings: Mapping | OpticsSettings | None, source: str | None = None
) -> OpticsSettings:
    """The :class:`OpticsSettings` of a ``[scene.optics]`` table.

    Parameters
    ----------
    settings : mapping or OpticsSettings or None
        The table (None: defaults); a settings object is returned as is.
    source : str, optional
        File named in error messages.

    Returns
    -------
    OpticsSettings
        The validated settings.

    Raises
    ------
    ConfigError
        Naming the first bad key.
    """
    if isinstance(settings, OpticsSettings):
        return settings
    return _validate(settings, source=source)


def run_stage(
    settings: Mapping | OpticsSettings | None,
    output: str | Path,
    cache_dir: Path | None = None,
    progress: bool = True,
) -> Path:
    """Build (or fetch from the cache) the PSF grid and write it as a ``psfgrid`` product.

    Parameters
    ----------
    settings : mapping or OpticsSettings
        The ``[scene.optics]`` table.
    output : path
        The HDF5 product to write (atomically).
    cache_dir : Path, optional
        PSF-grid cache folder.
    progress : bool
        Progress bar while a PSF grid is computed (on a terminal only).

    Returns
    -------
    Path
        ``output``.
    """
    return _build_and_write(validate_settings(settings), output, cache_dir, progress)[0]


def _build_and_write(
    s: OpticsSettings, output: str | Path, cache_dir: Path | None, progress: bool
) -> tuple[Path, Optics]:
    """Build the optics and write the grid product; returns (path, optics)."""
    optics = build_optics(s, cache_dir=cache_dir, progress=progress)
    output = Path(output)
    if optics.cache_path is not None and optics.cache_path.exists():
        result = read_grid(optics.cache_path)
        key = optics.cache_path.stem.removeprefix("psfgrid-")
    else:  # pragma: no cover - the cache always writes a file
        raise InputError("PSF grid cache file missing after build", path=optics.cache_path)
    arrays, attrs = tiptilt_product_fields(optics, result.grid)
    write_grid(output, result, key, config=to_mapping(s), extra_arrays=arrays, extra_attrs=attrs)
    return output, optics


def tiptilt_product_fields(optics: Optics, grid: PSFGrid) -> tuple[dict, dict]:
    """The TT kernel map on the grid nodes and the conditions, for the ``psfgrid`` product.

    Parameters
    ----------
    optics : Optics
        The scene's optics.
    grid : PSFGrid
        The PSF grid whose nodes [arcsec] are used.

    Returns
    -------
    arrays : dict
        ``tt_sigma_major``, ``tt_sigma_minor`` [mas] and ``tt_angle`` [deg] (major-axis
        position angle from +x towards +y), each (n_nodes_y, n_nodes_x).
    attrs : dict
        ``seeing`` [arcsec], ``zenith_angle`` [deg], ``asterism``, ``tt_scale_factor``.
    """
    gx, gy = np.meshgrid(grid.nodes_x, grid.nodes_y)
    km = kernel_map(optics.tiptilt, gx, gy)
    s = optics.settings
    arrays = {
        "tt_sigma_major": km.sigma_major * u.mas,
        "tt_sigma_minor": km.sigma_minor * u.mas,
        "tt_angle": km.angle * u.deg,
    }
    attrs = {
        "seeing": s.atmosphere.seeing * u.arcsec,
        "zenith_angle": s.atmosphere.zenith_angle * u.deg,
        "asterism": s.tiptilt.asterism if s.tiptilt.enabled else "none",
        "tt_scale_factor": float(s.tiptilt.scale_factor),
    }
    return arrays, attrs


def load_scene_optics(path: str | Path) -> Mapping:
    """The ``[scene.optics]`` table of a scene TOML file (empty when absent).

    The file's ``[scene]`` table is used when present, else its top level.

    Parameters
    ----------
    path : str or pathlib.Path
        The scene TOML file.

    Returns
    -------
    mapping
        The optics table.

    Raises
    ------
    InputError
        When the file does not exist.
    ConfigError
        When it is not valid TOML, has unknown ``[scene]`` keys, or ``optics`` is not a
        table.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("scene file does not exist", path=path)
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"invalid TOML ({exc})", source=str(path)) from None
    scene = data.get("scene", data)
    if isinstance(scene, Mapping):  # a typo ([opticz]) must not silently mean "defaults"
        import dataclasses

        from mavispm.core.config import check_known_keys
        from mavispm.simulate.render.scene import SceneSettings

        known = [f.name for f in dataclasses.fields(SceneSettings)]
        check_known_keys(scene, known, "scene" if "scene" in data else "", str(path))
        if "scene" in data:
            check_known_keys(data, ["scene"], "", str(path))
    optics = scene.get("optics", {}) if isinstance(scene, Mapping) else {}
    if not isinstance(optics, Mapping):
        raise ConfigError("expected a table", key="scene.optics", source=str(path))
    return optics


def _handler(args: argparse.Namespace) -> int:
    table = load_scene_optics(args.scene) if args.scene else {}
    settings = validate_settings(table, source=str(args.scene) if args.scene else None)
    cache = Path(args.cache_dir) if args.cache_dir else None
    out, optics = _build_and_write(settings, args.output, cache, not args.quiet)
    print(f"wrote {out}")
    if args.plots:
        from mavispm.simulate.optics.plots import draw_all

        for p in draw_all(optics, Path(args.plots)):
            print(f"wrote {p}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add the ``optics`` sub-command.

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
        "optics",
        help="build/cache the field-variable PSF grid and draw the optics plots",
        description="Build (or load from the cache) the MCAO PSF grid of a scene, write it "
        "as a psfgrid HDF5 product, and optionally draw PSF thumbnails, the radial "
        "profile, the tip-tilt ellipse map and the static distortion map.",
    )
    p.add_argument("--scene", help="scene TOML file ([scene.optics] table); defaults if omitted")
    p.add_argument("-o", "--output", required=True, help="output psfgrid HDF5 file")
    p.add_argument("--plots", help="folder for the PNG plots")
    p.add_argument("--cache-dir", help="PSF grid cache folder (default $MAVISPM_CACHE)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_handler)
    return p


__all__ = ["register", "run_stage", "validate_settings", "load_scene_optics"]
