"""Load ``scipy.linalg.cython_blas`` without the ``scipy.linalg`` package (program start-up).

Importing numba runs ``numba.np.arraymath``, whose module-level BLAS check imports
``scipy.linalg.cython_blas``: the whole ``scipy.linalg`` package (its ``__init__``
imports ``scipy._lib._array_api``, which reaches ``numpy.f2py`` and
``charset_normalizer``): 0.1-0.2 s of CPU of every ``mavispm`` process that uses a
compiled kernel, ~5 % of a 3,500-star ``simulate frames`` process. numba needs only the
extension module itself (its C function pointers, ``__pyx_capi__``).
:func:`load_cython_blas_alone` loads that extension module on its own under its full
name, so numba's import finds it in ``sys.modules``; a later ``import scipy.linalg``
(in a process that needs it) imports the package as usual and gets the same extension
module as its ``cython_blas`` attribute.

Only the ``mavispm`` program calls it (``workflows/cli.py``: ``main()`` reading
``sys.argv``), before the command's modules are imported; library callers are not
affected.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import sys
from pathlib import Path

from mavispm.core.import_hook import wrap_on_import

__all__ = ["load_cython_blas_alone"]

_NAME = "scipy.linalg.cython_blas"


def _link(exec_module, module) -> None:
    """Run ``scipy.linalg``'s code, then set the preloaded ``cython_blas`` on it.

    The import system sets a submodule as an attribute of its package only when it
    loads the submodule itself; the preloaded one is linked here instead.
    """
    exec_module(module)
    if _NAME in sys.modules and not hasattr(module, "cython_blas"):
        module.cython_blas = sys.modules[_NAME]


def load_cython_blas_alone() -> bool:
    """Load ``scipy.linalg.cython_blas`` into ``sys.modules`` without ``scipy.linalg``.

    Does nothing when numba, ``scipy.linalg`` or the module itself is already imported,
    or when the extension module is not found (numba then imports it as usual).

    Returns
    -------
    bool
        Whether the module was loaded here.
    """
    if _NAME in sys.modules or "scipy.linalg" in sys.modules or "numba" in sys.modules:
        return False
    spec = importlib.util.find_spec("scipy")  # locates the package without importing it
    if spec is None or not spec.submodule_search_locations:
        return False
    folder = Path(next(iter(spec.submodule_search_locations))) / "linalg"
    paths = [folder / f"cython_blas{s}" for s in importlib.machinery.EXTENSION_SUFFIXES]
    path = next((p for p in paths if p.is_file()), None)
    if path is None:
        return False
    loader = importlib.machinery.ExtensionFileLoader(_NAME, str(path))
    ext_spec = importlib.util.spec_from_file_location(_NAME, path, loader=loader)
    try:
        module = importlib.util.module_from_spec(ext_spec)
        sys.modules[_NAME] = module
        loader.exec_module(module)
    except Exception:  # an unusual build: leave it to numba's own import
        sys.modules.pop(_NAME, None)
        return False
    wrap_on_import("scipy.linalg", _link)
    return True
