"""Glue between the workflow graph and the real stage modules (docs/stages.md).

Each adapter turns the runner's uniform call
``run(inputs, settings, params, seed, outdir) -> {"main": path, ...}`` into the
stage's documented ``run_stage`` signature, and :func:`product_metrics` reads a
finished product's scalar attributes for summaries and sweep tables.

Every ``run_<stage>`` adapter takes the same arguments (numpydoc, shared):

Parameters
----------
inputs : dict of str to Path or list of Path
    Upstream products by input name ("catalogue", "psf", "frames", "measured",
    "propermotions", "truth", "truth_no_imbh").
settings : mapping
    The stage's TOML table.
params : mapping
    Node parameters (epoch, scene name, output switches).
seed : int or None
    The node's seed.
outdir : pathlib.Path
    Empty folder the products are written into.

Returns
-------
dict of str to Path
    Product name to path; "main" feeds the downstream stages.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mavispm.workflows.registry import StageRegistry, StageSpec, resolve

__all__ = [
    "KNOB_STAGES",
    "STAGE_MODULES",
    "UI_KEYS",
    "canonical_settings",
    "default_registry",
    "product_metrics",
    "run_calibration",
    "run_cluster",
    "run_dynamics",
    "run_frames",
    "run_optics",
    "run_propermotions",
    "run_stars",
]

_THIS = "mavispm.workflows.stages"

#: Stage -> (module of run_stage/validate_settings/write_report, code globs). The
#: globs cover the sub-packages the stage imports (each imports only core/ and,
#: for frames, the optics model); "!" drops code no product depends on.
STAGE_MODULES = {
    "cluster": ("mavispm.simulate.cluster.cli", ("simulate/cluster/*.py",)),
    "optics": (
        "mavispm.simulate.optics.cli",
        ("simulate/optics/*.py", "!simulate/optics/plots.py"),
    ),
    "calibration": (  # rendered hole images use the renderer and the star fitter
        "mavispm.simulate.optics.calibration_cli",
        (
            "simulate/optics/*.py",
            "!simulate/optics/plots.py",
            "simulate/render/*.py",
            "measure/stars/*.py",
        ),
    ),
    "frames": (
        "mavispm.simulate.render.cli",
        ("simulate/render/*.py", "simulate/optics/*.py", "!simulate/optics/plots.py"),
    ),
    "stars": ("mavispm.measure.stars.cli", ("measure/stars/*.py",)),
    "propermotions": (
        "mavispm.measure.propermotions.cli",
        ("measure/propermotions/*.py", "!measure/propermotions/report.py"),
    ),
    "dynamics": ("mavispm.dynamics.cli", ("dynamics/*.py",)),
}

#: Settings keys per stage that change neither results nor product data (not in keys).
UI_KEYS = {
    "frames": ("render.threads",),
    "stars": ("progress",),
    "dynamics": ("progress", "workers"),
}

#: Stages whose settings tables hold accuracy/speed knobs: their canonical spelling
#: (:func:`canonical_settings`) is hashed, so where a knob is written does not matter.
KNOB_STAGES = ("cluster", "optics", "frames", "stars", "propermotions", "dynamics")

#: Files every stage's key depends on (the shared product format).
COMMON_CODE = ("core/*.py",)


def default_registry() -> StageRegistry:
    """The registry of the real mavispm stages."""
    specs = []
    for name, (module, code) in STAGE_MODULES.items():
        specs.append(
            StageSpec(
                name=name,
                run=f"{_THIS}:run_{name}",
                validate=f"{module}:validate_settings",
                summarize=f"{_THIS}:product_metrics",
                report=f"{module}:write_report",
                code=COMMON_CODE + code,
                exclusive=name == "dynamics",  # draws plots with pyplot
                ui_keys=UI_KEYS.get(name, ()),
                canonical=f"{_THIS}:canonical_settings" if name in KNOB_STAGES else None,
            )
        )
    return StageRegistry.of(specs)


def _stage(name: str):
    return resolve(f"{STAGE_MODULES[name][0]}:run_stage")


def _scatter(settings: Mapping, stage: str) -> dict:
    from mavispm.core.knobs import scatter_knobs

    if stage == "cluster":
        from mavispm.simulate.cluster.settings import CLUSTER_KNOB_HOMES as homes
    elif stage == "optics":
        from mavispm.simulate.optics.model import OPTICS_KNOB_HOMES as homes
    elif stage == "stars":
        from mavispm.measure.stars.settings import KNOB_NAMES

        homes = {name: () for name in KNOB_NAMES}
    elif stage == "dynamics":
        from mavispm.dynamics.settings import DYNAMICS_KNOB_HOMES as homes
    else:
        from mavispm.measure.propermotions.settings import PM_KNOB_HOMES as homes
    return scatter_knobs(settings, homes)


def canonical_settings(settings: Mapping, stage: str) -> dict:
    """A stage's settings table with its knobs at their home keys (for cache keys).

    ``[cluster.knobs]`` entries go to ``[cluster.resolution]``, ``[scene.optics.knobs]``
    to ``[scene.optics.psf]`` (also inside a frames node's scene table), and those of
    ``[measure.knobs]``, ``[propermotions.knobs]`` and ``[dynamics.knobs]`` to flat keys: the spelling of
    workflows written before the knobs tables, whose keys therefore stay the same.

    Parameters
    ----------
    settings : mapping
        The stage's settings table, as written.
    stage : str
        Stage name (``cluster``, ``optics``, ``frames``, ``stars``, ``propermotions``).

    Returns
    -------
    dict
        The canonical table (a copy; other stages' tables are returned as given).
    """
    if stage == "frames":
        out = dict(settings)
        if isinstance(out.get("optics"), Mapping):
            out["optics"] = _scatter(out["optics"], "optics")
        return out
    if stage not in KNOB_STAGES:
        return dict(settings)
    return _scatter(settings, stage)


def run_cluster(
    inputs: Mapping, settings: Mapping, params: Mapping, seed: int | None, outdir: Path
) -> dict:
    """Cluster catalogue at the workflow's epochs (set as ``epochs`` in years).

    The ``[epochs]`` table owns the epochs (config refuses ``[cluster] epochs``);
    an external star list's path is already absolute and hashed as an input.

    Inputs: none used (an external star list is a setting).

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    settings = {**settings, "epochs": [float(t) for _, t in params["epochs"]]}
    out = _stage("cluster")(settings, outdir / "catalogue.h5", seed)
    return {"main": out}


def run_optics(
    inputs: Mapping, settings: Mapping, params: Mapping, seed: int | None, outdir: Path
) -> dict:
    """PSF grid (and seeing halo) of a scene's optics (``[scene.optics]``).

    The grid comes from, or is computed into, the optics module's disk cache of
    PSF grids keyed by their parameters, and is hard-linked (not copied) into the
    node's folder as ``psfgrid-<key>.h5`` (with the grids of the broadband slices,
    ``[scene.optics.broadband]``); the halo profile is kept beside it. The
    scene's frames nodes take this folder as their declared ``psf`` input.

    Inputs: none used.

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    from mavispm.simulate.optics.cli import validate_settings
    from mavispm.simulate.optics.model import build_optics

    s = validate_settings(dict(settings))
    built = build_optics(s, progress=False)
    source = built.cache_path
    main = Path(outdir) / source.name
    _link_or_copy(source, main)
    products = {"main": main}
    for k, path in enumerate(built.slice_cache_paths):  # broadband: a grid per wavelength
        products[f"slice_{k}"] = Path(outdir) / path.name
        _link_or_copy(path, products[f"slice_{k}"])
    build_optics(s, cache_dir=Path(outdir), progress=False)  # the halo beside the grid
    return products


def run_calibration(inputs, settings, params, seed, outdir: Path) -> dict:
    """Calibration mask of a scene (``[scenes.NAME.calibration]``): images the pinhole
    grid through the scene's distortion (``params["distortion"]``; rendered through the
    scene, ``params["scene"]``, when the mask's ``imaging`` is "rendered") and writes the
    recovered distortion; the scene's frames take it as their ``calibration`` input.

    Inputs: none used; products: ``main``.

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    out = _stage("calibration")(
        dict(settings),
        dict(params.get("distortion") or {}),
        outdir / "calibration.h5",
        seed,
        scene=params.get("scene"),
    )
    return {"main": out}


def _link_or_copy(source: Path, target: Path) -> None:
    """Hard-link ``source`` to ``target`` (a copy across file systems)."""
    import os
    import shutil

    try:
        os.link(source, target)
    except OSError:
        shutil.copyfile(source, target)


def run_frames(
    inputs: Mapping, settings: Mapping, params: Mapping, seed: int | None, outdir: Path
) -> dict:
    """Frames of one epoch of one scene (HDF5, plus FITS when ``[outputs] fits``).

    The optics are read from the scene's ``optics`` node (the declared ``psf``
    input: its PSF grid and halo); the stamp plans are cached in the optics
    module's disk cache, shared by the scene's epochs. A ``calibration`` input (the
    scene's calibration node) becomes ``[scene.optics.distortion] calibration``.

    Inputs: ``catalogue``, ``psf`` (the optics node's grid), optional ``calibration``;
    products: ``main``, ``fits``.

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    scene = dict(settings)
    if "calibration" in inputs:  # the post-calibration residual distortion
        optics = dict(scene.get("optics") or {})
        optics["distortion"] = {
            **dict(optics.get("distortion") or {}),
            "calibration": str(inputs["calibration"]),
        }
        scene["optics"] = optics
    fits = outdir / "frames.fits" if params.get("fits", True) else None
    kwargs = {}
    if "psf" in inputs:
        from mavispm.simulate.optics.psf_grid import default_cache_dir
        from mavispm.simulate.render import cli as render_cli
        from mavispm.simulate.render.frame import make_renderer

        settings_obj = render_cli.scene_from_mapping(scene)
        optics = render_cli.build_scene_optics(settings_obj, Path(inputs["psf"]).parent)
        kwargs["optics"] = optics
        kwargs["renderer"] = make_renderer(optics, settings_obj, default_cache_dir())
    out = _stage("frames")(
        inputs["catalogue"],
        params["epoch"],
        scene,
        outdir / "frames.h5",
        seed,
        fits_path=fits,
        **kwargs,
    )
    products = {"main": out}
    if fits is not None and Path(fits).is_file():
        products["fits"] = fits
    return products


def run_stars(
    inputs: Mapping, settings: Mapping, params: Mapping, seed: int | None, outdir: Path
) -> dict:
    """Measured stars of one frame (observer mode: started from the ``earlier``
    epochs' measured products when the graph gives them).

    Inputs: ``frames``, optional ``earlier`` (list of measured products), optional
    ``psf_prior`` (the scene's optics product: the PSF-R prior, docs/measure.md).

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    earlier = list(inputs.get("earlier") or ())
    prior = inputs.get("psf_prior")
    out = _stage("stars")(
        inputs["frames"],
        dict(settings),
        outdir / "measured.h5",
        seed,
        earlier=earlier,
        psf_prior=Path(prior) if prior else None,
    )
    return {"main": out}


def run_propermotions(
    inputs: Mapping, settings: Mapping, params: Mapping, seed: int | None, outdir: Path
) -> dict:
    """Proper motions from the measured catalogues of all epochs.

    The true motions come from the catalogue (``truth``). When ``[propermotions]``
    sets no ``distance``, the catalogue's distance is used, so the product carries
    the distance the dynamics stage needs (measured products do not copy it).

    Inputs: ``measured`` (list), ``truth`` (catalogue).

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    settings = dict(settings)
    if "truth" in inputs and settings.get("distance") is None:
        settings["distance"] = _catalogue_distance(inputs["truth"])
    out = _stage("propermotions")(
        list(inputs["measured"]),
        settings,
        outdir / "propermotions.h5",
        truth=inputs.get("truth"),
    )
    return {"main": out}


def _catalogue_distance(path) -> str | None:
    """The catalogue product's distance as a quantity string ("4.6 kpc"), or None."""
    from mavispm.core.products import read_product

    distance = read_product(path, "catalogue", load_arrays=False).attrs.get("distance")
    return None if distance is None else f"{float(distance.to_value('kpc'))!r} kpc"


def run_dynamics(
    inputs: Mapping, settings: Mapping, params: Mapping, seed: int | None, outdir: Path
) -> dict:
    """Dynamical fit and IMBH model comparison (plots in ``plots/``).

    Inputs: ``propermotions``, optional ``truth``, ``truth_no_imbh``, ``artificial_stars``
    (the variant's own catalogue, with ``completeness_source = "artificial_stars"``); products: ``main`` and ``plot_<name>`` per PNG.

    Parameters
    ----------
    inputs : dict of str to Path or list of Path
        Upstream products by input name.
    settings : mapping
        The stage's TOML table.
    params : mapping
        Node parameters (epoch, scene name, output switches).
    seed : int or None
        The node's seed.
    outdir : pathlib.Path
        Empty folder the products are written into.

    Returns
    -------
    dict of str to Path
        Product name to path; "main" feeds the downstream stages.
    """
    plots = outdir / "plots" if params.get("plots", True) else None
    out = _stage("dynamics")(
        inputs["propermotions"],
        # the runner draws its own bars; the sampler's only when the workflow asks
        {"progress": False, **dict(settings)},
        outdir / "dynamics.h5",
        seed,
        plots_dir=plots,
        truth=inputs.get("truth"),
        truth_no_imbh=inputs.get("truth_no_imbh"),
        artificial_stars=inputs.get("artificial_stars"),
    )
    products = {"main": out}
    if plots is not None and plots.is_dir():
        for png in sorted(plots.glob("*.png")):
            products[f"plot_{png.stem}"] = png
    return products


#: Root attributes that are provenance, not results.
_PROVENANCE = {"seed", "format_version", "format", "kind", "mavispm_version", "created", "config"}


def product_metrics(products: Mapping[str, Path]) -> dict:
    """Scalar results of a product: numeric root attributes and table row counts.

    Parameters
    ----------
    products : mapping of str to Path
        The node's products; only ``main`` (an HDF5 product) is read.

    Returns
    -------
    dict
        ``attr`` -> float for every finite scalar numeric root attribute (units
        dropped; see the product's documentation), ``n_<table>`` -> row count.
    """
    import h5py

    main = Path(products["main"])
    if main.suffix not in (".h5", ".hdf5"):
        return {}
    out: dict = {}
    with h5py.File(main, "r") as f:
        for key, value in f.attrs.items():
            if key in _PROVENANCE or key.endswith("__unit"):
                continue
            arr = np.asarray(value)
            if arr.ndim == 0 and arr.dtype.kind in "iuf" and np.isfinite(arr):
                out[key] = arr.item()

        def visit(name, obj):
            if obj.attrs.get("mavispm_table", False):  # a table (dataset, or v1 group)
                out[f"n_{name.replace('/', '_')}"] = int(obj.attrs.get("nrows", 0))

        f.visititems(visit)
    return out
