"""``mavispm simulate frames``: render catalogue epochs into stacked frames.

Stage interface (``docs/stages.md``): :func:`register`, :func:`validate_settings`
and :func:`run_stage`. The scene (TOML, keys in ``docs/render.md``) defines the
exposure, detector, photometry, accuracy knobs and the optics settings, which are
passed to ``mavispm.simulate.optics.model``.
"""

from __future__ import annotations

import argparse
import tomllib
import zlib
from collections.abc import Mapping
from pathlib import Path

import astropy.units as u
import numpy as np

from mavispm.core.catalogue import Catalogue, read_catalogue
from mavispm.core.cliargs import non_negative_int
from mavispm.core.config import to_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.frame import validate_truth
from mavispm.core.products import write_product
from mavispm.simulate.render.frame import (
    Frame,
    RenderedStack,
    make_renderer,
    render_stack,
)
from mavispm.simulate.render.scene import SceneSettings, scene_from_mapping

__all__ = [
    "build_scene_optics",
    "epoch_rng",
    "FRAMES_KIND",
    "plan_cache_dir",
    "register",
    "run_stage",
    "validate_settings",
    "write_frame",
]

FRAMES_KIND = "frames"


def _optics_module():
    try:
        from mavispm.simulate.optics import model as optics
    except ModuleNotFoundError as exc:  # pragma: no cover - depends on the build
        raise ConfigError(
            f"the optics model (mavispm.simulate.optics.model) is not available: {exc}",
            key="optics",
        ) from None
    return optics


def validate_settings(scene_mapping: Mapping | None, source=None) -> SceneSettings:
    """Check a scene mapping (a TOML document) and return :class:`SceneSettings`.

    The ``optics`` sub-table is checked by ``mavispm.simulate.optics.model.validate_settings``.

    Parameters
    ----------
    scene_mapping : mapping or None
        The stage's TOML table (keys in docs/render.md); None: all defaults.
    source : str, optional
        File name, for messages.

    Returns
    -------
    SceneSettings

    Raises
    ------
    ConfigError
        Naming the key: unknown keys, wrong types, inconsistent units, bad values.
    """
    scene = scene_from_mapping(scene_mapping, source=source)
    _optics_module().validate_settings(scene.optics, source=source)
    from mavispm.core.limits import check_memory

    det = scene.detector
    check_memory(
        float(det.nx) * float(det.ny) * BYTES_PER_PIXEL,
        f"a {det.nx} x {det.ny} pixel detector",
        "detector.nx",
        source,
    )
    return scene


#: Memory per detector pixel while a frame is made: about six float64 images
#: (mean, stack, noiseless, variance, mask, output).
BYTES_PER_PIXEL = 48


def build_scene_optics(scene: SceneSettings, cache_dir=None, progress: bool = False):
    """The optics model of a scene (``mavispm.simulate.optics.model.build_optics``).

    Parameters
    ----------
    scene : SceneSettings
    cache_dir : path, optional
        PSF-grid cache folder (default: the optics module's default).
    progress : bool
        Progress bar while a PSF grid is computed.
    """
    optics = _optics_module()
    settings = optics.validate_settings(scene.optics)
    return optics.build_optics(settings, cache_dir=cache_dir, progress=progress)


def plan_cache_dir(optics, cache_dir=None) -> Path | None:
    """Folder for the renderer's stamp-plan cache: ``cache_dir``, else the PSF-grid cache's.

    None (in memory only) when neither is known, e.g. for optics built in memory.

    Parameters
    ----------
    optics : Optics
        The scene's optics (``cache_path``: its PSF-grid cache file, or None).
    cache_dir : path, optional
        An explicit cache folder.

    Returns
    -------
    pathlib.Path or None
    """
    if cache_dir is not None:
        return Path(cache_dir)
    grid_file = getattr(optics, "cache_path", None)
    return Path(grid_file).parent if grid_file is not None else None


def epoch_rng(seed: int | None, epoch: str) -> np.random.Generator:
    """Noise generator of one epoch: independent per epoch name, reproducible per seed.

    Parameters
    ----------
    seed : int or None
        The run's noise seed (None: 0).
    epoch : str
        Epoch name ("e0", ...).

    Returns
    -------
    numpy.random.Generator
    """
    seed = 0 if seed is None else int(seed)
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(epoch.encode())]))


