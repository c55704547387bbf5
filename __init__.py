"""mavispm: MAVIS multi-conjugate adaptive optics proper-motion pipeline.

Simulate MCAO images of star clusters as MAVIS (VLT) will take them, measure them,
turn epochs into proper motions and fit dynamical models to test for an
intermediate-mass black hole.

The stage entry points are available here, imported on first use (see
:mod:`mavispm.api` and the README's "Python API" section)::

    import mavispm
    cat = mavispm.simulate_cluster({...}, seed=1)        # Catalogue of QTables
    optics = mavispm.build_optics({...})                 # PSF grid, tip-tilt, ...
    frame = mavispm.render_epoch(cat, "e0", scene, optics)  # Frame
    stars, psf = mavispm.measure_stars(frame)            # QTable
    pm = mavispm.proper_motions([stars0, stars1])        # QTable
    fit = mavispm.fit_dynamics(pm)                       # DynamicsResult

Sub-packages
------------
core      data formats (HDF5 products), the Frame type, units, errors, atomic writes
simulate  cluster catalogues and epochs (cluster/), optics (optics/), rendering (render/)
measure   stars: ePSF building and PSF fitting; propermotions: matching, alignment, motions
dynamics  dispersion profiles, Jeans models, emcee fits, IMBH model comparison
workflows the runner, CLI and configuration
"""

__version__ = "0.1.0"

#: Public name -> module that defines it (imported lazily by :func:`__getattr__`).
_LAZY = {
    "simulate_cluster": "mavispm.api",
    "build_optics": "mavispm.api",
    "render_epoch": "mavispm.api",
    "measure_stars": "mavispm.api",
    "proper_motions": "mavispm.api",
    "fit_dynamics": "mavispm.api",
    "read_catalogue": "mavispm.api",
    "read_frame": "mavispm.api",
    "Catalogue": "mavispm.api",
    "Frame": "mavispm.api",
    "DynamicsResult": "mavispm.api",
    "read_table": "mavispm.core.products",
    "export_table": "mavispm.core.products",
}

__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    """Import a stage entry point on first use (keeps ``import mavispm`` fast)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mavispm' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
