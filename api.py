"""The in-memory Python API: every stage as a function of astropy objects.

``import mavispm`` gives these names (imported on first use, so ``import
mavispm`` stays fast). Each function takes and returns what the matching
command reads and writes, in memory:

=========================  =============================  ==============================
function                   takes                          returns
=========================  =============================  ==============================
:func:`simulate_cluster`   ``[cluster]`` settings, seed   :class:`Catalogue` (QTables)
:func:`build_optics`       ``[scene.optics]`` settings    optics model (PSF grid ...)
:func:`render_epoch`       catalogue, epoch, scene        :class:`Frame`
:func:`measure_stars`      :class:`Frame`                 QTable of measured stars
:func:`proper_motions`     measured QTables of epochs     QTable of proper motions
:func:`fit_dynamics`       proper-motion QTable           :class:`DynamicsResult`
=========================  =============================  ==============================

Settings are mappings (the TOML tables of ``docs/*.md``, quantities as strings
such as ``"4.5 arcsec"`` or as :class:`~astropy.units.Quantity`) or the stage's
settings dataclass. Tables carry units; ``table.meta`` carries what the product
files hold as root attributes (epoch, distance, ...). The command-line stages
call these same functions and write their results (docs/stages.md), so a chain
run in memory gives the numbers the files would hold.

Example
-------
The README's "Python API" section chains the whole pipeline; one stage alone:

>>> import mavispm
>>> cat = mavispm.simulate_cluster(
...     {"preset": "ngc3201", "n_stars": 50, "field_size": "2 arcsec", "epochs": [0, 5]}, seed=1)
>>> list(cat.epochs), cat.epochs["e0"]["x"].unit
(['e0', 'e1'], Unit("arcsec"))
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import TYPE_CHECKING

import astropy.units as u

from mavispm.core.catalogue import Catalogue, read_catalogue
from mavispm.core.errors import InputError
from mavispm.core.frame import Frame
from mavispm.dynamics.cli import DynamicsResult, fit_dynamics
from mavispm.measure.propermotions.cli import proper_motions
from mavispm.measure.stars.cli import measure_stars
from mavispm.measure.stars.measure_frame import read_frame

if TYPE_CHECKING:
    from mavispm.simulate.optics.model import Optics, OpticsSettings
    from mavispm.simulate.render.stamps import StarRenderer

__all__ = [
    "Catalogue",
    "DynamicsResult",
    "Frame",
    "build_optics",
    "fit_dynamics",
    "measure_stars",
    "proper_motions",
    "read_catalogue",
    "read_frame",
    "render_epoch",
    "simulate_cluster",
]


def simulate_cluster(settings: Mapping | None = None, seed: int = 0) -> Catalogue:
    """Simulate (or import) a cluster catalogue in memory.

    Parameters
    ----------
    settings : mapping or ClusterSettings, optional
        The ``[cluster]`` table (docs/cluster.md), including ``epochs`` [yr];
        default: the defaults.
    seed : int
        Random seed.

    Returns
    -------
    Catalogue
        ``epochs``: epoch name ("e0", ...) to QTable (``id``, ``x``, ``y``
        [arcsec], ``pm_x``, ``pm_y`` [mas/yr], ``mag`` [mag], ...) with
        ``meta["epoch"]`` [yr]; ``attrs``: ``distance`` [kpc], ``imbh_mass``
        [solMass], ... (the ``catalogue`` product in memory).
    """
    from mavispm.core.catalogue import _validate_epoch
    from mavispm.simulate.cluster.cli import build_catalogue, validate_settings
    from mavispm.simulate.cluster.settings import ClusterSettings

    obj = settings if isinstance(settings, ClusterSettings) else validate_settings(settings)
    tables, attrs = build_catalogue(obj, seed)
    epochs = {}
    for name, table in tables.items():
        name = name.removeprefix("epochs/")
        checked = _validate_epoch(table, None, name)
        checked.meta["epoch"] = u.Quantity(table.meta["epoch"], u.yr)
        epochs[name] = checked
    order = sorted(epochs, key=lambda n: epochs[n].meta["epoch"].value)
    return Catalogue(epochs={n: epochs[n] for n in order}, attrs=dict(attrs))


def build_optics(
    settings: Mapping | OpticsSettings | None = None,
    cache_dir: str | os.PathLike | None = None,
    progress: bool = False,
) -> Optics:
    """The optics of a scene: PSF grid, seeing halo, tip-tilt, blur, distortion.

    Parameters
    ----------
    settings : mapping or OpticsSettings, optional
        The ``[scene.optics]`` table (docs/optics.md).
    cache_dir : path, optional
        PSF-grid cache folder (default ``$MAVISPM_CACHE`` or ``~/.cache/mavispm``).
    progress : bool
        Progress bar while a PSF grid is computed.

    Returns
    -------
    mavispm.simulate.optics.model.Optics
    """
    from mavispm.simulate.optics.model import OpticsSettings, validate_settings
    from mavispm.simulate.optics.model import build_optics as _build

    obj = settings if isinstance(settings, OpticsSettings) else validate_settings(settings)
    return _build(obj, cache_dir=cache_dir, progress=progress)


def render_epoch(
    catalogue: Catalogue | str | os.PathLike,
    epoch: str | int = 0,
    scene: Mapping | None = None,
    optics: Optics | None = None,
    seed: int = 0,
    renderer: StarRenderer | None = None,
) -> Frame:
    """Render one epoch of a catalogue into a stacked frame, in memory.

    Parameters
    ----------
    catalogue : Catalogue or path
        From :func:`simulate_cluster` or a ``catalogue`` product.
    epoch : str or int
        Epoch name ("e0", ...) or index in time order.
    scene : mapping or SceneSettings, optional
        The ``[scene]`` table (docs/render.md): exposure, detector, photometry,
        render knobs and ``optics``.
    optics : Optics, optional
        From :func:`build_optics` (default: built from ``scene["optics"]``);
        pass it to render several epochs with one PSF grid.
    seed : int
        Noise seed; epochs draw independent noise from (seed, epoch name), as
        ``mavispm simulate frames`` does.
    renderer : StarRenderer, optional
        Reuse cached PSF transforms across epochs
        (:func:`mavispm.simulate.render.frame.make_renderer`).

    Returns
    -------
    Frame
        The stack in electrons with its truth table and ``frames`` attributes;
        what :func:`measure_stars` takes.

    Examples
    --------
    A diffraction-limited 2 x 2 PSF grid (cached in a temporary folder) and
    the second epoch of a small catalogue on a 128 x 128 detector:

    >>> import tempfile, mavispm
    >>> cat = mavispm.simulate_cluster(
    ...     {"preset": "ngc3201", "n_stars": 50, "field_size": "2 arcsec", "epochs": [0, 5]})
    >>> optics = mavispm.build_optics(
    ...     {"psf": {"mode": "diffraction", "n_nodes": 2, "pupil_sampling": 32,
    ...              "stamp_size": "0.2 arcsec", "field_size": "2 arcsec"},
    ...      "halo": {"enabled": False}}, cache_dir=tempfile.mkdtemp())
    >>> frame = mavispm.render_epoch(
    ...     cat, "e1", {"nexp": 2, "detector": {"nx": 128, "ny": 128}}, optics, seed=3)
    >>> frame.shape, frame.epoch, frame.to_nddata().unit
    ((128, 128), <Quantity 5. yr>, Unit("adu"))
    """
    from mavispm.simulate.render import cli as render_cli
    from mavispm.simulate.render.frame import render_frame
    from mavispm.simulate.render.scene import SceneSettings, scene_from_mapping

    cat = catalogue if isinstance(catalogue, Catalogue) else read_catalogue(catalogue)
    if isinstance(epoch, int):
        names = list(cat.epochs)
        if not -len(names) <= epoch < len(names):
            raise InputError(f"epoch index {epoch} out of range; the catalogue has {names}")
        epoch = names[epoch]
    settings = scene if isinstance(scene, SceneSettings) else scene_from_mapping(scene)
    table, t = render_cli._select_epoch(cat, epoch)
    if optics is None:
        optics = render_cli.build_scene_optics(settings)
    frame = render_frame(
        table, t, settings, optics, render_cli.epoch_rng(seed, epoch), renderer=renderer
    )
    for key in ("distance", "ra_center", "dec_center"):
        if key in cat.attrs:
            frame.attrs[key] = cat.attrs[key]
    return frame