def _load_catalogue(catalogue) -> Catalogue:
    if isinstance(catalogue, Catalogue):
        return catalogue
    return read_catalogue(catalogue)


def _select_epoch(cat: Catalogue, epoch: str):
    if epoch not in cat.epochs:
        raise InputError(
            f"epoch '{epoch}' not in the catalogue; available: {list(cat.epochs)}", path=cat.path
        )
    table = cat.epochs[epoch]
    return table, u.Quantity(table.meta["epoch"], u.yr)


def write_frame(
    frame: Frame | RenderedStack,
    output,
    scene: SceneSettings,
    cat: Catalogue,
    seed,
    fits_path=None,
    release: bool = False,
) -> Path:
    """Write a rendered frame as the ``frames`` product (and optionally FITS), atomically.

    Parameters
    ----------
    frame : Frame or RenderedStack
        From :func:`~mavispm.simulate.render.frame.render_frame` (or
        :func:`~mavispm.simulate.render.frame.render_stack`, written without the
        round trip through float64 electrons; the same file).
    output : path
        The HDF5 product.
    scene : SceneSettings
        Recorded as the product's ``scene`` attribute and configuration.
    cat : Catalogue
        Source of ``distance``, ``ra_center``, ``dec_center`` and the FITS ``OBJECT``.
    seed : int
        Recorded as the product's seed.
    fits_path : path, optional
        Also write the image as FITS here.
    release : bool
        For a :class:`RenderedStack`: the caller is done with it, and its ``adu`` image
        is released page by page as it is written (``write_product``'s ``release``: the
        output's page cache reuses the image's memory instead of 64 MB of fresh pages for
        a 4000 x 4000 frame); it reads as zeros afterwards. The image of a ``Frame`` is
        computed here (``Frame.adu``), so it is always released.

    Returns
    -------
    pathlib.Path
        ``output``.
    """
    if isinstance(frame, RenderedStack):
        adu, truth = frame.adu, validate_truth(frame.truth)
    else:
        adu, truth = frame.adu, frame.truth  # frame.adu: two full-frame passes, done once
        release = True  # a new array, ours alone
    attrs = dict(frame.attrs)
    for key in ("distance", "ra_center", "dec_center"):
        if key in cat.attrs:
            attrs[key] = cat.attrs[key]
    scene_map = to_mapping(scene)
    attrs["scene"] = scene_map
    if fits_path is not None:
        # imported here: astropy.io.fits is ~0.03 s of CPU a process without --fits skips
        from mavispm.simulate.render.fits_output import write_frame_fits

        fits_attrs = {**attrs, "config": cat.attrs.get("config") or {}}  # OBJECT from the preset
        write_frame_fits(fits_path, adu, fits_attrs, scene_map, frame.saturated)
    arrays = {"image": u.Quantity(adu, u.adu, copy=False), "saturated": frame.saturated}
    if scene.save_noiseless:
        arrays["noiseless"] = u.Quantity(frame.noiseless.astype(np.float32), u.electron)
    return write_product(
        output,
        FRAMES_KIND,
        tables={"truth": truth},
        arrays=arrays,
        attrs=attrs,
        config={"scene": scene_map},
        seed=seed,
        release=("image",) if release else (),
    )


def run_stage(
    catalogue,
    epoch: str,
    scene,
    output,
    seed,
    fits_path=None,
    *,
    optics=None,
    renderer=None,
    progress: bool = False,
    cache_dir=None,
) -> Path:
    """Render one epoch of a catalogue into a ``frames`` product.

    Parameters
    ----------
    catalogue : path or Catalogue
        The cluster catalogue product.
    epoch : str
        Epoch table name ("e0", ...).
    scene : mapping or SceneSettings
        Scene settings (TOML mapping).
    output : path
        The frames HDF5 product (written atomically).
    seed : int
        Noise seed; each epoch draws independent noise from (seed, epoch name).
    fits_path : path, optional
        Also write the image as FITS.
    optics : object, optional
        A prebuilt optics model (default: built from ``scene.optics``).
    renderer : StarRenderer, optional
        Reuse cached PSF transforms across epochs.
    progress : bool
        Progress bars.
    cache_dir : path, optional
        PSF-grid cache folder for the optics model; the stamp plans (PSF-node
        transforms) and the halo profile are cached there too, so the other
        epochs of the scene, rendered by other calls or processes, reuse them.
        Default: the folder of the PSF-grid cache file the optics came from
        (``optics.cache_path``), or no disk cache when the optics have none.

    Returns
    -------
    pathlib.Path
        ``output``.
    """
    cat = _load_catalogue(catalogue)
    settings = scene_from_mapping(scene)
    table, t = _select_epoch(cat, epoch)
    from mavispm.simulate.render.frame import check_drawable

    try:
        check_drawable(table, settings)
    except InputError as exc:
        path = getattr(cat, "path", None) or (
            catalogue if isinstance(catalogue, (str, Path)) else None
        )
        raise InputError(f"epoch '{epoch}': {exc}", path=path) from None
    if optics is None:
        optics = build_scene_optics(settings, cache_dir, progress)
    if renderer is None:
        renderer = make_renderer(optics, settings, plan_cache_dir(optics, cache_dir))
    stack = render_stack(
        table,
        t,
        settings,
        optics,
        epoch_rng(seed, epoch),
        renderer=renderer,
        progress=progress,
        noiseless=settings.save_noiseless,  # not written otherwise: not scaled either
    )
    # the stack is ours alone: its image's memory goes to the output's page cache
    return write_frame(stack, output, settings, cat, seed, fits_path, release=True)


def _read_scene(path) -> tuple[dict, str]:
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise InputError("scene file does not exist", path=path) from None
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"not a readable TOML scene file ({exc})", path=path) from None
    if set(data) == {"scene"} and isinstance(data["scene"], dict):
        data = data["scene"]
    return data, str(path)


def _handle(args: argparse.Namespace) -> int:
    mapping, source = _read_scene(args.scene) if args.scene else ({}, None)
    scene = validate_settings(mapping, source=source)
    cat = read_catalogue(args.catalogue)
    names = list(cat.epochs)
    many = args.epoch == "all"
    if many:
        todo = names
    elif args.epoch is not None:
        todo = [args.epoch]
    elif len(names) == 1:
        todo = names
    else:
        raise InputError(
            f"the catalogue has epochs {names}; choose one with --epoch or use --epoch all",
            path=args.catalogue,
        )
    optics = build_scene_optics(scene, args.cache_dir, args.progress)
    renderer = make_renderer(optics, scene, plan_cache_dir(optics, args.cache_dir))
    for name in todo:
        out = Path(args.output) / f"frames_{name}.h5" if many else Path(args.output)
        fits_path = None
        if args.fits_dir:
            fits_path = Path(args.fits_dir) / f"frames_{name}.fits"
        elif args.fits and not many:
            fits_path = Path(args.fits)
        run_stage(
            cat,
            name,
            scene,
            out,
            args.seed,
            fits_path,
            optics=optics,
            renderer=renderer,
            progress=args.progress,
        )
        print(f"wrote {out}" + (f" and {fits_path}" if fits_path else ""))
    return 0


def register(subparsers) -> None:
    """Add the ``frames`` sub-command (``mavispm simulate frames``).

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The sub-parsers of the ``mavispm`` parser (or of its command group).
    """
    p = subparsers.add_parser(
        "frames",
        help="render catalogue epochs into stacked MAVIS frames",
        description="Render one epoch (or all) of a cluster catalogue into a stacked frame "
        "(HDF5 'frames' product, optional FITS).",
    )
    p.add_argument("catalogue", help="cluster catalogue product (HDF5)")
    p.add_argument("--scene", help="scene TOML (keys: docs/render.md); defaults if omitted")
    p.add_argument(
        "--epoch", help="epoch name (e0, e1, ...) or 'all' (then -o is a folder)", default=None
    )
    p.add_argument("-o", "--output", required=True, help="frames product (or folder for 'all')")
    p.add_argument("--fits", help="also write the image as this FITS file")
    p.add_argument("--fits-dir", help="write FITS copies into this folder (frames_<epoch>.fits)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="noise seed (default 0)")
    p.add_argument(
        "--cache-dir", help="PSF-grid and stamp-plan cache folder (default: the optics default)"
    )
    p.add_argument("--progress", action="store_true", help="show progress bars")
    p.set_defaults(func=_handle)
